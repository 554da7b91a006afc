"""ALOHA/ACT and robomimic HDF5: export to ALOHA, import both, validate both.

ALOHA / ACT, one file per episode ``episode_<i>.hdf5``, as act-plus-plus
(``record_sim_episodes.py``, ``compress_data.py``) and the ALOHA recorders write it::

    attrs                        sim (bool), compress (bool; absent in older files); ours
                                 also fps, task, action_names, seed and, with several
                                 cameras, cameras (JSON: their names in view order)
    /observations/images/<cam>   (T, H, W, 3) uint8, or when compressed (T, L) uint8: one
                                 JPEG per row, padded with zeros to the longest
    /observations/qpos           (T, S) float32 (h5py's default dtype; 14 on ALOHA)
    /observations/qvel           (T, S) float32
    /action                      (T, A) float32
    /base_action                 (T, 2) float32, Mobile ALOHA only
    /compress_len                (n_cams, T) float32, compressed files only: JPEG byte lengths

robomimic, one file (robomimic docs/datasets/overview.md)::

    data                         attrs: total, env_args (JSON: env_name, env_type, env_kwargs)
    data/demo_<i>/actions        (T, A)
    data/demo_<i>/obs/<key>      (T, ...): images ``*_image`` (T, H, W, 3) uint8, low-dim (T, D)

Cameras: an ALOHA export writes each view of the store as ``/observations/images/<name>``
(a store of one view as ``top``, ACT's simulated camera, as ever). An import without
``camera`` reads every RGB camera: ALOHA's in the order of the file's ``cameras`` attribute
when it lists them all (ours), else ``top`` first (when there is one) and the others in file
order, named as in the file (``cam_left_wrist``); robomimic's image obs keys with
``agentview_image`` first (its usual camera) and the others in name order, named without
``_image`` (``robot0_eye_in_hand_image`` -> ``robot0_eye_in_hand``). The first goes to
``img``, the others to ``img_<name>``; every episode must hold every camera.
"""

from __future__ import annotations

import io
import json
import logging
import math
import re
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import h5py
import numpy as np

from iwsim.data.formats.common import (
    FormatError,
    SourceViews,
    check_episode,
    decode_images,
    positive_int,
    reason,
    store_views,
    where,
)
from iwsim.data.store import EpisodeStore

log = logging.getLogger(__name__)

ALOHA_FPS = 50  # act-plus-plus constants.py: DT = 0.02
ROBOMIMIC_FPS = 20  # robosuite's default control_freq, kept in env_args.env_kwargs when recorded
ALOHA_CAMERA = "top"  # the camera of ACT's simulated tasks, and the name of a one-view store's export
ROBOMIMIC_CAMERA = "agentview_image"  # robomimic's usual camera, imported first
ROBOMIMIC_IMAGE_SUFFIX = "_image"  # robomimic's image obs keys end so; a view's name drops it
_ARM = ("waist", "shoulder", "elbow", "forearm_roll", "wrist_angle", "wrist_rotate", "gripper")
ALOHA_ACTION_NAMES = [f"{side}_{joint}" for side in ("left", "right") for joint in _ARM]
MOBILE_BASE_NAMES = ["linear_vel", "angular_vel"]
# A compressed dataset cannot honestly expand by more than this (deflate tops out near 1032:1);
# a larger claim means a damaged header, and reading it would allocate the claimed size.
_MAX_EXPANSION = 1100
# What h5py, libhdf5 and Pillow raise on a damaged file; each becomes one FormatError line.
_READ_ERRORS = (OSError, KeyError, ValueError, TypeError, IndexError, RuntimeError, MemoryError)


def _open(path: Path, episode: int | None = None) -> h5py.File:
    try:
        return h5py.File(path, "r")
    except _READ_ERRORS as e:
        raise FormatError(f"{where(path, episode=episode)}: not a readable HDF5 file ({reason(e)}).") from None


def _dataset(group: h5py.Group, key: str, at: str) -> h5py.Dataset:
    node = group.get(key)
    if not isinstance(node, h5py.Dataset):
        raise FormatError(f"{at}: missing." if node is None else f"{at}: is a group, not a dataset.")
    return node


