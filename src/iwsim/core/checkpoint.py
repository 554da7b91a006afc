"""Checkpoints: safetensors + JSON directories, written atomically, never pickle.

Layout of a run directory's checkpoints::

    checkpoints/<step:08d>/model.safetensors        weights people load (the EMA weights)
    checkpoints/<step:08d>/config.json              the resolved config of the run
    checkpoints/<step:08d>/training_state/          raw weights, optimizer state, step
    checkpoints/last -> <step:08d>                  symlink to the newest whole checkpoint

A checkpoint is written under a temporary name and renamed into place, and ``last`` is
replaced atomically afterwards, so a crash never leaves ``last`` pointing at a partial one.

A model directory (a checkpoint, or a standalone export) holds ``model.safetensors`` and a
``config.json`` whose ``kind`` says what it holds; :func:`load_model_dir` reads one of a
given kind, and every model class loads through it.
"""

from __future__ import annotations

import errno
import json
import os
import shutil
from collections.abc import Callable, Iterator
from itertools import chain
from pathlib import Path
from typing import Any, NoReturn, Protocol, TypeVar

import numpy as np
import torch
from safetensors import SafetensorError
from safetensors.torch import load_file, save_file

from iwsim.core.errors import InputError, IwsimError
from iwsim.core.resources import human_bytes, read_capped, require_memory

# What each ``config.json`` kind holds, for messages.
KINDS = {"autoencoder": "an autoencoder", "world_model": "a world model", "policy": "a policy"}
PROJECT_ROOT = Path(__file__).resolve().parents[3]  # the checkout the package is installed from (editable)


class CheckpointError(IwsimError, ValueError):
    """A checkpoint that is missing, incomplete or corrupt (a ValueError too, as it always was)."""


def write_text_atomic(path: Path, text: str) -> None:
    """Write ``text`` to a temporary name next to ``path``, then rename it into place."""
    tmp = path.with_name(f".{path.name}.tmp")
    tmp.write_text(text)
    os.replace(tmp, path)


def write_json_atomic(path: Path, obj: Any, sort_keys: bool = True) -> None:
    write_text_atomic(path, json.dumps(obj, indent=2, sort_keys=sort_keys) + "\n")


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


# The mode a file this process creates gets (0666 less the umask; read once, at import,
# before any thread runs: reading the umask sets it for a moment).
FILE_MODE = 0o666 & ~_umask()


def save_tensors(tensors: dict[str, torch.Tensor], path: Path, metadata: dict[str, str] | None = None) -> None:
    """``safetensors`` ``save_file``, with a failed write (e.g. a full disk) an OSError
    naming ``path`` instead of a SafetensorError, and no partial file left behind. The
    file gets the mode every other file gets (``save_file`` itself writes 0600, so weights
    would be unreadable to the group and others who can read the ``config.json`` beside)."""
    try:
        save_file({k: v.detach().cpu().contiguous() for k, v in tensors.items()}, path, metadata=metadata)
        os.chmod(path, FILE_MODE)
    except SafetensorError as e:
        Path(path).unlink(missing_ok=True)
        full = "StorageFull" in str(e) or "os error 28" in str(e)
        raise OSError(errno.ENOSPC if full else errno.EIO,
                      os.strerror(errno.ENOSPC) if full else " ".join(str(e).split())[:200], str(path)) from None


def load_tensors(path: Path) -> dict[str, torch.Tensor]:
    """Read a safetensors file, or raise CheckpointError naming it."""
    if not path.is_file():
        raise CheckpointError(f"checkpoint file {path} is missing.")
    try:
        return load_file(path)
    except (SafetensorError, OSError, ValueError) as e:
        raise CheckpointError(f"checkpoint file {path} is unreadable (truncated or corrupt): {e}.") from None


JSON_MAX_BYTES = 64 << 20  # a checkpoint's config or state is far smaller


def load_json(path: Path, what: str = "checkpoint file") -> dict[str, Any]:
    """The JSON file at ``path`` (read with a cap), or one line of error calling it ``what``."""
    if not os.path.lexists(path):
        raise CheckpointError(f"{what} {path} is missing.")
    try:
        return json.loads(read_capped(path, JSON_MAX_BYTES, CheckpointError))
    except FileNotFoundError:
        raise CheckpointError(f"{what} {path} is missing.") from None
    except UnicodeDecodeError:
        raise CheckpointError(f"{what} {path} is not UTF-8 text.") from None
    except json.JSONDecodeError as e:
        raise CheckpointError(f"{what} {path} is not valid JSON: {e}.") from None


