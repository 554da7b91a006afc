"""Episode stores to and from the formats robot-learning tools read and write.

    export:   lerobot-v3, lerobot-v2.1, hdf5-aloha
    import:   lerobot-v3, lerobot-v2.1, hdf5-aloha, robomimic, zarr (Diffusion Policy)
    validate: an episode store, a LeRobot dataset (v3 or v2.1) or ALOHA/robomimic HDF5
    merge:    episode stores of one task (and one set of cameras) into a new one

Every camera travels (see :mod:`iwsim.data.views` for the store's side): an export writes
each view of the store (LeRobot: one ``observation.images.<name>`` video feature each, or
``observation.image`` for a store of one view, as ever; ALOHA: ``/observations/images/<name>``,
or ``top`` for one view); an import without ``camera`` reads every camera of the source, the
first into ``data/img``, each further one into ``data/img_<name>`` (names made by
:func:`~iwsim.data.formats.common.view_name`), and records them in ``cameras``; with
``camera`` it reads that one only, as a store of one view.

Every format module offers some of:

- ``export_<fmt>(store, out, *, fps, task, progress)``: write ``store`` into the empty
  directory ``out`` (this module hands it a temporary directory and renames it at the end);
- ``read_<fmt>(src, *, camera) -> (attrs, n_episodes, episodes)``: the source's
  attributes (task, fps, action names, ...) and an iterator of ``(episode, seed)``;
- ``validate_<fmt>(path) -> problems``: one line per thing that is wrong, empty if none.
"""

from __future__ import annotations

import json
import logging
import os
from pathlib import Path

from iwsim.core.errors import InputError
from iwsim.data import views
from iwsim.data.formats.common import (
    FormatError,
    check_resize_memory,
    output_dir,
    read_meta,
    store_views,
    write_store,
)
from iwsim.data.store import EpisodeStore

log = logging.getLogger(__name__)

EXPORT_FORMATS = ("lerobot-v3", "lerobot-v2.1", "hdf5-aloha")
IMPORT_FORMATS = ("lerobot-v3", "lerobot-v2.1", "hdf5-aloha", "robomimic", "zarr")

__all__ = ["EXPORT_FORMATS", "IMPORT_FORMATS", "FormatError", "export", "import_", "merge", "validate"]

# Attributes every store of a merge must share (the rest may differ: policy, steps, ...).
MERGE_MATCHING = ("task", "image_size", "fps")


def export(fmt: str, store: str | os.PathLike, out: str | os.PathLike, *, fps: int | None = None,
           task: str | None = None, progress: bool = True) -> Path:
    """Write the episode store ``store`` as ``fmt`` to the new directory ``out``."""
    if fmt not in EXPORT_FORMATS:
        raise InputError(f"unknown export format {fmt!r}; expected one of {', '.join(EXPORT_FORMATS)}.")
    src = EpisodeStore.open(store, "r")
    if src.n_episodes == 0:
        raise FormatError(f"{store} holds no episodes to export.")
    fps = int(fps or src.attrs.get("fps") or 10)
    if fps < 1:
        raise InputError(f"--fps must be a positive integer, got {fps}.")
    task = task or str(src.attrs.get("task") or "")
    dropped = sorted(set(src.keys) - {"state", "action", *store_views(src).values()})
    if dropped:
        log.info("%s has no place for %s; they are not exported", fmt, ", ".join(dropped))
    if fmt == "hdf5-aloha":
        from iwsim.data.formats.hdf5 import export_aloha as writer
    else:
        from iwsim.data.formats.lerobot import export_v3, export_v21

        writer = export_v3 if fmt == "lerobot-v3" else export_v21
    with output_dir(out) as tmp:
        writer(src, tmp, fps=fps, task=task, progress=progress)
    return Path(out)


def import_(fmt: str, src: str | os.PathLike, out: str | os.PathLike, *, camera: str | None = None,
            image_size: int | None, progress: bool = True) -> EpisodeStore:
    """Read ``src`` (in ``fmt``) into a new episode store at ``out``, frames resized to
    ``image_size`` (None keeps them; ``iwsim data import`` resizes to the default task's).
    Every camera of the source becomes a view of the store, or only ``camera`` when given."""
    if fmt not in IMPORT_FORMATS:
        raise InputError(f"unknown import format {fmt!r}; expected one of {', '.join(IMPORT_FORMATS)}.")
    if image_size is not None and image_size < 1:
        raise InputError(f"--image-size must be a positive integer, got {image_size}.")
    if image_size is not None:  # before reading anything: one frame must fit
        check_resize_memory(1, image_size, f"--image-size {image_size} (for a single frame)")
    src = Path(src)
    if not src.exists():
        raise FileNotFoundError(f"{src} does not exist.")
    if fmt == "hdf5-aloha":
        from iwsim.data.formats.hdf5 import read_aloha as reader
    elif fmt == "robomimic":
        from iwsim.data.formats.hdf5 import read_robomimic as reader
    elif fmt == "zarr":
        from iwsim.data.formats.dp_zarr import read_zarr as reader
    else:
        from iwsim.data.formats.lerobot import read_v3, read_v21

        reader = read_v3 if fmt == "lerobot-v3" else read_v21
    attrs, n, episodes = reader(src, camera=camera)
    n_views = len(views.store_cameras(attrs))
    if image_size is not None and n_views > 1:  # before reading any episode: one frame of each view must fit
        check_resize_memory(1, image_size, f"--image-size {image_size} (for a single frame of {n_views} views)",
                            n_views=n_views)
    attrs = {**attrs, "source_format": fmt, "source": str(src)}
    if image_size is not None:
        attrs["image_size"] = image_size
    return write_store(out, episodes, attrs, image_size=image_size, progress=progress, total=n)