def _read(ds: h5py.Dataset, at: str, file_size: int) -> np.ndarray:
    """All of ``ds``, after checking its header does not claim more data than the file can hold."""
    nbytes = math.prod(ds.shape) * ds.dtype.itemsize
    limit = file_size * (_MAX_EXPANSION if ds.compression else 1)
    if nbytes > limit:
        raise FormatError(f"{at}: claims {nbytes} bytes but the file holds {file_size}; it is truncated or damaged.")
    return ds[()]


def _attr_text(value: Any) -> str | None:
    if isinstance(value, bytes):
        return value.decode("utf-8", "replace")
    return value if isinstance(value, str) else None


def _attr_names(value: Any) -> list[str] | None:
    """A list of names stored as a JSON string or an array of strings; None if neither."""
    text = _attr_text(value)
    if text is not None:
        try:
            value = json.loads(text)
        except json.JSONDecodeError:
            return None
    if isinstance(value, np.ndarray):
        value = value.tolist()
    if isinstance(value, list) and all(isinstance(v, (str, bytes)) for v in value):
        return [v.decode() if isinstance(v, bytes) else v for v in value]
    return None


def _square_or_hw(h: int, w: int) -> int | list[int]:
    """The store's ``image_size`` attribute: the side of square frames, else [H, W]."""
    return int(h) if h == w else [int(h), int(w)]


# --- ALOHA: export ---------------------------------------------------------------------------
def export_aloha(store: EpisodeStore, out: Path, *, fps: int, task: str, progress: bool) -> None:
    """Write each episode of ``store`` to ``out/episode_<i>.hdf5`` in ACT's uncompressed layout:
    ``/observations/images/<camera>`` (T, H, W, 3) uint8 per view (``top`` for a store of one
    view), ``/observations/qpos`` (T, S) and ``/action`` (T, A) float32; root attrs sim,
    compress, fps, task (and action_names, seed, and cameras when there are several)."""
    from tqdm import tqdm

    keys = store_views(store)
    if len(keys) == 1:
        keys = {ALOHA_CAMERA: next(iter(keys.values()))}
    names = store.attrs.get("action_names")
    seeds = store.seeds
    for i in tqdm(range(store.n_episodes), unit="ep", desc=f"export {out.name}", disable=not progress):
        ep = check_episode(store.episode(i), where(store.path, episode=i), tuple(keys.values()))
        state = ep["state"]
        # Built in memory, then written by Python: the HDF5 library on a full disk crashed
        # the process (segmentation fault); a failed Python write is an OSError, one line.
        image = io.BytesIO()
        with h5py.File(image, "w") as f:
            f.attrs["sim"] = True  # ACT aligns sim actions with their frame (real ones one step earlier)
            f.attrs["compress"] = False
            f.attrs["fps"] = int(fps)
            f.attrs["task"] = task
            if names:
                f.attrs["action_names"] = json.dumps([str(n) for n in names])
            if seeds[i] is not None:
                f.attrs["seed"] = int(seeds[i])
            if len(keys) > 1:  # the view order (h5py lists datasets by name)
                f.attrs["cameras"] = json.dumps(list(keys))
            for cam, key in keys.items():
                # One frame per chunk, as ACT writes them: its loader reads one time step at a time.
                img = ep[key]
                f.create_dataset(f"observations/images/{cam}", data=img, chunks=(1, *img.shape[1:]))
            f.create_dataset("observations/qpos", data=state)
            # ACT's loaders read qvel unconditionally but never use it; zeros keep them working.
            f.create_dataset("observations/qvel", data=np.zeros_like(state))
            f.create_dataset("action", data=ep["action"])
        with open(out / f"episode_{i}.hdf5", "wb") as file:
            file.write(image.getbuffer())


# --- ALOHA: import ---------------------------------------------------------------------------
def _episode_order(path: Path) -> tuple[int, int, str]:
    """Sort key: the last integer in the file name (episode_12 -> 12), unnumbered files last."""
    numbers = re.findall(r"\d+", path.stem)
    return (0, int(numbers[-1]), path.name) if numbers else (1, 0, path.name)


