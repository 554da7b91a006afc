"""The one training loop every stage uses.

A stage supplies a :class:`TrainTask`: a module whose ``forward(batch)`` returns the loss,
a way to build this rank's share of step k's batch, an evaluation and an export. The loop
does the rest: AdamW with linear warm-up, gradient clipping, EMA weights, bf16 autocast on
CUDA (and on the CPU with ``cpu_bf16``, where the CPU has the instructions:
:func:`training_precision`), optionally ``torch.compile`` of the module's networks, DDP
under torchrun, periodic evaluation and atomic checkpoints, logging to ``log.txt`` and
``metrics.jsonl`` (each training row names the numeric path it took), and exact resumption.

Exact resumption without saving RNG states: everything random at step k (which samples,
which noise) is drawn from a generator seeded by (seed, k) for the *global* batch, of
which each rank takes its slice. So a resumed run, a single process and K ranks with the
same global batch all see the same data at every step (EDM2 does the same with
per-sample seeds).
"""

from __future__ import annotations

import contextlib
import copy
import json
import logging
import math
import os
import shutil
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any, Protocol, TypeVar

import torch
from torch import nn
from torch.nn.parallel import DistributedDataParallel
from tqdm import tqdm

from iwsim.core import distributed
from iwsim.core.checkpoint import (
    CheckpointError,
    last_checkpoint,
    load_json,
    load_tensors,
    optimizer_from_tensors,
    optimizer_to_tensors,
    resume_candidates,
    save_checkpoint,
    write_json_atomic,
)
from iwsim.core.config import TrainConfig
from iwsim.core.errors import InputError, IwsimError
from iwsim.core.lock import DirLock, LockedError
from iwsim.core.precision import Precision, bf16_available, cpu_info
from iwsim.core.resources import MiB, human_bytes, require_memory

log = logging.getLogger(__name__)


class TrainingError(IwsimError):
    """Training cannot go on (e.g. the loss became non-finite)."""


M = TypeVar("M", bound=nn.Module)


class TrainTask(Protocol[M]):
    """What a stage gives the loop; ``M``: the class of its module."""

    @property
    def module(self) -> M: ...  # forward(batch) -> (loss, {name: float})

    def batch(self, step: int, generator: torch.Generator, part: slice, device: torch.device) -> Any:
        """This rank's ``part`` of step ``step``'s global batch; draw everything random
        for the whole global batch from ``generator`` first, then slice."""

    def evaluate(self, module: M, step: int, out_dir: Path) -> dict[str, float]:
        """Score ``module`` (the EMA weights) on held-out data; may write files to out_dir."""

    def export(self, module: M) -> dict[str, torch.Tensor]:
        """The tensors of ``model.safetensors`` (what users load) from ``module``."""


def step_generator(seed: int, step: int) -> torch.Generator:
    """The generator of everything random at ``step``."""
    return torch.Generator().manual_seed(seed * 1_000_003 + step)


# Top-level config entries that describe a run without changing its training, added to
# iwsim after runs were started (a world model's "task"): a run whose config lacks one
# resumes, and its config gains it.
ADDED_DESCRIPTIONS = ("task",)
# Training fields a resume may change: ``steps`` (training longer is a resume) and
# ``checkpoint_every`` (how often a run saves does not change its weights: every step's
# randomness is drawn from its own generator, step_generator).
RESUMABLE_CHANGES = ("steps", "checkpoint_every")