class Weighted(Protocol):
    """A network as build_within_memory counts it (an nn.Module, or a Codec)."""

    def parameters(self, recurse: bool = True) -> Iterator[torch.nn.Parameter]: ...

    def buffers(self, recurse: bool = True) -> Iterator[torch.Tensor]: ...


M = TypeVar("M", bound=Weighted)


def build_within_memory(make: Callable[[], M], what: str) -> M:
    """``make()``, a network from a config that may come from a file, once its weights are
    known to fit: it is first built on the meta device (nothing allocated) to count them.
    A config that cannot be built is a CheckpointError, one that would not fit a
    ResourceError; both one line naming ``what``.

    Any arithmetic on the meta device runs through torch's reference ops, whose first use
    imports torch._dynamo (about 2 s a process): a constructor's tables of constants are
    therefore made on the CPU (``device="cpu"``, or from NumPy values)."""
    try:
        with torch.device("meta"):
            probe = make()
    except (RuntimeError, ValueError, TypeError, OverflowError, MemoryError) as e:
        raise CheckpointError(f"{what} does not describe a network that can be built: "
                              f"{' '.join(str(e).split())[:200]}") from None
    need = sum(t.numel() * t.element_size() for t in chain(probe.parameters(), probe.buffers()))
    require_memory(2 * need, f"{what} ({human_bytes(need)} of weights, held twice while loading)")
    return make()


def locate(path: str | os.PathLike[str]) -> Path:
    """``path``; or, when it is relative and missing from the working directory, the same
    path in the project's checkout if it is there (the shipped ``checkpoints/`` are found
    from any working directory)."""
    path = Path(path)
    if not path.is_absolute() and not path.exists() and (PROJECT_ROOT / path).exists():
        return PROJECT_ROOT / path
    return path


def _where(path: Path) -> str:
    """What a missing relative path was looked up against, for an error message."""
    return "" if path.is_absolute() else f" (a relative path: looked for in {Path.cwd()} and {PROJECT_ROOT})"


def load_model_dir(path: str | Path, kind: str) -> tuple[dict[str, Any], dict[str, torch.Tensor]]:
    """The ``config.json`` and the tensors of the model directory ``path`` (:func:`locate`),
    whose config must say ``kind`` (one of :data:`KINDS`); a CheckpointError naming the
    file otherwise."""
    path = locate(path)
    if not path.is_dir():
        raise CheckpointError(f"{path} is not a checkpoint directory (model.safetensors + config.json){_where(path)}.")
    config = load_json(path / "config.json")
    if not isinstance(config, dict) or not isinstance(config.get("kind"), str):
        raise CheckpointError(f"{path} is not an iwsim checkpoint: its config.json is not a JSON object with a "
                              f"'kind'; expected {KINDS.get(kind, repr(kind))}.")
    found = config["kind"]
    if found != kind:
        raise CheckpointError(f"{path} is a {found!r} checkpoint, not {KINDS.get(kind, repr(kind))}.")
    tensors = load_tensors(path / "model.safetensors")
    check_finite(tensors, path / "model.safetensors")
    return config, tensors


def check_finite(tensors: dict[str, torch.Tensor], where: Path) -> None:
    """Refuse weights that hold NaN or infinite values (a run that diverged, a damaged
    file): a model made of them runs, but everything it computes is garbage."""
    for name, t in tensors.items():
        if t.is_floating_point() and not bool(torch.isfinite(t).all()):
            raise CheckpointError(f"{where}: tensor {name!r} holds NaN or infinite values; the checkpoint is broken "
                                  "(e.g. saved from a run whose weights diverged) and is not used.")


def check_finite_output(value: torch.Tensor | np.ndarray, model: str, output: str) -> None:
    """Refuse a model's output that holds NaN or infinite values (``model`` and ``output``
    name them): with finite weights, a computation that overflows (weights trained far out
    of range, a latent scale of 0), whose every later step would be garbage."""
    ok = bool(torch.isfinite(value).all()) if isinstance(value, torch.Tensor) else bool(np.isfinite(value).all())
    if not ok:
        raise CheckpointError(f"{model} gave NaN or infinite values in {output} although its weights are finite "
                              "(the computation overflows); it cannot be used.")


def same_weights(a: torch.nn.Module, b: torch.nn.Module) -> bool:
    """Whether two networks hold the same tensors (names, shapes and values), wherever they
    were loaded from: what identifies a model, not its path."""
    sa, sb = a.state_dict(), b.state_dict()
    return sa.keys() == sb.keys() and all(sa[k].shape == sb[k].shape and torch.equal(sa[k], sb[k]) for k in sa)