def _aloha_files(src: Path) -> list[Path]:
    if src.is_file():
        return [src]
    files = sorted((p for p in src.iterdir() if p.suffix in (".hdf5", ".h5") and p.is_file()), key=_episode_order)
    if not files:
        raise FormatError(f"{src} holds no .hdf5 files; expected ALOHA episode_<i>.hdf5 files.")
    return files


def _rgb_cameras(images: h5py.Group) -> list[str]:
    """Camera names in file order (h5py lists by name), depth cameras left out as ACT does."""
    return [name for name in images if "depth" not in name]


def _pick_cameras(cameras: list[str], camera: str | None, at: str, order: list[str] | None = None) -> list[str]:
    """The cameras to read: ``camera``, else all of them, in ``order`` (the file's
    ``cameras`` attribute) when it lists them all, else "top" first and the rest in file order."""
    if camera is not None:
        if camera not in cameras:
            raise FormatError(f"{at}: no camera {camera!r}; it has {', '.join(cameras) or 'none'}.")
        return [camera]
    if not cameras:
        raise FormatError(f"{at}: holds no RGB camera.")
    if order is not None and sorted(order) == sorted(cameras):
        return list(order)
    return sorted(cameras, key=lambda c: c != ALOHA_CAMERA)  # stable: the rest keep file order


def _decode_jpegs(rows: np.ndarray, at: str, frame_ids: list[int] | None = None) -> np.ndarray:
    """(T, L) uint8 rows of zero-padded JPEG bytes -> (T, H, W, 3) uint8 frames, as ACT sees them.

    Each row is decoded whole, as ACT's loader does (JPEG decoders stop at the end-of-image
    marker), so /compress_len is not needed: its rows follow the writer's camera order, which
    is the task's camera list in record_episodes.py but h5py's sorted order in compress_data.py.

    act-plus-plus encodes its RGB arrays with ``cv2.imencode('.jpg', image)``, which takes them
    for BGR, and decodes with ``cv2.imdecode``, which returns BGR: the round trip gives back its
    RGB arrays. Pillow decodes the JPEG's true colours, i.e. with R and B swapped relative to
    those arrays, so the channels are reversed here. ``frame_ids`` name the rows in messages.
    """
    frames = decode_images([row.tobytes() for row in rows], at, formats=("JPEG",), ids=frame_ids)
    return np.ascontiguousarray(frames[..., ::-1])


def _aloha_frames(f: h5py.File, cam: str, path: Path, i: int, size: int) -> np.ndarray:
    key = f"observations/images/{cam}"
    at = where(path, key, i)
    data = _read(_dataset(f, key, at), at, size)
    if data.ndim == 2 and data.dtype == np.uint8:  # JPEG rows (compressed variant)
        return _decode_jpegs(data, at)
    return data


def _read_aloha_file(path: Path, i: int, cams: SourceViews) -> tuple[dict[str, np.ndarray], int | None]:
    with _open(path, i) as f:
        try:
            size = path.stat().st_size
            images = f.get("observations/images")
            if not isinstance(images, h5py.Group):
                raise FormatError(f"{where(path, 'observations/images', i)}: missing.")
            have = _rgb_cameras(images)
            for cam in cams.sources:
                _pick_cameras(have, cam, where(path, "observations/images", i))
            ep = {
                **{key: _aloha_frames(f, cam, path, i, size) for cam, key in cams.keys.items()},
                "state": _read(_dataset(f, "observations/qpos", where(path, "observations/qpos", i)),
                               where(path, "observations/qpos", i), size),
                "action": _read(_dataset(f, "action", where(path, "action", i)), where(path, "action", i), size),
            }
            if "base_action" in f:  # Mobile ALOHA: ACT trains on [action, base_action]
                at = where(path, "base_action", i)
                base = _read(_dataset(f, "base_action", at), at, size)
                if base.ndim != 2 or ep["action"].ndim != 2 or len(base) != len(ep["action"]):
                    raise FormatError(f"{at}: expected (T, 2) next to action {ep['action'].shape}, got {base.shape}.")
                ep["action"] = np.concatenate([ep["action"], base], axis=1)
            seed = f.attrs.get("seed")
        except FormatError:
            raise
        except _READ_ERRORS as e:
            raise FormatError(f"{where(path, episode=i)}: unreadable ({reason(e)}).") from None
    seed = int(seed) if isinstance(seed, (int, np.integer)) else None
    return check_episode(ep, where(path, episode=i), tuple(cams.keys.values())), seed