def prepare_run_dir(run_dir: Path, config: dict[str, Any], force: bool = False,
                    complete: Callable[[dict[str, Any]], dict[str, Any]] | None = None) -> None:
    """Create ``run_dir`` with ``config.json``, or check that an existing one holds the
    same config (so rerunning the same command resumes). ``train.steps`` and
    ``train.checkpoint_every`` may differ (:data:`RESUMABLE_CHANGES`). ``force`` overwrites
    a different config. ``complete`` fills a stored config with the defaults of fields
    added to iwsim since (as loading the run reads it), so that a run started before a new
    field resumes."""
    run_dir.mkdir(parents=True, exist_ok=True)
    path = run_dir / "config.json"
    if path.exists():
        old = load_json(path)
        if complete is not None:
            old = json.loads(json.dumps(complete(old)))
        config = json.loads(json.dumps(config))  # tuples -> lists, as read back

        def comparable(c: Any) -> Any:  # the config without the train fields a resume may change
            if not isinstance(c, dict):
                return c
            return {k: ({kk: vv for kk, vv in v.items() if kk not in RESUMABLE_CHANGES}
                        if k == "train" and isinstance(v, dict) else comparable(v)) for k, v in c.items()}

        # compared without the descriptions the old config predates
        new = {k: v for k, v in config.items() if k in old or k not in ADDED_DESCRIPTIONS}
        old, new = data_by_content(old, new)
        if comparable(old) != comparable(new):
            diff = sorted(_diff_keys(comparable(old), comparable(new)))
            if not force:
                raise InputError(
                    f"{run_dir} holds a run with a different config (differs in {', '.join(diff)}); "
                    "use another --out, or --force to train it with the new config."
                )
            # --force starts over: the old run's checkpoints, metrics and evaluations were
            # trained with the old config, and resuming from them would mix the two
            log.warning("%s: --force with a different config (%s): starting over, removing the old run's "
                        "checkpoints, metrics and evaluations", run_dir, ", ".join(diff))
            for name in ("checkpoints", "eval"):
                shutil.rmtree(run_dir / name, ignore_errors=True)
            (run_dir / "metrics.jsonl").unlink(missing_ok=True)
    write_json_atomic(path, config)


def data_by_content(old: dict[str, Any], new: dict[str, Any]) -> tuple[dict[str, Any], dict[str, Any]]:
    """Two configs' ``data`` sources made comparable by what they hold: where every source
    of both records its content hash (``sha256``), without their paths (a store moved, or
    reached by another path, is the same data; so are the episode counts by path that
    describe it, ``episodes_used``); else, a run from before the hashes, by path."""
    a, b = old.get("data"), new.get("data")
    if not (isinstance(a, list) and isinstance(b, list) and all(isinstance(d, dict) for d in a + b)):
        return old, new
    if not all("sha256" in d for d in a + b):
        return ({**old, "data": [{k: v for k, v in d.items() if k != "sha256"} for d in a]},
                {**new, "data": [{k: v for k, v in d.items() if k != "sha256"} for d in b]})

    def by_content(c: dict[str, Any]) -> dict[str, Any]:
        return {**{k: v for k, v in c.items() if k != "episodes_used"},
                "data": [{k: v for k, v in d.items() if k != "path"} for d in c["data"]]}
    return by_content(old), by_content(new)


def _diff_keys(a: Any, b: Any, prefix: str = "") -> set[str]:
    if isinstance(a, dict) and isinstance(b, dict):
        out: set[str] = set()
        for k in set(a) | set(b):
            out |= _diff_keys(a.get(k), b.get(k), f"{prefix}{k}.")
        return out
    return set() if a == b else {prefix.rstrip(".")}


def _truncate_metrics(path: Path, step: int) -> None:
    """Drop rows logged after the checkpoint a run resumes from (they will be redone)."""
    if path.exists():
        rows = [line for line in path.read_text().splitlines() if line and json.loads(line)["step"] <= step]
        tmp = path.with_name(f".{path.name}.tmp")
        tmp.write_text("".join(f"{r}\n" for r in rows))
        os.replace(tmp, path)


def _lr(cfg: TrainConfig, step: int) -> float:
    """Linear warm-up, then constant or a cosine decay to 0 at ``cfg.steps``."""
    if step < cfg.warmup_steps:
        return cfg.lr * (step + 1) / cfg.warmup_steps
    if cfg.lr_decay == "constant":
        return cfg.lr
    progress = (step - cfg.warmup_steps) / max(1, cfg.steps - cfg.warmup_steps)
    return cfg.lr * 0.5 * (1 + math.cos(math.pi * min(1.0, progress)))


@torch.no_grad()
def _ema_update(ema: nn.Module, model: nn.Module, decay: float) -> None:
    for e, p in zip(ema.parameters(), model.parameters()):
        e.lerp_(p, 1.0 - decay)


def _setup_logging(run_dir: Path) -> logging.Handler:
    handler = logging.FileHandler(run_dir / "log.txt")
    handler.setFormatter(logging.Formatter("%(asctime)s %(levelname)s %(name)s: %(message)s"))
    logger = logging.getLogger("iwsim")
    if logger.getEffectiveLevel() > logging.INFO:  # log.txt always gets INFO
        logger.setLevel(logging.INFO)
    logger.addHandler(handler)
    return handler