def validate(path: str | os.PathLike) -> tuple[str, list[str]]:
    """What ``path`` is and what is wrong with it: (kind, problems), no problems if valid."""
    path = Path(path)
    if not path.exists():
        raise FileNotFoundError(f"{path} does not exist.")
    if os.path.lexists(path / "meta" / "info.json"):  # even a broken one: validate says what is wrong with it
        from iwsim.data.formats.lerobot import validate_lerobot

        return validate_lerobot(path)
    if (path / "meta" / "episode_ends").exists() or (path / ".zgroup").exists():
        from iwsim.data.formats.dp_zarr import read_zarr, validate_store

        try:
            attrs = json.loads(read_meta(path / ".zattrs"))
        except (OSError, ValueError):  # FormatError too
            attrs = {}
        if isinstance(attrs, dict) and "store_version" in attrs:
            return "episode store", validate_store(path)
        try:  # another tool's replay buffer (e.g. Diffusion Policy's): valid if it imports
            for _ in read_zarr(path, camera=None)[2]:
                pass
        except FormatError as e:
            return "Diffusion Policy zarr", [str(e)]
        return "Diffusion Policy zarr", []
    if path.suffix in (".hdf5", ".h5") or (path.is_dir() and any(path.glob("*.hdf5"))):
        from iwsim.data.formats.hdf5 import validate_hdf5

        return validate_hdf5(path)
    raise FormatError(f"{path} is none of: an episode store, a LeRobot dataset (meta/info.json), "
                      "ALOHA or robomimic HDF5.")


def merge(sources: list[str | os.PathLike], out: str | os.PathLike, *, progress: bool = True) -> EpisodeStore:
    """A new episode store at ``out`` holding every episode of ``sources`` in order (with
    their seeds). The sources must share the task, image size, fps, cameras (their names and
    order, when any has several) and arrays; the merged store's ``policy`` joins theirs with
    ``+`` and ``sources`` lists them."""
    if len(sources) < 2:
        raise InputError(f"merge takes at least 2 stores, got {len(sources)}.")
    target = Path(out).resolve()
    seen: dict[Path, str | os.PathLike] = {}
    for src in sources:
        if target.is_relative_to(Path(src).resolve()):
            raise InputError(f"--out {out} is inside the input {src}; write the merged store elsewhere.")
        if Path(src).resolve() in seen:  # its episodes would be written twice
            raise InputError(f"merge names the store {seen[Path(src).resolve()]} twice ({src}); give each store once.")
        seen[Path(src).resolve()] = src
    stores = [EpisodeStore.open(src, "r") for src in sources]
    first = stores[0]
    first_cameras = views.store_cameras(first.attrs, first.keys)
    for s in stores[1:]:
        for key in MERGE_MATCHING:
            if s.attrs.get(key) != first.attrs.get(key):
                raise InputError(f"cannot merge {s.path} into {first.path}: {key} {s.attrs.get(key)!r} differs "
                                 f"from {first.attrs.get(key)!r}.")
        cameras = views.store_cameras(s.attrs, s.keys)
        # One view is data/img whatever its name; several must be the same views in the same order.
        if cameras != first_cameras and max(len(cameras), len(first_cameras)) > 1:
            raise InputError(f"cannot merge {s.path} into {first.path}: cameras {list(cameras)} differ from "
                             f"{list(first_cameras)}.")
        if sorted(s.keys) != sorted(first.keys):
            raise InputError(f"cannot merge {s.path} into {first.path}: arrays {sorted(s.keys)} differ from "
                             f"{sorted(first.keys)}.")
    policies = list(dict.fromkeys(str(s.attrs.get("policy")) for s in stores))
    attrs = {k: v for k, v in first.attrs.items() if k not in ("seeds", "store_version", "steps")}
    attrs.update(policy="+".join(policies), sources=[str(s.path) for s in stores])

    def episodes():
        for s in stores:
            for i, seed in enumerate(s.seeds[:s.n_episodes]):
                yield s.episode(i), seed

    return write_store(out, episodes(), attrs, progress=progress, total=sum(s.n_episodes for s in stores))
