"""Diffusion Policy ReplayBuffer Zarr stores (and our own episode stores): import and validate.

A ReplayBuffer (diffusion_policy/common/replay_buffer.py) is a Zarr format 2 group::

    data/<key>           (N, ...) arrays concatenated over episodes
    meta/episode_ends    (E,) int64, cumulative

Its Push-T file ``pusht_cchi_v7_replay.zarr`` holds ``img`` (N, 96, 96, 3) float32 in [0, 255]
(LeRobot's converter checks that range and casts to uint8), ``state`` (N, 5) = agent xy and
block pose, ``action`` (N, 2), ``keypoint`` (N, 9, 2) and ``n_contacts`` (N, 1), at 10 fps.

Cameras: every image array ((N, H, W, 3), uint8 or float) is a camera. An import without
``camera`` reads them all: in the order of the store's ``cameras`` attribute where it names
image arrays the store holds (our own stores, :mod:`iwsim.data.views`), then ``img`` (when
not yet taken), then the others in name order. ``img`` is named as a store without
``cameras`` names its view (its ``camera`` attribute, else ``top``); the others by their
array's name without ``img_`` and ``_image`` / ``_img`` (``img_wrist`` -> ``wrist``,
``agentview_image`` -> ``agentview``). ``camera`` reads one array (by its name, or by the
view name it would get) as a store of one view.
"""

from __future__ import annotations

import json
import logging
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import zarr

from iwsim.core.errors import InputError
from iwsim.data import views
from iwsim.data.formats.common import FormatError, SourceViews, check_episode, positive_int, reason, view_name, where
from iwsim.data.store import EpisodeStore, StoreError

log = logging.getLogger(__name__)

ZARR_FPS = 10  # Push-T's control rate, LeRobot's default when converting DP's pusht zarr
IMAGE_KEY, STATE_KEYS, ACTION_KEY = "img", ("state", "agent_pos"), "action"
# What zarr and numcodecs raise on a damaged store: Blosc reports a bad chunk as RuntimeError,
# or as SystemError when a damaged header gives it a negative size.
_READ_ERRORS = (OSError, KeyError, ValueError, TypeError, IndexError, RuntimeError, SystemError, MemoryError)
_STORE_ATTRS = ("seeds", "store_version", "source_format", "source",  # managed by the store / import_
                "camera", "cameras", "source_cameras")  # set anew from the cameras imported
VIEW_PREFIXES, VIEW_SUFFIXES = (views.VIEW_PREFIX,), ("_image", "_img")  # dropped from an array's view name


def _is_image(arr: zarr.Array) -> bool:
    return arr.ndim == 4 and arr.shape[-1] == 3 and (arr.dtype == np.uint8 or np.issubdtype(arr.dtype, np.floating))


def _open(src: Path) -> tuple[zarr.Group, dict[str, zarr.Array], np.ndarray]:
    """The root group, its data arrays and the committed episode ends."""
    try:
        root = zarr.open_group(src, mode="r")
    except _READ_ERRORS as e:
        raise FormatError(f"{src}: not a readable Zarr group ({reason(e)}).") from None
    try:
        data = root.get("data")
        if not isinstance(data, zarr.Group):
            raise FormatError(f"{where(src, 'data')}: missing; expected a ReplayBuffer's data/ group.")
        arrays = dict(data.arrays())
        ends_arr = root.get("meta/episode_ends")
        if not isinstance(ends_arr, zarr.Array):
            raise FormatError(f"{where(src, 'meta/episode_ends')}: missing.")
        raw = np.asarray(ends_arr[:])
    except FormatError:
        raise
    except _READ_ERRORS as e:
        raise FormatError(f"{src}: unreadable ({reason(e)}).") from None
    if raw.ndim != 1 or not np.issubdtype(raw.dtype, np.integer):
        raise FormatError(f"{where(src, 'meta/episode_ends')}: expected (E,) integers, got {raw.dtype} {raw.shape}.")
    ends = raw.astype(np.int64)
    if len(ends) > 1 and ends[-1] == 0:
        # Our store's interrupted append leaves one unwritten trailing entry (it reads as 0).
        log.warning("%s: ignoring the unwritten last entry of meta/episode_ends", src)
        ends = ends[:-1]
    if not len(ends):
        raise FormatError(f"{where(src, 'meta/episode_ends')}: no episodes.")
    starts = np.concatenate([[0], ends[:-1]])
    bad = np.flatnonzero(ends <= starts)
    if len(bad):
        i = int(bad[0])
        raise FormatError(f"{where(src, 'meta/episode_ends', i)}: episode ends must increase strictly; "
                          f"entry {i} is {ends[i]} after {starts[i]} (an empty or negative episode).")
    return root, arrays, ends