def training_precision(device: torch.device, bf16: bool) -> Precision:
    """The numeric path of a training step: bf16 autocast on CUDA always; on the CPU when
    the config asks for it (``cpu_bf16``) and the CPU has the instructions, else float32
    with a warning (so a recipe that asks for bf16 runs on any machine, and a run started on
    one with AMX resumes on one without)."""
    if device.type == "cuda":
        return Precision(bf16=True)
    if bf16 and not bf16_available(device):
        log.warning("bf16 asked for (train.cpu_bf16) but this CPU (%s) has neither AMX nor AVX-512-BF16, where bf16 "
                    "is emulated and many times slower: training in float32", cpu_info().model)
        bf16 = False
    return Precision(bf16=bf16)


def compile_networks(module: nn.Module) -> None:
    """``torch.compile`` the networks of a training module in place (their weights' names
    stay), those it lists in ``compile_targets()`` or else the module itself."""
    targets = getattr(module, "compile_targets", None)
    for net in (targets() if targets is not None else (module,)):
        net.compile()


def train(task: TrainTask[M], cfg: TrainConfig, run_dir: Path, config: dict[str, Any], *,
          device: torch.device = torch.device("cpu"), force: bool = False, progress: bool = True,
          complete: Callable[[dict[str, Any]], dict[str, Any]] | None = None,
          compile: bool = False) -> dict[str, float]:
    """Train ``task`` to ``cfg.steps`` in ``run_dir``, resuming from its last checkpoint
    (``complete``: as :func:`prepare_run_dir`'s). ``compile``: ``torch.compile`` the
    module's networks (:func:`compile_networks`; a speed setting only, so not part of the
    config: a run may resume with or without it).

    Returns the last evaluation's metrics (rank 0; empty elsewhere).
    """
    d = distributed.init(device)
    if device.type == "cuda" and d.world > 1:
        device = torch.device("cuda", d.local_rank)
        torch.cuda.set_device(device)
    if cfg.lr_decay not in ("cosine", "constant"):
        raise InputError(f"lr_decay must be 'cosine' or 'constant', got {cfg.lr_decay!r}.")
    if cfg.batch_size % d.world:
        raise InputError(f"batch size {cfg.batch_size} does not split evenly over {d.world} processes.")
    run_dir = Path(run_dir)
    lock = None
    if d.main:
        lock = lock_run_dir(run_dir)  # one writer per run: held until training ends
    try:
        if d.main:
            prepare_run_dir(run_dir, config, force, complete)
        distributed.barrier(d)
        handler = _setup_logging(run_dir) if d.main else None
        try:
            return _train(task, cfg, run_dir, config, device, d, progress, compile)
        finally:
            if handler is not None:
                logging.getLogger("iwsim").removeHandler(handler)
                handler.close()
    finally:
        if lock is not None:
            lock.release()


def lock_run_dir(run_dir: Path) -> DirLock:
    """The run directory's writer lock (``run_dir/.iwsim.lock``, as an episode store's);
    a second process training into ``run_dir`` is refused in one line naming the first."""
    try:
        run_dir.mkdir(parents=True, exist_ok=True)
        return DirLock(run_dir, what="training", hint="wait for it to finish, or train into another --out.")
    except LockedError as e:
        raise InputError(e.strerror) from None