def _aloha_episodes(files: list[Path], cams: SourceViews) -> Iterator[tuple[dict[str, np.ndarray], int | None]]:
    dims: tuple[int, int] | None = None
    for i, path in enumerate(files):
        ep, seed = _read_aloha_file(path, i, cams)
        got = (ep["state"].shape[1], ep["action"].shape[1])
        if dims is None:
            dims = got
        elif got != dims:
            raise FormatError(f"{where(path, episode=i)}: qpos/action have {got[0]}/{got[1]} dims per step; "
                              f"episode 0 has {dims[0]}/{dims[1]}.")
        yield ep, seed


def read_aloha(src: Path, *, camera: str | None) -> tuple[dict, int, Iterator[tuple[dict, int | None]]]:
    """ALOHA/ACT episodes from a directory of ``episode_<i>.hdf5`` files (in the order of the
    number in their names) or one such file: ``img`` (T, H, W, 3) uint8 from
    ``/observations/images/<camera>`` (JPEG-compressed files are decoded) and ``img_<name>``
    from each further camera (see the module docstring; ``camera`` reads that one only),
    ``state`` (T, S) from ``/observations/qpos``, ``action`` (T, A) from ``/action``."""
    src = Path(src)
    files = _aloha_files(src)
    first = files[0]
    with _open(first, 0) as f:
        try:
            images = f.get("observations/images")
            if not isinstance(images, h5py.Group):
                raise FormatError(f"{where(first, 'observations/images', 0)}: missing; expected ALOHA's "
                                  "/observations/images/<camera> datasets.")
            cams = SourceViews.of(_pick_cameras(_rgb_cameras(images), camera, where(first, "observations/images", 0),
                                                _attr_names(f.attrs.get("cameras"))))
            cam = cams.sources[0]
            img = _dataset(images, cam, where(first, f"observations/images/{cam}", 0))
            if img.ndim == 4:
                h, w = img.shape[1:3]
            else:  # JPEG rows: the frame size is in the first frame
                h, w = _aloha_frames(f, cam, first, 0, first.stat().st_size).shape[1:3]
            action = _dataset(f, "action", where(first, "action", 0))
            a_dim = action.shape[-1] if action.ndim == 2 else 0
            has_base = "base_action" in f
            root = dict(f.attrs)
        except FormatError:
            raise
        except _READ_ERRORS as e:
            raise FormatError(f"{where(first, episode=0)}: unreadable ({reason(e)}).") from None
    attrs: dict[str, Any] = {
        "task": _attr_text(root.get("task")) or (src if src.is_dir() else src.parent).name,
        "fps": positive_int(root.get("fps")) or ALOHA_FPS,
        **cams.attrs(),
        "image_size": _square_or_hw(h, w),
    }
    names = _attr_names(root.get("action_names"))
    if names is None and a_dim == len(ALOHA_ACTION_NAMES):
        names = ALOHA_ACTION_NAMES + (MOBILE_BASE_NAMES if has_base else [])
    if names is not None:
        attrs["action_names"] = names
    if isinstance(root.get("sim"), (bool, np.bool_, int, np.integer)):
        attrs["sim"] = bool(root["sim"])
    return attrs, len(files), _aloha_episodes(files, cams)


# --- robomimic: import -----------------------------------------------------------------------
def _demo_names(f: h5py.File, src: Path) -> list[str]:
    data = f.get("data")
    if not isinstance(data, h5py.Group):
        raise FormatError(f"{where(src, 'data')}: missing; expected robomimic's data/demo_<i> groups.")
    demos = [k for k in data if re.fullmatch(r"demo_\d+", k)]
    if not demos:
        raise FormatError(f"{where(src, 'data')}: holds no demo_<i> groups.")
    return sorted(demos, key=lambda k: int(k[5:]))  # robomimic's SequenceDataset sorts them this way