def _all_views(arrays: dict[str, zarr.Array], attrs: dict[str, Any]) -> SourceViews | None:
    """Every image array as a view, in the order of the module docstring; None if none."""
    images = [k for k in sorted(arrays) if _is_image(arrays[k])]
    sources: list[str] = []
    names: list[str] = []
    if "cameras" in attrs:  # our own store's views, when they are what it holds
        try:
            keys = views.view_keys(views.store_cameras(attrs))
        except InputError:
            keys = {}
        if all(k in images for k in keys.values()):
            sources, names = list(keys.values()), list(keys)
    if IMAGE_KEY in images and IMAGE_KEY not in sources:
        sources.append(IMAGE_KEY)
        names.append(views.store_cameras({k: v for k, v in attrs.items() if k != "cameras"})[0])
    for key in images:
        if key not in sources:
            sources.append(key)
            names.append(view_name(key, VIEW_PREFIXES, VIEW_SUFFIXES))
    return SourceViews.of(sources, names) if sources else None


def _pick(arrays: dict[str, zarr.Array], src: Path, camera: str | None,
          attrs: dict[str, Any]) -> tuple[SourceViews, str]:
    """(the cameras to read, state key) of the store."""
    have = ", ".join(sorted(arrays)) or "none"
    every = _all_views(arrays, attrs)
    if camera is not None:
        by_name = dict(zip(every.names, every.sources)) if every is not None else {}
        if camera not in arrays and camera not in by_name:
            raise FormatError(f"{where(src, f'data/{camera}')}: no such array; data/ holds {have}.")
        key = camera if camera in arrays else by_name[camera]
        named = {k: n for n, k in by_name.items()}  # the view's own name where the store names it
        cams = SourceViews.of([key], [named[key]] if key in named and "cameras" in attrs else None)
    elif IMAGE_KEY in arrays and not _is_image(arrays[IMAGE_KEY]):
        cams = SourceViews.of([IMAGE_KEY])  # refused below, naming it
    elif every is None:
        raise FormatError(f"{where(src, 'data')}: no image arrays ((N, H, W, 3) frames); data/ holds {have}.")
    else:
        cams = every
    for img in cams.sources:
        if not _is_image(arrays[img]):
            a = arrays[img]
            raise FormatError(f"{where(src, f'data/{img}')}: expected (N, H, W, 3) uint8 frames, "
                              f"got {a.dtype} {a.shape}.")
    state = next((k for k in STATE_KEYS if k in arrays), None)
    if state is None:
        raise FormatError(f"{where(src, 'data')}: no data/state or data/agent_pos; data/ holds {have}.")
    if ACTION_KEY not in arrays:
        raise FormatError(f"{where(src, 'data/action')}: missing; data/ holds {have}.")
    return cams, state


def _frames(value: np.ndarray, at: str) -> np.ndarray:
    """uint8 frames; float frames must hold 0..255 (Diffusion Policy's Push-T stores them so)."""
    if value.dtype == np.uint8:
        return value
    if not np.isfinite(value).all() or value.min() < 0 or value.max() > 255:
        raise FormatError(f"{at}: float frames must hold values in [0, 255].")
    return np.rint(value).astype(np.uint8)


def _episodes(src: Path, arrays: dict[str, zarr.Array], keys: dict[str, str], view_keys: tuple[str, ...],
              ends: np.ndarray, seeds: list[Any]) -> Iterator[tuple[dict[str, np.ndarray], int | None]]:
    start = 0
    for i, stop in enumerate(ends.tolist()):
        ep = {}
        for name, key in keys.items():
            at = where(src, f"data/{key}", i)
            try:
                value = np.asarray(arrays[key][start:stop])
            except _READ_ERRORS as e:
                raise FormatError(f"{at}: unreadable ({reason(e)}).") from None
            ep[name] = _frames(value, at) if name in view_keys else value
        seed = seeds[i] if i < len(seeds) and isinstance(seeds[i], int) else None
        yield check_episode(ep, where(src, episode=i), view_keys), seed
        start = stop