def _train(task: TrainTask[M], cfg: TrainConfig, run_dir: Path, config: dict[str, Any], device: torch.device,
           d: distributed.Dist, progress: bool, compile: bool = False) -> dict[str, float]:
    module = task.module.to(device)
    ema = copy.deepcopy(module).requires_grad_(False).eval()
    ckpt_root = run_dir / "checkpoints"
    start, elapsed = 0, 0.0
    found = _newest_whole_checkpoint(ckpt_root)
    if found is not None:
        last, state, tensors = found
        start, elapsed = state["step"], float(state["elapsed_s"])
        log.info("resuming from %s (step %d)", last, start)
        with _fitting(last):
            module.load_state_dict(tensors["model"])
            ema.load_state_dict(tensors["ema"])
        if start >= cfg.steps:  # before the optimizer, whose first construction imports torch._dynamo (seconds)
            log.info("%s is already trained to step %d (>= %d)", run_dir, start, cfg.steps)
            return {}
        if d.main:
            _truncate_metrics(run_dir / "metrics.jsonl", start)
    precision = training_precision(device, cfg.cpu_bf16)
    opt = torch.optim.AdamW(module.parameters(), lr=cfg.lr, betas=cfg.betas, weight_decay=cfg.weight_decay)
    if found is not None:
        with _fitting(last):
            optimizer_from_tensors(opt, tensors["optimizer"], state["optimizer"])

    path = ("bf16" if precision.bf16 else "fp32") + ("+compile" if compile else "")
    log.info("training path: %s on %s (%s; bf16 instructions: %s)", path, device.type, cpu_info().model,
             cpu_info().bf16)
    if compile:
        compile_networks(module)
    net: nn.Module = module
    if d.world > 1:
        net = DistributedDataParallel(module, device_ids=[device] if device.type == "cuda" else None)
    per_rank = cfg.batch_size // d.world
    part = slice(d.rank * per_rank, (d.rank + 1) * per_rank)
    metrics_file = (run_dir / "metrics.jsonl").open("a") if d.main else None
    last_eval: dict[str, float] = {}

    def checkpoint(step: int) -> None:
        opt_tensors, opt_meta = optimizer_to_tensors(opt)
        save_checkpoint(
            ckpt_root, step, task.export(ema), config,
            {"model": module.state_dict(), "ema": ema.state_dict(), "optimizer": opt_tensors},
            {"optimizer": opt_meta, "elapsed_s": elapsed},
        )

    def record(row: dict[str, Any]) -> None:
        assert metrics_file is not None  # only rank 0 records
        metrics_file.write(json.dumps(row) + "\n")
        metrics_file.flush()

    module.train()
    t_mark, images = time.perf_counter(), 0
    bar = tqdm(range(start, cfg.steps), initial=start, total=cfg.steps, desc="train", disable=not (progress and d.main))
    try:
        for step in bar:
            t0 = time.perf_counter()
            for group in opt.param_groups:
                group["lr"] = _lr(cfg, step)
            batch = task.batch(step, step_generator(cfg.seed, step), part, device)
            with precision.autocast(device):
                loss, parts = net(batch)
            loss_all = distributed.mean(loss.detach(), d)
            if not torch.isfinite(loss_all):
                where = last_checkpoint(ckpt_root)
                raise TrainingError(
                    f"the loss became non-finite ({loss_all.item()}) at step {step}; training stopped. "
                    f"The last good checkpoint is {where if where else 'none (no checkpoint was written yet)'}."
                )
            opt.zero_grad(set_to_none=True)
            loss.backward()
            grad_norm = torch.nn.utils.clip_grad_norm_(module.parameters(), cfg.grad_clip)
            opt.step()
            # EMA warm-up: average over the steps seen so far until that exceeds the decay.
            _ema_update(ema, module, min(cfg.ema_decay, (1 + step) / (10 + step)))
            elapsed += time.perf_counter() - t0
            images += cfg.batch_size
            done = step + 1
            if d.main and (done % cfg.log_every == 0 or done == cfg.steps):
                rate = images / (time.perf_counter() - t_mark)
                t_mark, images = time.perf_counter(), 0
                row = {"step": done, "loss": loss_all.item(), **parts, "grad_norm": grad_norm.item(),
                       "lr": _lr(cfg, step), "images_per_s": rate, "elapsed_s": elapsed, "path": path}
                record(row)
                bar.set_postfix(loss=f"{row['loss']:.4f}", img_s=f"{rate:.0f}")
            if d.main and (done % cfg.eval_every == 0 or done == cfg.steps):
                t_eval = time.perf_counter()
                last_eval = task.evaluate(ema, done, run_dir / "eval")
                record({"step": done, "elapsed_s": elapsed, **{f"eval/{k}": v for k, v in last_eval.items()}})
                log.info("step %d: %s", done, ", ".join(f"{k} {v:.4f}" for k, v in last_eval.items()))
                t_mark += time.perf_counter() - t_eval  # evaluation time is not training throughput
            if done % cfg.checkpoint_every == 0 or done == cfg.steps:
                if d.main:
                    checkpoint(done)
                distributed.barrier(d)
    finally:
        bar.close()
        if metrics_file is not None:
            metrics_file.close()
    return last_eval