def _is_image(name: str, ds: h5py.Dataset) -> bool:
    return name.endswith("_image") or (ds.ndim == 4 and ds.shape[-1] == 3)


def _obs_keys(obs: h5py.Group) -> tuple[list[str], list[tuple[str, int]]]:
    """(image keys, [(low-dim key, size)]) of one demo's obs group, each sorted by name.
    Low-dim keys are numeric datasets of one vector (or number) per step."""
    images, lowdim = [], []
    for name in sorted(obs):
        ds = obs[name]
        if not isinstance(ds, h5py.Dataset):
            continue
        if _is_image(name, ds):
            images.append(name)
        elif ds.ndim in (1, 2) and (np.issubdtype(ds.dtype, np.number) or ds.dtype == bool):
            lowdim.append((name, int(ds.shape[1]) if ds.ndim == 2 else 1))
    return images, lowdim


def _env_args(data: h5py.Group, src: Path) -> dict[str, Any]:
    text = _attr_text(data.attrs.get("env_args"))
    if text is None:
        return {}
    try:
        args = json.loads(text)
    except json.JSONDecodeError:
        log.warning("%s: data.attrs['env_args'] is not JSON; ignored", src)
        return {}
    return args if isinstance(args, dict) else {}


def _read_demo(f: h5py.File, src: Path, i: int, demo: str, cams: SourceViews,
               state_keys: list[tuple[str, int]], size: int) -> dict[str, np.ndarray]:
    base = f"data/{demo}"
    at = where(src, f"{base}/actions", i)
    actions = _read(_dataset(f, f"{base}/actions", at), at, size)
    t = len(actions) if actions.ndim else 0
    if t == 0:
        raise FormatError(f"{where(src, base, i)}: the episode is empty.")
    obs = f.get(f"{base}/obs")
    if not isinstance(obs, h5py.Group):
        raise FormatError(f"{where(src, f'{base}/obs', i)}: missing.")

    def steps(key: str) -> np.ndarray:
        at = where(src, f"{base}/obs/{key}", i)
        value = _read(_dataset(obs, key, at), at, size)
        n = len(value) if value.ndim else 0
        if n != t:
            raise FormatError(f"{at}: {n} steps, but actions has {t}.")
        return value

    parts = []
    for key, dim in state_keys:
        value = steps(key)
        if not (np.issubdtype(value.dtype, np.number) or value.dtype == bool) or value.reshape(t, -1).shape[1] != dim:
            raise FormatError(f"{where(src, f'{base}/obs/{key}', i)}: expected {dim} numbers per step (as in "
                              f"the first demo), got {value.dtype} {value.shape}.")
        parts.append(value.reshape(t, dim).astype(np.float32))
    ep = {**{key: steps(cam) for cam, key in cams.keys.items()}, "state": np.concatenate(parts, axis=1),
          "action": actions}
    return check_episode(ep, where(src, base, i), tuple(cams.keys.values()))


def _robomimic_episodes(src: Path, demos: list[str], cams: SourceViews,
                        state_keys: list[tuple[str, int]]) -> Iterator[tuple[dict, int | None]]:
    with _open(src) as f:
        size = src.stat().st_size
        a_dim: int | None = None
        for i, demo in enumerate(demos):
            try:
                ep = _read_demo(f, src, i, demo, cams, state_keys, size)
            except FormatError:
                raise
            except _READ_ERRORS as e:
                raise FormatError(f"{where(src, f'data/{demo}', i)}: unreadable ({reason(e)}).") from None
            a_dim = a_dim or ep["action"].shape[1]
            if ep["action"].shape[1] != a_dim:
                raise FormatError(f"{where(src, f'data/{demo}/actions', i)}: {ep['action'].shape[1]} dims per step; "
                                  f"the first demo has {a_dim}.")
            yield ep, None