def read_zarr(src: Path, *, camera: str | None) -> tuple[dict, int, Iterator[tuple[dict, int | None]]]:
    """Episodes of a Diffusion Policy ReplayBuffer (or one of our stores): ``img`` (T, H, W, 3)
    uint8 and ``img_<name>`` from its image arrays (see the module docstring; ``camera``
    reads that one only), ``state`` (T, S) from ``data/state`` (else ``agent_pos``),
    ``action`` (T, A) from ``data/action``; other numeric per-frame arrays that are not
    images are carried under their own names."""
    src = Path(src)
    root, arrays, ends = _open(src)
    try:
        source = dict(root.attrs)
    except _READ_ERRORS:
        source = {}
    cams, state = _pick(arrays, src, camera, source)
    img = cams.sources[0]
    n = int(ends[-1])
    keys = {**{key: cam for cam, key in cams.keys.items()}, "state": state, "action": ACTION_KEY}
    for key in keys.values():
        length = arrays[key].shape[0] if arrays[key].ndim else 0
        if length < n:
            raise FormatError(f"{where(src, f'data/{key}')}: holds {length} frames but meta/episode_ends counts {n}.")
    for key, arr in sorted(arrays.items()):
        # Extras: per-frame numbers (e.g. keypoint, n_contacts); cameras not asked for stay behind.
        taken = key in keys.values() or key in keys
        numeric = np.issubdtype(arr.dtype, np.number) or arr.dtype == bool
        if not taken and numeric and 1 <= arr.ndim <= 3 and arr.shape[0] >= n:
            keys[key] = key
    attrs = {k: v for k, v in source.items() if k not in _STORE_ATTRS and _json_ok(v)}
    h, w = arrays[img].shape[1:3]
    attrs.update({
        "task": str(source.get("task") or src.name.removesuffix(".zarr")),
        "fps": positive_int(source.get("fps")) or ZARR_FPS,
        **(cams.attrs() if len(cams.names) > 1 or "cameras" not in source else {"camera": cams.names[0]}),
        "image_size": int(h) if h == w else [int(h), int(w)],
    })
    seeds = source.get("seeds")
    return attrs, len(ends), _episodes(src, arrays, keys, tuple(cams.keys.values()), ends,
                                       seeds if isinstance(seeds, list) else [])


def _json_ok(value: Any) -> bool:
    try:
        json.dumps(value)
    except (TypeError, ValueError):
        return False
    return True


# --- validation ------------------------------------------------------------------------------
def _episodes_of(ends: np.ndarray, a: int, b: int) -> str:
    """'episode i' or 'episodes i..j' holding frames [a, b)."""
    i = int(np.searchsorted(ends, a, side="right"))
    j = int(np.searchsorted(ends, max(a, b - 1), side="right"))
    return f"episode {i}" if i == j else f"episodes {i}..{j}"