def resolve_checkpoint(path: str | Path) -> Path:
    """A checkpoint directory, or a run directory (its ``checkpoints/last``); relative
    paths as :func:`locate` finds them."""
    path = locate(path)
    if (path / "model.safetensors").is_file():
        return path
    last = last_checkpoint(path / "checkpoints")
    if last is None:
        where = _where(path) if not path.exists() else ""
        raise CheckpointError(f"{path} is neither a checkpoint directory (model.safetensors + config.json) "
                              f"nor a run directory with checkpoints{where}.")
    return last


def check_output_dir(path: str | os.PathLike, flag: str = "--out") -> None:
    """A directory a command writes its report into is absent, or a directory that is
    neither an episode store nor a model checkpoint or run: results written into those
    would mix with (or overwrite) what another command wrote. Checked before any work."""
    path = Path(path)
    if not path.exists():
        return
    if not path.is_dir():
        raise InputError(f"{flag} {path} is a file; expected a directory (it is created if missing).")
    if (path / ".zgroup").is_file() or (path / "meta" / "episode_ends").exists():
        what = "an episode store"
    elif (path / "model.safetensors").is_file() or (path / "checkpoints").is_dir():
        what = "a model checkpoint or training run"
    else:
        return
    raise InputError(f"{flag} {path} is {what}; give the report a directory of its own.")


def named_checkpoints(items: list[str], flag: str = "--models") -> dict[str, str]:
    """``NAME=CHECKPOINT`` items (a checkpoint, or a run: its last) -> {name: checkpoint
    path}, in order, for the scripts that compare models; one line of error for an item
    without a name, or with a name given before (its row would silently be one)."""
    named: dict[str, str] = {}
    for item in items:
        name, sep, path = item.partition("=")
        if not sep or not name:
            raise InputError(f"{flag} takes NAME=CHECKPOINT, got {item!r}.")
        if name in named:
            raise InputError(f"{flag} names {name!r} twice ({named[name]} and {path}); give each model its own name.")
        named[name] = str(resolve_checkpoint(path))
    return named


def optimizer_to_tensors(opt: torch.optim.Optimizer) -> tuple[dict[str, torch.Tensor], dict[str, Any]]:
    """Split an optimizer's state_dict into tensors (for safetensors) and JSON metadata."""
    sd = opt.state_dict()
    tensors, scalars = {}, {}
    for pid, state in sd["state"].items():
        for k, v in state.items():
            if torch.is_tensor(v):
                tensors[f"{pid}.{k}"] = v.contiguous()
            else:
                scalars[f"{pid}.{k}"] = v
    return tensors, {"param_groups": sd["param_groups"], "scalars": scalars}


def optimizer_from_tensors(opt: torch.optim.Optimizer, tensors: dict[str, torch.Tensor], meta: dict[str, Any]) -> None:
    state: dict[int, dict[str, Any]] = {}
    for key, v in tensors.items():
        pid, k = key.split(".", 1)
        state.setdefault(int(pid), {})[k] = v
    for key, v in meta["scalars"].items():
        pid, k = key.split(".", 1)
        state.setdefault(int(pid), {})[k] = v
    opt.load_state_dict({"state": state, "param_groups": meta["param_groups"]})


def save_checkpoint(root: Path, step: int, model: dict[str, torch.Tensor], config: dict[str, Any],
                    training_tensors: dict[str, dict[str, torch.Tensor]], training_meta: dict[str, Any]) -> Path:
    """Write ``root/<step:08d>`` atomically and point ``root/last`` at it.

    ``training_tensors`` maps a file stem to tensors (e.g. ``{"model": ..., "optimizer": ...}``),
    each written to ``training_state/<stem>.safetensors``; ``training_meta`` goes to
    ``training_state/state.json``.
    """
    root.mkdir(parents=True, exist_ok=True)
    final = root / f"{step:08d}"
    tmp = root / f".{step:08d}.tmp"
    shutil.rmtree(tmp, ignore_errors=True)
    try:
        (tmp / "training_state").mkdir(parents=True)
        save_tensors(model, tmp / "model.safetensors")
        write_json_atomic(tmp / "config.json", config)
        for stem, tensors in training_tensors.items():
            save_tensors(tensors, tmp / "training_state" / f"{stem}.safetensors")
        write_json_atomic(tmp / "training_state" / "state.json", {**training_meta, "step": step})
    except OSError as e:  # e.g. a full disk: the checkpoints already written stay as they are
        shutil.rmtree(tmp, ignore_errors=True)
        last = last_checkpoint(root) if (root / "last").is_symlink() else None
        raise OSError(f"cannot write checkpoint {final.name} of {root.parent}: {e.strerror or e}; rerunning the "
                      f"command resumes from {'the start' if last is None else 'step ' + str(int(last.name))}"
                      ) from None
    if final.exists():
        shutil.rmtree(final)
    os.replace(tmp, final)
    link_tmp = root / ".last.tmp"
    link_tmp.unlink(missing_ok=True)
    os.symlink(final.name, link_tmp)
    os.replace(link_tmp, root / "last")
    return final