def read_robomimic(src: Path, *, camera: str | None) -> tuple[dict, int, Iterator[tuple[dict, int | None]]]:
    """robomimic demos (``data/demo_<i>``, in the order of i): ``img`` (T, H, W, 3) uint8 and
    ``img_<name>`` from the image obs keys (see the module docstring; ``camera`` reads that
    key only), ``state`` (T, S) the low-dimensional obs keys concatenated in sorted order
    (listed with their sizes in the ``state_keys`` attribute), ``action`` (T, A) from
    ``actions``."""
    src = Path(src)
    if src.is_dir():
        raise FormatError(f"{src} is a directory; a robomimic dataset is one .hdf5 file.")
    with _open(src) as f:
        try:
            demos = _demo_names(f, src)
            at = where(src, f"data/{demos[0]}/obs", 0)
            obs = f.get(f"data/{demos[0]}/obs")
            if not isinstance(obs, h5py.Group):
                raise FormatError(f"{at}: missing.")
            image_keys, state_keys = _obs_keys(obs)
            if camera is not None:
                if camera not in obs:
                    raise FormatError(f"{at}: no obs key {camera!r}; image keys: {', '.join(image_keys) or 'none'}.")
                chosen = [camera]
            elif image_keys:
                chosen = sorted(image_keys, key=lambda k: k != ROBOMIMIC_CAMERA)  # stable: the rest by name
            else:
                raise FormatError(f"{at}: no image observations (*_image keys of (T, H, W, 3) frames).")
            cams = SourceViews.of(chosen, suffixes=(ROBOMIMIC_IMAGE_SUFFIX,))
            state_keys = [(k, d) for k, d in state_keys if k not in chosen]
            if not state_keys:
                raise FormatError(f"{at}: no low-dimensional observations to use as the state.")
            shapes = {cam: _dataset(obs, cam, where(src, f"data/{demos[0]}/obs/{cam}", 0)).shape for cam in chosen}
            env_args = _env_args(f["data"], src)
        except FormatError:
            raise
        except _READ_ERRORS as e:
            raise FormatError(f"{src}: unreadable ({reason(e)}).") from None
    for cam, shape in shapes.items():
        if len(shape) != 4:
            raise FormatError(f"{where(src, f'data/{demos[0]}/obs/{cam}', 0)}: expected (T, H, W, 3) frames, "
                              f"got {shape}.")
    shape = shapes[chosen[0]]
    env_kwargs = env_args.get("env_kwargs")
    kwargs = env_kwargs if isinstance(env_kwargs, dict) else {}
    attrs: dict[str, Any] = {
        "task": str(env_args.get("env_name") or src.stem),
        "fps": positive_int(kwargs.get("control_freq")) or ROBOMIMIC_FPS,
        **cams.attrs(),
        "image_size": _square_or_hw(shape[1], shape[2]),
        "state_keys": [[k, d] for k, d in state_keys],
    }
    if env_args:
        attrs["env_args"] = env_args
    return attrs, len(demos), _robomimic_episodes(src, demos, cams, state_keys)


# --- validation ------------------------------------------------------------------------------
def _is_float(dtype: np.dtype) -> bool:
    return np.issubdtype(dtype, np.floating)


