"""Diffusion Policy ReplayBuffer Zarr stores (and our own episode stores): import and validate.

A ReplayBuffer (diffusion_policy/common/replay_buffer.py) is a Zarr format 2 group::

    data/<key>           (N, ...) arrays concatenated over episodes
    meta/episode_ends    (E,) int64, cumulative

Its Push-T file ``pusht_cchi_v7_replay.zarr`` holds ``img`` (N, 96, 96, 3) float32 in [0, 255]
(LeRobot's converter checks that range and casts to uint8), ``state`` (N, 5) = agent xy and
block pose, ``action`` (N, 2), ``keypoint`` (N, 9, 2) and ``n_contacts`` (N, 1), at 10 fps.
"""

from __future__ import annotations

import json
import logging
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import zarr

from iwsim.data.formats.common import FormatError, check_episode, positive_int, reason, where
from iwsim.data.store import EpisodeStore, StoreError

log = logging.getLogger(__name__)

ZARR_FPS = 10  # Push-T's control rate, LeRobot's default when converting DP's pusht zarr
IMAGE_KEY, STATE_KEYS, ACTION_KEY = "img", ("state", "agent_pos"), "action"
# What zarr and numcodecs raise on a damaged store: Blosc reports a bad chunk as RuntimeError,
# or as SystemError when a damaged header gives it a negative size.
_READ_ERRORS = (OSError, KeyError, ValueError, TypeError, IndexError, RuntimeError, SystemError, MemoryError)
_STORE_ATTRS = ("seeds", "store_version", "source_format", "source")  # managed by the store / import_


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


def _pick(arrays: dict[str, zarr.Array], src: Path, camera: str | None) -> tuple[str, str]:
    """(image key, state key) of the store."""
    have = ", ".join(sorted(arrays)) or "none"
    if camera is not None:
        if camera not in arrays:
            raise FormatError(f"{where(src, f'data/{camera}')}: no such array; data/ holds {have}.")
        img = camera
    elif IMAGE_KEY in arrays:
        img = IMAGE_KEY
    else:
        images = [k for k, a in arrays.items() if _is_image(a)]
        if len(images) != 1:
            raise FormatError(f"{where(src, 'data')}: no data/img and {len(images)} image arrays "
                              f"({', '.join(images) or 'none'}); choose one with --camera.")
        img = images[0]
    if not _is_image(arrays[img]):
        a = arrays[img]
        raise FormatError(f"{where(src, f'data/{img}')}: expected (N, H, W, 3) uint8 frames, got {a.dtype} {a.shape}.")
    state = next((k for k in STATE_KEYS if k in arrays), None)
    if state is None:
        raise FormatError(f"{where(src, 'data')}: no data/state or data/agent_pos; data/ holds {have}.")
    if ACTION_KEY not in arrays:
        raise FormatError(f"{where(src, 'data/action')}: missing; data/ holds {have}.")
    return img, state


def _frames(value: np.ndarray, at: str) -> np.ndarray:
    """uint8 frames; float frames must hold 0..255 (Diffusion Policy's Push-T stores them so)."""
    if value.dtype == np.uint8:
        return value
    if not np.isfinite(value).all() or value.min() < 0 or value.max() > 255:
        raise FormatError(f"{at}: float frames must hold values in [0, 255].")
    return np.rint(value).astype(np.uint8)


def _episodes(src: Path, arrays: dict[str, zarr.Array], keys: dict[str, str], ends: np.ndarray,
              seeds: list[Any]) -> Iterator[tuple[dict[str, np.ndarray], int | None]]:
    start = 0
    for i, stop in enumerate(ends.tolist()):
        ep = {}
        for name, key in keys.items():
            at = where(src, f"data/{key}", i)
            try:
                value = np.asarray(arrays[key][start:stop])
            except _READ_ERRORS as e:
                raise FormatError(f"{at}: unreadable ({reason(e)}).") from None
            ep[name] = _frames(value, at) if name == "img" else value
        seed = seeds[i] if i < len(seeds) and isinstance(seeds[i], int) else None
        yield check_episode(ep, where(src, episode=i)), seed
        start = stop


def read_zarr(src: Path, *, camera: str | None) -> tuple[dict, int, Iterator[tuple[dict, int | None]]]:
    """Episodes of a Diffusion Policy ReplayBuffer (or one of our stores): ``img`` (T, H, W, 3)
    uint8 from ``data/<camera>`` (default ``img``, else the only image array), ``state`` (T, S)
    from ``data/state`` (else ``agent_pos``), ``action`` (T, A) from ``data/action``; other
    numeric per-frame arrays that are not images are carried under their own names."""
    src = Path(src)
    root, arrays, ends = _open(src)
    img, state = _pick(arrays, src, camera)
    n = int(ends[-1])
    keys = {"img": img, "state": state, "action": ACTION_KEY}
    for key in keys.values():
        length = arrays[key].shape[0] if arrays[key].ndim else 0
        if length < n:
            raise FormatError(f"{where(src, f'data/{key}')}: holds {length} frames but meta/episode_ends counts {n}.")
    for key, arr in sorted(arrays.items()):
        # Extras: per-frame numbers (e.g. keypoint, n_contacts); other cameras stay behind.
        taken = key in keys.values() or key in keys
        numeric = np.issubdtype(arr.dtype, np.number) or arr.dtype == bool
        if not taken and numeric and 1 <= arr.ndim <= 3 and arr.shape[0] >= n:
            keys[key] = key
    try:
        source = dict(root.attrs)
    except _READ_ERRORS:
        source = {}
    attrs = {k: v for k, v in source.items() if k not in _STORE_ATTRS and _json_ok(v)}
    h, w = arrays[img].shape[1:3]
    attrs.update({
        "task": str(source.get("task") or src.name.removesuffix(".zarr")),
        "fps": positive_int(source.get("fps")) or ZARR_FPS,
        "camera": img,
        "image_size": int(h) if h == w else [int(h), int(w)],
    })
    seeds = source.get("seeds")
    return attrs, len(ends), _episodes(src, arrays, keys, ends, seeds if isinstance(seeds, list) else [])


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
    episode ends, array shapes/dtypes/lengths, unreadable chunks, non-finite state/action and
    the fps/image_size/seeds attributes. Empty if it is valid."""
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
    for key in ("img", "state", "action"):
        if key not in store.keys:
            problems.append(f"{where(path, f'data/{key}')}: missing.")
    shapes = {k: store.array(k).shape for k in store.keys}
    if "img" in shapes:
        a = store.array("img")
        if a.dtype != np.uint8 or a.ndim != 4 or a.shape[-1] != 3:
            problems.append(f"{where(path, 'data/img')}: expected uint8 (N, H, W, 3) frames, got {a.dtype} {a.shape}.")
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
    if "img" in shapes and len(shapes["img"]) == 4:
        h, w = shapes["img"][1:3]
        if not (size == [h, w] or (h == w and size == h)):
            problems.append(f"{path}: attribute 'image_size' is {size!r}; data/img holds {h}x{w} frames.")
    elif size is None:
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