MODEL_DIR_EXTRAS = ("README.md", "metrics.json")  # what iwsim writes beside a checkpoint's model and config


def _check_replaceable(path: Path, ours: set[str], kind: Any) -> None:
    """Refuse to replace ``path`` unless it is a checkpoint directory iwsim wrote of the
    same ``kind`` as the new one (a world model never replaces a policy): a ``config.json``
    of that kind and nothing but the files a checkpoint holds."""
    def refuse(why: str) -> NoReturn:
        raise FileExistsError(f"{path} {why}; --force replaces only a checkpoint directory iwsim wrote, "
                              "choose another --out.")

    if path.is_symlink() or not path.is_dir():
        refuse("is not a directory")
    try:
        config = load_json(path / "config.json")
    except (OSError, ValueError):  # CheckpointError too
        config = None
    if not isinstance(config, dict) or config.get("kind") not in KINDS:
        refuse("is not an iwsim checkpoint (no config.json of a known kind)")
    if config["kind"] != kind:
        refuse(f"is {KINDS[config['kind']]}, not {KINDS.get(kind, repr(kind))}")
    others = sorted(e.name for e in path.iterdir() if e.name not in ours or not e.is_file() or e.is_symlink())
    if others:
        refuse(f"holds what a checkpoint does not ({', '.join(others[:3])}{', ...' if len(others) > 3 else ''})")


def save_model_dir(path: Path, tensors: dict[str, torch.Tensor], config: dict[str, Any], force: bool = False,
                   json_files: dict[str, Any] | None = None) -> Path:
    """Write a standalone checkpoint directory (``model.safetensors`` + ``config.json``
    and any ``json_files``) atomically. An existing directory is replaced only with
    ``force``, only if it is a checkpoint directory iwsim wrote of the same kind (nothing
    else in it), and only once the new one is complete; what this call does not write (a
    ``README.md``, a ``metrics.json`` beside the weights) is kept, not deleted."""
    path = Path(path)
    if path.exists() and not force:
        raise FileExistsError(f"{path} already exists; choose another --out or pass --force to replace it.")
    if path.exists():
        _check_replaceable(path, {"model.safetensors", "config.json", *MODEL_DIR_EXTRAS, *(json_files or {})},
                           config.get("kind"))
    path.parent.mkdir(parents=True, exist_ok=True)
    full = path.resolve()  # a name to put the temporary directories beside (also for ".")
    tmp = full.with_name(f".{full.name}.tmp")
    shutil.rmtree(tmp, ignore_errors=True)
    tmp.mkdir()
    try:
        save_tensors(tensors, tmp / "model.safetensors")
        write_json_atomic(tmp / "config.json", config)
        for name, obj in (json_files or {}).items():
            write_json_atomic(tmp / name, obj)
    except OSError:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    if path.exists():
        for name in MODEL_DIR_EXTRAS:  # written by someone else (a person, a ship script): carried over
            if (path / name).is_file() and not (tmp / name).exists():
                shutil.copy2(path / name, tmp / name)
        old = full.with_name(f".{full.name}.old")
        shutil.rmtree(old, ignore_errors=True)
        os.replace(path, old)
        os.replace(tmp, path)
        shutil.rmtree(old)
    else:
        os.replace(tmp, path)
    return path


def resume_candidates(root: Path) -> list[Path]:
    """Checkpoints a run may resume from, newest first: the one ``root/last`` names (even if
    it is gone), then every older ``<step:08d>`` directory; empty without ``last``."""
    link = root / "last"
    if not link.is_symlink():
        return [] if not link.exists() else [link.resolve()]
    newest = root / os.readlink(link)
    try:
        newest_step = int(newest.name)
    except ValueError:
        return [newest]
    older = sorted((p for p in root.iterdir() if p.name.isdigit() and len(p.name) == 8 and p.is_dir()
                    and int(p.name) < newest_step), key=lambda p: int(p.name), reverse=True)
    return [newest, *older]


def last_checkpoint(root: Path) -> Path | None:
    """The directory ``root/last`` points at, or None when there is none yet."""
    link = root / "last"
    if not link.is_symlink() and not link.exists():
        return None
    target = link.resolve()
    if not target.is_dir():
        raise CheckpointError(f"{link} points at {target}, which is not a checkpoint directory.")
    return target