def _aloha_problems(f: h5py.File, path: Path, i: int, dims: dict[str, Any]) -> list[str]:
    """What is wrong with one ALOHA episode file, each camera's frames on their own; ``dims``
    carries the first file's sizes and cameras."""
    problems: list[str] = []
    size = path.stat().st_size
    lengths: dict[str, int] = {}
    for key in ("action", "observations/qpos"):
        at = where(path, key, i)
        ds = f.get(key)
        if not isinstance(ds, h5py.Dataset):
            problems.append(f"{at}: missing.")
            continue
        if ds.ndim != 2 or not _is_float(ds.dtype):
            problems.append(f"{at}: expected floats of shape (T, D), got {ds.dtype} {ds.shape}.")
            continue
        lengths[key] = ds.shape[0]
        if not np.isfinite(_read(ds, at, size)).all():
            problems.append(f"{at}: holds non-finite values.")
        first = dims.setdefault(key, ds.shape[1])
        if ds.shape[1] != first:
            problems.append(f"{at}: {ds.shape[1]} dims per step; the first episode has {first}.")
    images = f.get("observations/images")
    if not isinstance(images, h5py.Group) or not len(images):
        problems.append(f"{where(path, 'observations/images', i)}: missing (no cameras).")
        images = {}
    rgb = sorted(c for c in images if "depth" not in c)
    first_cams = dims.setdefault("cameras", rgb) if rgb else rgb
    if rgb != first_cams:
        problems.append(f"{where(path, 'observations/images', i)}: cameras {', '.join(rgb) or 'none'}; the first "
                        f"episode has {', '.join(first_cams) or 'none'} (an import reads every camera of each).")
    jpeg_cams = 0
    for cam in images:
        key = f"observations/images/{cam}"
        at = where(path, key, i)
        ds = images[cam]
        if not isinstance(ds, h5py.Dataset):
            problems.append(f"{at}: is a group, not a dataset.")
            continue
        lengths[key] = ds.shape[0] if ds.ndim else 0
        if "depth" in cam:
            continue
        if ds.dtype != np.uint8 or not (ds.ndim == 2 or (ds.ndim == 4 and ds.shape[-1] == 3)):
            problems.append(f"{at}: expected uint8 (T, H, W, 3) frames or (T, L) JPEG rows, "
                            f"got {ds.dtype} {ds.shape}.")
            continue
        if not ds.shape[0]:
            continue
        try:
            if ds.ndim == 2:
                jpeg_cams += 1
                ends = [0, ds.shape[0] - 1]
                # Decoding every frame would take minutes on real datasets; the ends show truncation.
                _decode_jpegs(_read(ds, at, size)[ends], at, ends)
            else:
                ds[0], ds[-1]  # noqa: B018 - reads the ends to find missing data
        except FormatError as e:
            problems.append(str(e))
    if jpeg_cams and "compress_len" in f:
        at = where(path, "compress_len", i)
        cl = f["compress_len"]
        t = max(lengths.values())
        if not isinstance(cl, h5py.Dataset) or cl.shape != (jpeg_cams, t) or not np.issubdtype(cl.dtype, np.number):
            problems.append(f"{at}: expected numbers of shape (cameras={jpeg_cams}, T={t}), "
                            f"got {getattr(cl, 'dtype', 'a group')} {getattr(cl, 'shape', '')}.")
        else:
            widths = [ds.shape[1] for ds in images.values() if isinstance(ds, h5py.Dataset) and ds.ndim == 2]
            values = _read(cl, at, size)
            if not (np.isfinite(values).all() and (values > 0).all() and (values <= max(widths)).all()):
                problems.append(f"{at}: lengths must lie in 1..{max(widths)} (the JPEG rows' width).")
    if lengths and len(set(lengths.values())) != 1:
        problems.append(f"{where(path, episode=i)}: datasets differ in length: {lengths}.")
    if lengths and min(lengths.values()) == 0:
        problems.append(f"{where(path, episode=i)}: the episode is empty.")
    return problems