def _read_checkpoint(ckpt: Path) -> tuple[dict[str, Any], dict[str, dict[str, torch.Tensor]]]:
    """Everything a resume reads from ``ckpt`` (state.json and the training tensors), having
    checked that the whole checkpoint is readable; a CheckpointError names what is not."""
    state = load_json(ckpt / "training_state" / "state.json")
    if not isinstance(state.get("step"), int) or not isinstance(state.get("elapsed_s"), (int, float)) \
            or not isinstance(state.get("optimizer"), dict):
        raise CheckpointError(f"checkpoint file {ckpt / 'training_state' / 'state.json'} lacks step, elapsed_s "
                              "or optimizer.")
    load_json(ckpt / "config.json")
    load_tensors(ckpt / "model.safetensors")  # what users load must be whole too
    return state, {stem: load_tensors(ckpt / "training_state" / f"{stem}.safetensors")
                   for stem in ("model", "ema", "optimizer")}


def _newest_whole_checkpoint(
        ckpt_root: Path) -> tuple[Path, dict[str, Any], dict[str, dict[str, torch.Tensor]]] | None:
    """The newest whole checkpoint of a run, read (its path, state.json and training
    tensors), or None when the run has none. A damaged one (truncated or unreadable files,
    e.g. from a full disk or a kill outside our atomic writes) is skipped with a warning
    naming it."""
    damaged: list[str] = []
    for ckpt in resume_candidates(ckpt_root):
        try:
            return (ckpt, *_read_checkpoint(ckpt))
        except CheckpointError as e:
            log.warning("%s; resuming from the checkpoint before it instead", " ".join(str(e).split())[:300])
            damaged.append(ckpt.name)
    if damaged:
        raise CheckpointError(f"no checkpoint in {ckpt_root} is whole (damaged: {', '.join(damaged)}); remove them "
                              "to train from scratch, or train into a new --out.")
    return None


@contextlib.contextmanager
def _fitting(ckpt: Path) -> Iterator[None]:
    """Loading ``ckpt``'s tensors: a checkpoint of another model is an error, not skipped."""
    try:
        yield
    except (RuntimeError, KeyError, ValueError) as e:
        raise CheckpointError(f"checkpoint {ckpt} does not fit this model ({' '.join(str(e).split())[:200]}); "
                              "train into a new --out.") from None


# Peak memory per sample of one training step on CPU at 64x64, measured with the pusht-64
# (ae, dynamics) and dp presets as the growth of peak RSS from batch 4 to 64 (2 to 16 for
# dynamics), rounded down: enough to refuse a batch that cannot fit before allocating it.
TRAIN_MIB_PER_SAMPLE = {"ae": 20.0, "decoder-finetune": 20.0, "dynamics": 60.0, "policy": 0.75}


def check_batch_memory(stage: str, batch_size: int, image_size: int) -> None:
    """Refuse a global batch of ``stage`` (a key of :data:`TRAIN_MIB_PER_SAMPLE`) on frames
    of ``image_size`` that cannot fit in this machine's memory (this process's share of it
    under torchrun)."""
    per_sample = TRAIN_MIB_PER_SAMPLE[stage] * MiB * (image_size / 64) ** 2
    per_rank = -(-batch_size // int(os.environ.get("WORLD_SIZE", "1")))
    require_memory(per_rank * per_sample, f"--batch-size {batch_size} (about {human_bytes(per_sample)} per sample)")


def resolve_device(name: str) -> torch.device:
    """``auto`` -> cuda when available, else cpu (only the CLI resolves ``auto``)."""
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    try:
        device = torch.device(name)
    except RuntimeError:
        raise InputError(f"unknown device {name!r}; expected auto, cpu, cuda or cuda:N.") from None
    if device.type == "cuda":
        if not torch.cuda.is_available():
            build = "this PyTorch build has no CUDA" if torch.version.cuda is None else "no CUDA GPU is visible"
            raise InputError(f"--device {name}: {build}; use --device cpu (or auto).")
        if device.index is not None and device.index >= torch.cuda.device_count():
            raise InputError(f"--device {name}: there are only {torch.cuda.device_count()} CUDA devices "
                             f"(cuda:0..cuda:{torch.cuda.device_count() - 1}).")
    elif device.type != "cpu":
        raise InputError(f"unknown device {name!r}; expected auto, cpu, cuda or cuda:N.")
    return device