def validate_store(path: Path) -> list[str]:
    """What is wrong with an episode store, one line per problem naming the key and episode:
    episode ends, array shapes/dtypes/lengths, unreadable chunks, non-finite state/action,
    the fps/image_size/seeds/cameras attributes and each camera view's frames. Empty if it
    is valid."""
    path = Path(path)
    try:
        store = EpisodeStore.open(path, "r")
        root = zarr.open_group(path, mode="r")
        ends_arr = root["meta/episode_ends"]
        assert isinstance(ends_arr, zarr.Array)  # EpisodeStore.open checked it
        raw = np.asarray(ends_arr[:])
    except StoreError as e:
        return [str(e)]
    except _READ_ERRORS as e:
        return [f"{path}: unreadable ({reason(e)})."]
    problems: list[str] = []
    ends, n = store.episode_ends, store.n_frames
    if not np.issubdtype(raw.dtype, np.integer):
        problems.append(f"{where(path, 'meta/episode_ends')}: expected integers, got {raw.dtype}.")
    # The store drops a single unwritten trailing 0 (an interrupted append); anything else is damage.
    extra = raw[len(ends):]
    if len(extra) and not (len(extra) == 1 and extra[0] == 0):
        prev = ends[-1] if len(ends) else 0
        problems.append(f"{where(path, 'meta/episode_ends', len(ends))}: episode ends must increase strictly; "
                        f"entry {len(ends)} is {extra[0]} after {prev}.")
    if not store.n_episodes:  # one problem, not one per array it has yet to define
        problems.append(f"{path}: holds no episodes: an empty store (a collect stopped before its first episode "
                        "leaves one; a collect into it, with any flags, fills it).")
        return problems
    try:
        view_keys = views.view_keys(views.store_cameras(store.attrs))
    except InputError as e:
        problems.append(f"{path}: {e}")
        view_keys = {views.DEFAULT_CAMERA: views.IMAGE_KEY}

    def of(name: str) -> str:
        return f" (camera {name!r} of {', '.join(view_keys)})" if len(view_keys) > 1 else ""

    shapes = {k: store.array(k).shape for k in store.keys}
    for name, key in view_keys.items():
        if key not in shapes:
            problems.append(f"{where(path, f'data/{key}')}: missing{of(name)}.")
            continue
        a = store.array(key)
        if a.dtype != np.uint8 or a.ndim != 4 or a.shape[-1] != 3:
            problems.append(f"{where(path, f'data/{key}')}: expected uint8 (N, H, W, 3) frames{of(name)}, "
                            f"got {a.dtype} {a.shape}.")
    for key in ("state", "action"):
        if key not in store.keys:
            problems.append(f"{where(path, f'data/{key}')}: missing.")
    for key in ("state", "action"):
        if key in shapes:
            a = store.array(key)
            if a.ndim != 2 or not np.issubdtype(a.dtype, np.floating):
                problems.append(f"{where(path, f'data/{key}')}: expected floats of shape (N, D), "
                                f"got {a.dtype} {a.shape}.")
    # Read every array chunk by chunk: a damaged chunk shows only when it is decoded.
    for key in store.keys:
        arr = store.array(key)
        step = arr.chunks[0] if arr.ndim else 1
        for lo in range(0, n, step):
            hi = min(n, lo + step)
            try:
                block = arr[lo:hi]
            except _READ_ERRORS as e:
                problems.append(f"{where(path, f'data/{key}')} ({_episodes_of(ends, lo, hi)}): "
                                f"frames {lo}..{hi - 1} unreadable ({reason(e)}).")
                continue
            if key in ("state", "action") and np.issubdtype(block.dtype, np.floating):
                rows = np.flatnonzero(~np.isfinite(block.reshape(len(block), -1)).all(axis=1))
                if len(rows):
                    first = lo + int(rows[0])
                    problems.append(f"{where(path, f'data/{key}')} ({_episodes_of(ends, first, first + 1)}): "
                                    "holds non-finite values.")
    attrs = store.attrs
    if positive_int(attrs.get("fps")) is None:
        problems.append(f"{path}: attribute 'fps' is {attrs.get('fps')!r}; expected a positive integer.")
    size = attrs.get("image_size")
    held = [key for key in view_keys.values() if key in shapes and len(shapes[key]) == 4]
    for key in held:
        h, w = shapes[key][1:3]
        if not (size == [h, w] or (h == w and size == h)):
            problems.append(f"{path}: attribute 'image_size' is {size!r}; data/{key} holds {h}x{w} frames.")
    if not held and size is None:
        problems.append(f"{path}: attribute 'image_size' is missing.")
    # Open checked there are enough seeds; one more is an interrupted append's leftover.
    seeds = root.attrs.get("seeds")
    n_episodes = store.n_episodes
    if isinstance(seeds, list) and len(seeds) > n_episodes + 1:
        problems.append(f"{path}: attribute 'seeds' lists {len(seeds)} seeds for {n_episodes} episodes.")
    bad = [i for i, s in enumerate(store.seeds) if s is not None and (not isinstance(s, int) or isinstance(s, bool))]
    if bad:
        problems.append(f"{where(path, episode=bad[0])}: seed {store.seeds[bad[0]]!r} is not an integer or null.")
    return problems