def _robomimic_problems(f: h5py.File, path: Path) -> list[str]:
    try:
        demos = _demo_names(f, path)
    except FormatError as e:
        return [str(e)]
    problems: list[str] = []
    size = path.stat().st_size
    a_dim: int | None = None
    lowdim: dict[str, int] = {}
    first_images: list[str] | None = None
    for i, demo in enumerate(demos):
        base = f"data/{demo}"
        try:
            ds = f.get(f"{base}/actions")
            if not isinstance(ds, h5py.Dataset):
                problems.append(f"{where(path, f'{base}/actions', i)}: missing.")
                t = None
            elif ds.ndim != 2 or not _is_float(ds.dtype):
                problems.append(f"{where(path, f'{base}/actions', i)}: expected floats of shape (T, A), "
                                f"got {ds.dtype} {ds.shape}.")
                t = ds.shape[0] if ds.ndim else None
            else:
                t = ds.shape[0]
                if not np.isfinite(_read(ds, where(path, f"{base}/actions", i), size)).all():
                    problems.append(f"{where(path, f'{base}/actions', i)}: holds non-finite values.")
                a_dim = a_dim or ds.shape[1]
                if ds.shape[1] != a_dim:
                    problems.append(f"{where(path, f'{base}/actions', i)}: {ds.shape[1]} dims per step; "
                                    f"the first demo has {a_dim}.")
            if t == 0:
                problems.append(f"{where(path, base, i)}: the episode is empty.")
            n = f[base].attrs.get("num_samples")
            if t is not None and isinstance(n, (int, np.integer)) and int(n) != t:
                problems.append(f"{where(path, base, i)}: num_samples is {n} but actions holds {t} steps.")
            obs = f.get(f"{base}/obs")
            if not isinstance(obs, h5py.Group):
                problems.append(f"{where(path, f'{base}/obs', i)}: missing.")
                continue
            images: list[str] = []
            for key in sorted(obs):
                at = where(path, f"{base}/obs/{key}", i)
                ds = obs[key]
                if not isinstance(ds, h5py.Dataset):
                    continue
                if t is not None and (ds.shape[0] if ds.ndim else 0) != t:
                    problems.append(f"{at}: {ds.shape[0] if ds.ndim else 0} steps, but actions has {t}.")
                if _is_image(key, ds):
                    images.append(key)
                    if ds.dtype != np.uint8 or ds.ndim != 4 or ds.shape[-1] != 3:
                        problems.append(f"{at}: expected uint8 (T, H, W, 3) frames, got {ds.dtype} {ds.shape}.")
                elif ds.ndim in (1, 2):
                    d = int(ds.shape[1]) if ds.ndim == 2 else 1
                    first = lowdim.setdefault(key, d)
                    if d != first:
                        problems.append(f"{at}: {d} numbers per step; the first demo has {first}.")
            if not images:
                problems.append(f"{where(path, f'{base}/obs', i)}: no image observations (*_image).")
            elif first_images is None:
                first_images = images
            elif images != first_images:
                problems.append(f"{where(path, f'{base}/obs', i)}: image keys {', '.join(images)}; the first demo "
                                f"has {', '.join(first_images)} (an import reads every camera of each).")
        except FormatError as e:
            problems.append(str(e))
        except _READ_ERRORS as e:
            problems.append(f"{where(path, base, i)}: unreadable ({reason(e)}).")
    return problems


def _file_problems(path: Path, i: int | None, dims: dict[str, Any]) -> tuple[str, list[str]]:
    """(kind, problems) of one HDF5 file; ``i`` is its episode index within an ALOHA directory."""
    try:
        f = _open(path, i)
    except FormatError as e:
        return "hdf5", [str(e)]
    with f:
        try:
            if i is None and isinstance(f.get("data"), h5py.Group):
                return "robomimic", _robomimic_problems(f, path)
            if i is None and "action" not in f and "observations" not in f:
                return "hdf5", [f"{path}: neither ALOHA (/action, /observations) nor robomimic (/data/demo_<i>)."]
            return "hdf5-aloha", _aloha_problems(f, path, i or 0, dims)
        except FormatError as e:
            return "hdf5-aloha", [str(e)]
        except _READ_ERRORS as e:
            return "hdf5", [f"{where(path, episode=i)}: unreadable ({reason(e)})."]


def validate_hdf5(path: Path) -> tuple[str, list[str]]:
    """(kind, problems) for ALOHA files (a directory of episode_<i>.hdf5 or one file; kind
    "hdf5-aloha") or a robomimic file ("robomimic"): one line per problem naming file, key and
    episode; no problems if valid. JPEG frames are decoded at each episode's ends only."""
    path = Path(path)
    if path.is_file():
        return _file_problems(path, None, {})
    try:
        files = _aloha_files(path)
    except FormatError as e:
        return "hdf5-aloha", [str(e)]
    dims: dict[str, Any] = {}
    problems: list[str] = []
    for i, file in enumerate(files):
        problems += _file_problems(file, i, dims)[1]
    return "hdf5-aloha", problems
