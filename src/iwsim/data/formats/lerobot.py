"""LeRobotDataset v3.0 and v2.1, written and read without the ``lerobot`` package.

v3.0 (LeRobot's current layout; many episodes per file)::

    meta/info.json                          codebase_version "v3.0", fps, features, totals,
                                            chunks_size, file size limits, data_path, video_path, splits
    meta/stats.json                         per feature: min, max, mean, std, count, q01 q10 q50 q90 q99
    meta/tasks.parquet                      task_index, indexed by the task string
    meta/episodes/chunk-000/file-000.parquet  one row per episode: length, tasks, the data and
                                            video files it lives in, its rows and timestamps there,
                                            and its own stats (stats/<feature>/<stat>)
    data/chunk-000/file-000.parquet         observation.state, action, timestamp, frame_index,
                                            episode_index, index, task_index
    videos/observation.image/chunk-000/file-000.mp4   H.264, yuv420p, all episodes back to back

v2.1 (one file per episode; JSON-lines metadata)::

    meta/info.json, meta/episodes.jsonl, meta/tasks.jsonl, meta/episodes_stats.jsonl
    data/chunk-000/episode_000000.parquet
    videos/chunk-000/observation.image/episode_000000.mp4

Cameras: a store of one view exports it as the feature ``observation.image`` (as ever); a
store of several views (:mod:`iwsim.data.views`) exports one video feature
``observation.images.<name>`` per view, in view order, each with its own video files (in
v3 its own chunk and file indices per episode, LeRobot's ``videos/<feature>/...`` columns;
in v2.1 ``total_videos`` counts episodes x cameras). An import reads every ``video`` or
``image`` feature in info.json's order, the first into ``img``, or the one ``camera`` names.

Checked against LeRobot's ``src/lerobot/datasets/utils.py`` (path templates, default
features, ``create_empty_dataset_info``), ``compute_stats.py`` (stats keys and the image
stats' (3, 1, 1) shape in [0, 1]), ``dataset_metadata.py`` (tasks.parquet indexed by task)
and ``video_utils.py`` (the video ``info`` block); the import also against a dataset of two
cameras that LeRobot 0.4.4's own writer made (``tests/data/lerobot_two_cameras``, AV1 video,
written by ``scripts/lerobot_two_camera_fixture.py``).
"""

from __future__ import annotations

import json
import math
import os
import re
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from iwsim.core.errors import InputError
from iwsim.data import views
from iwsim.data.formats.common import (
    FormatError,
    SourceViews,
    check_episode,
    decode_images,
    positive_int,
    read_meta,
    store_episodes,
    store_views,
    where,
)
from iwsim.data.formats.video import CODEC_NAME, PIX_FMT, VideoWriter, read_video, write_episode_video
from iwsim.data.store import EpisodeStore

V3, V21 = "v3.0", "v2.1"
CHUNKS_SIZE = 1000  # files per chunk directory
DATA_FILE_MB, VIDEO_FILE_MB = 100, 500  # when a v3 data or video file is full, the next episode starts a new one
V3_DATA = "data/chunk-{chunk_index:03d}/file-{file_index:03d}.parquet"
V3_VIDEO = "videos/{video_key}/chunk-{chunk_index:03d}/file-{file_index:03d}.mp4"
V3_EPISODES = "meta/episodes/chunk-{chunk_index:03d}/file-{file_index:03d}.parquet"
V21_DATA = "data/chunk-{episode_chunk:03d}/episode_{episode_index:06d}.parquet"
V21_VIDEO = "videos/chunk-{episode_chunk:03d}/{video_key}/episode_{episode_index:06d}.mp4"
IMAGE = "observation.image"  # the feature of a store's only view
IMAGES = "observation.images"  # a store of several views: observation.images.<name> each
STATE, ACTION = "observation.state", "action"
FLOAT_DTYPES = ("float32", "float64", "float16")  # of the state and action features
INDEX_FEATURES = {"timestamp": "float32", "frame_index": "int64", "episode_index": "int64", "index": "int64",
                  "task_index": "int64"}
QUANTILES = {"q01": 0.01, "q10": 0.10, "q50": 0.50, "q90": 0.90, "q99": 0.99}
STATS_FRAMES = 100  # at most this many frames (evenly spaced) per image statistic, as LeRobot samples


# -- path templates -------------------------------------------------------------------------

# A template is literal path text and fields: {name} or, for integers, {name:Nd} / {name:0Nd}.
# Parsed here, never given to str.format: Python's format mini-language would evaluate
# attribute and index lookups ("{chunk_index.__class__.__mro__}") from an untrusted file.
_FIELD = re.compile(r"\{([a-z_]+)(?::(0?)([1-9]\d?)d)?\}")
_LITERAL = re.compile(r"[A-Za-z0-9_.\-/]*")  # path characters only: no braces, backslashes or NUL
TEMPLATE_FIELDS = {"episode_chunk": int, "episode_index": int, "chunk_index": int, "file_index": int,
                   "video_key": str}


@dataclass(frozen=True)
class PathTemplate:
    """A LeRobot ``data_path`` / ``video_path`` template, parsed with a strict grammar; see
    :meth:`parse`. :meth:`resolve` gives paths that stay inside the dataset root."""

    text: str
    parts: tuple[str | tuple[str, str, int], ...]  # literal text, or (field, zero pad "0"/"", width)
    at: str  # where the template came from, for errors

    @classmethod
    def parse(cls, text: object, fields: tuple[str, ...], at: str) -> PathTemplate:
        """``text`` as a relative path template using only ``fields`` (integers may carry a
        width); else a FormatError naming it."""
        expected = (f"expected a relative path using only {', '.join('{' + f + '}' for f in fields)} "
                    "(integers may have a width, e.g. {episode_index:06d})")
        if not isinstance(text, str):
            raise FormatError(f"{at}: {text!r} is not a path template; {expected}.")
        parts: list[str | tuple[str, str, int]] = []
        pos = 0
        for m in _FIELD.finditer(text):
            parts.append(text[pos:m.start()])
            name, zero, width = m.group(1), m.group(2), m.group(3)
            if name not in fields or (width and TEMPLATE_FIELDS[name] is not int):
                raise FormatError(f"{at}: template {text!r} has the field {m.group(0)}; {expected}.")
            parts.append((name, zero or "", int(width or 0)))
            pos = m.end()
        parts.append(text[pos:])
        literals = [p for p in parts if isinstance(p, str)]
        segments = re.split(r"\{[^}]*\}", text)
        if (not all(_LITERAL.fullmatch(p) for p in literals) or text.startswith("/")
                or any(seg == ".." for piece in segments for seg in piece.split("/"))):
            raise FormatError(f"{at}: template {text!r} is not allowed; {expected}.")
        return cls(text, tuple(p for p in parts if p != ""), at)

    def resolve(self, root: Path, **values: object) -> Path:
        """The path for ``values`` under ``root``; a FormatError if it would leave ``root``
        (e.g. through a ``video_key`` of ``..`` or a symlink)."""
        out = []
        for p in self.parts:
            if isinstance(p, str):
                out.append(p)
                continue
            name, zero, width = p
            v = values[name]
            if TEMPLATE_FIELDS[name] is int:
                if isinstance(v, bool) or not isinstance(v, (int, np.integer)) or v < 0:
                    raise FormatError(f"{self.at}: {name} {v!r} is not a non-negative integer.")
                out.append(str(int(v)).rjust(width, "0" if zero else " "))
            else:
                out.append(str(v))
        path = root / "".join(out)
        real_root = os.path.realpath(root)
        if os.path.commonpath([real_root, os.path.realpath(path)]) != real_root:
            raise FormatError(f"{self.at}: template {self.text!r} leads to {''.join(out)!r}, outside the dataset "
                              f"{root}.")
        return path


def _templates(info: dict, src: Path, default_data: str, default_video: str, data_fields: tuple[str, ...],
               video_fields: tuple[str, ...]) -> tuple[PathTemplate, PathTemplate]:
    """info.json's ``data_path`` and ``video_path`` (or the defaults), parsed."""
    at = src / "meta" / "info.json"
    return (PathTemplate.parse(info.get("data_path", default_data), data_fields, where(at, "data_path")),
            PathTemplate.parse(info.get("video_path") or default_video, video_fields, where(at, "video_path")))


# -- writing ------------------------------------------------------------------------------

def video_features(store: EpisodeStore) -> dict[str, str]:
    """{video feature: the store's data array} in view order: ``observation.image`` for a
    store of one view, else ``observation.images.<name>`` per view."""
    keys = store_views(store)
    if len(keys) == 1:
        return {IMAGE: views.IMAGE_KEY}
    return {f"{IMAGES}.{name}": key for name, key in keys.items()}


def _video_feature(shape: tuple[int, ...], fps: int) -> dict:
    """info.json's entry of a video feature of (h, w, ...) frames, as LeRobot writes it."""
    h, w = int(shape[0]), int(shape[1])
    return {"dtype": "video", "shape": [h, w, 3], "names": ["height", "width", "channels"],
            "info": {"video.height": h, "video.width": w, "video.codec": CODEC_NAME, "video.pix_fmt": PIX_FMT,
                     "video.is_depth_map": False, "video.fps": fps, "video.channels": 3, "has_audio": False}}


def features(store: EpisodeStore, fps: int) -> dict[str, dict]:
    """The ``features`` block of info.json for a store's views / state / action."""
    state, action = (store.array(k) for k in ("state", "action"))
    attrs = store.attrs

    def names(key: str, dim: int) -> list[str]:
        given = attrs.get(f"{key}_names") or (attrs.get("action_names") if key == "state" else None)
        return list(given) if given is not None and len(given) == dim else [f"{key}_{i}" for i in range(dim)]

    return {
        **{feat: _video_feature(store.array(key).shape[1:3], fps) for feat, key in video_features(store).items()},
        STATE: {"dtype": "float32", "shape": [state.shape[1]], "names": names("state", state.shape[1])},
        ACTION: {"dtype": "float32", "shape": [action.shape[1]], "names": names("action", action.shape[1])},
        **{k: {"dtype": d, "shape": [1], "names": None} for k, d in INDEX_FEATURES.items()},
    }


def feature_stats(x: np.ndarray, image: bool = False) -> dict[str, np.ndarray]:
    """min, max, mean, std, count and quantiles over the first axis of (N, D) values, or per
    channel of uint8 frames (N, H, W, 3) scaled to [0, 1] with shape (3, 1, 1), as LeRobot."""
    if image:
        if len(x) > STATS_FRAMES:
            x = x[np.round(np.linspace(0, len(x) - 1, STATS_FRAMES)).astype(int)]
        v = x.reshape(-1, 3).astype(np.float64) / 255.0
        shape: tuple[int, ...] = (3, 1, 1)
    else:
        v = x.reshape(len(x), -1).astype(np.float64)
        shape = (v.shape[1],)
    out = {"min": v.min(0), "max": v.max(0), "mean": v.mean(0), "std": v.std(0)}
    out.update({k: np.quantile(v, q, axis=0) for k, q in QUANTILES.items()})
    out = {k: s.reshape(shape) for k, s in out.items()}
    out["count"] = np.array([len(x)])
    return out


def episode_columns(ep: dict[str, np.ndarray], episode: int, start: int, fps: int) -> dict[str, np.ndarray]:
    """The per-frame columns of one episode (everything but the video)."""
    t = len(ep["img"])
    frame = np.arange(t, dtype=np.int64)
    return {STATE: ep["state"].astype(np.float32), ACTION: ep["action"].astype(np.float32),
            "timestamp": (frame / fps).astype(np.float32), "frame_index": frame,
            "episode_index": np.full(t, episode, np.int64), "index": start + frame,
            "task_index": np.zeros(t, np.int64)}


def _episodes(store: EpisodeStore, fps: int, desc: str, progress: bool
              ) -> Iterator[tuple[int, dict[str, np.ndarray], dict[str, np.ndarray], int]]:
    """(index, checked episode, its per-frame columns, its first global index) per episode."""
    from tqdm import tqdm

    start = 0
    keys = tuple(video_features(store).values())
    for e, ep in enumerate(tqdm(store_episodes(store), total=store.n_episodes, desc=desc, unit="ep",
                                disable=not progress)):
        ep = check_episode(ep, where(store.path, episode=e), keys)
        yield e, ep, episode_columns(ep, e, start, fps), start
        start += len(ep["img"])


def all_stats(columns: dict[str, np.ndarray], frames: dict[str, np.ndarray]) -> dict[str, dict[str, np.ndarray]]:
    """Stats of every video feature's ``frames`` and of the per-frame ``columns``."""
    return {**{f: feature_stats(x, image=True) for f, x in frames.items()},
            **{k: feature_stats(v) for k, v in columns.items()}}


def _table(columns: dict[str, np.ndarray]):
    import pyarrow as pa

    arrays = {}
    for k, v in columns.items():
        if v.ndim == 2:  # fixed-size float lists, as HF datasets' Sequence(length=D)
            arrays[k] = pa.FixedSizeListArray.from_arrays(pa.array(v.reshape(-1)), v.shape[1])
        else:
            arrays[k] = pa.array(v)
    return pa.table(arrays)


def _jsonable(stats: dict[str, dict[str, np.ndarray]]) -> dict:
    return {f: {k: v.tolist() for k, v in s.items()} for f, s in stats.items()}


def _write_json(path: Path, obj: Any) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(obj, indent=4))


def _write_tasks_parquet(path: Path, tasks: list[str]) -> None:
    import pandas as pd

    path.parent.mkdir(parents=True, exist_ok=True)
    pd.DataFrame({"task_index": np.arange(len(tasks), dtype=np.int64)},
                 index=pd.Index(tasks, name="task")).to_parquet(path)


def _info(version: str, store: EpisodeStore, fps: int, n_tasks: int, extra: dict) -> dict:
    return {"codebase_version": version, "robot_type": store.attrs.get("robot_type"),
            "total_episodes": store.n_episodes, "total_frames": store.n_frames, "total_tasks": n_tasks,
            "chunks_size": CHUNKS_SIZE, "fps": fps, "splits": {"train": f"0:{store.n_episodes}"}, **extra,
            "features": features(store, fps)}


def export_v3(store: EpisodeStore, out: Path, *, fps: int, task: str, progress: bool) -> None:
    """Write ``store`` as a LeRobotDataset v3.0 into the empty directory ``out``."""
    import pyarrow as pa
    import pyarrow.parquet as pq

    feats = video_features(store)
    videos: dict[str, VideoWriter] = {}  # per video feature, the file being written
    file = {"data": (0, 0), **{f: (0, 0) for f in feats}}  # (chunk_index, file_index) being written
    rows: list[dict[str, np.ndarray]] = []  # the current data file's episodes
    data_bytes = 0
    episodes_meta: list[dict[str, Any]] = []
    everything: list[dict[str, np.ndarray]] = []
    sample_frames: dict[str, list[np.ndarray]] = {f: [] for f in feats}
    frame_budget = max(1, 10 * STATS_FRAMES // store.n_episodes + 1)  # ~1000 frames for the dataset stats

    def next_file(kind: str) -> None:
        c, f = file[kind]
        file[kind] = (c + 1, 0) if f + 1 == CHUNKS_SIZE else (c, f + 1)

    def flush_data() -> None:
        nonlocal rows, data_bytes
        if rows:
            c, f = file["data"]
            path = out / V3_DATA.format(chunk_index=c, file_index=f)
            path.parent.mkdir(parents=True, exist_ok=True)
            pq.write_table(_table({k: np.concatenate([r[k] for r in rows]) for k in rows[0]}), path)
            rows, data_bytes = [], 0
            next_file("data")

    for e, ep, cols, start in _episodes(store, fps, "export lerobot-v3", progress):
        t = len(ep["img"])
        rows.append(cols)
        data_bytes += sum(v.nbytes for v in cols.values())
        meta: dict[str, Any] = {"episode_index": e, "tasks": [task], "length": t,
                                "data/chunk_index": file["data"][0], "data/file_index": file["data"][1],
                                "dataset_from_index": start, "dataset_to_index": start + t}
        for feat, key in feats.items():  # each camera's video files roll over on their own, as LeRobot's
            video = videos.get(feat)
            if video is None or video.size > VIDEO_FILE_MB * 2**20:
                if video is not None:
                    video.close()
                    next_file(feat)
                c, f = file[feat]
                video = videos[feat] = VideoWriter(out / V3_VIDEO.format(video_key=feat, chunk_index=c, file_index=f),
                                                   fps, *ep[key].shape[1:3])
            from_ts = video.frames / fps
            video.write(ep[key])
            meta.update({f"videos/{feat}/chunk_index": file[feat][0], f"videos/{feat}/file_index": file[feat][1],
                         f"videos/{feat}/from_timestamp": from_ts, f"videos/{feat}/to_timestamp": from_ts + t / fps})
        meta.update({"meta/episodes/chunk_index": 0, "meta/episodes/file_index": 0})
        for feat, stats in all_stats(cols, {f: ep[k] for f, k in feats.items()}).items():
            meta.update({f"stats/{feat}/{k}": v.tolist() for k, v in stats.items()})
        episodes_meta.append(meta)
        everything.append(cols)
        pick = np.linspace(0, t - 1, min(t, frame_budget)).round().astype(int)
        for feat, key in feats.items():
            sample_frames[feat].append(ep[key][pick])
        if data_bytes > DATA_FILE_MB * 2**20:
            flush_data()
    flush_data()
    assert videos  # the store holds episodes (frame_budget divides by their count)
    for video in videos.values():
        video.close()

    path = out / V3_EPISODES.format(chunk_index=0, file_index=0)
    path.parent.mkdir(parents=True, exist_ok=True)
    pq.write_table(pa.Table.from_pylist(episodes_meta), path)
    _write_tasks_parquet(out / "meta/tasks.parquet", [task])
    merged = {k: np.concatenate([c[k] for c in everything]) for k in everything[0]}
    _write_json(out / "meta/stats.json", _jsonable(all_stats(merged, {f: np.concatenate(x)
                                                                      for f, x in sample_frames.items()})))
    _write_json(out / "meta/info.json", _info(V3, store, fps, 1, {
        "data_files_size_in_mb": DATA_FILE_MB, "video_files_size_in_mb": VIDEO_FILE_MB,
        "data_path": V3_DATA, "video_path": V3_VIDEO}))


def export_v21(store: EpisodeStore, out: Path, *, fps: int, task: str, progress: bool) -> None:
    """Write ``store`` as a LeRobotDataset v2.1 (one parquet and one mp4 per episode)."""
    import pyarrow.parquet as pq

    feats = video_features(store)
    episodes, stats_lines = [], []
    for e, ep, cols, _ in _episodes(store, fps, "export lerobot-v2.1", progress):
        t = len(ep["img"])
        chunk = e // CHUNKS_SIZE
        path = out / V21_DATA.format(episode_chunk=chunk, episode_index=e)
        path.parent.mkdir(parents=True, exist_ok=True)
        pq.write_table(_table(cols), path)
        for feat, key in feats.items():
            write_episode_video(out / V21_VIDEO.format(episode_chunk=chunk, video_key=feat, episode_index=e), ep[key],
                                fps)
        episodes.append({"episode_index": e, "tasks": [task], "length": t})
        frames = {f: ep[k] for f, k in feats.items()}
        stats = {f: {k: v for k, v in s.items() if k not in QUANTILES} for f, s in all_stats(cols, frames).items()}
        stats_lines.append({"episode_index": e, "stats": _jsonable(stats)})

    def jsonl(name: str, items: list[dict]) -> None:
        (out / "meta").mkdir(parents=True, exist_ok=True)
        (out / "meta" / name).write_text("".join(json.dumps(x) + "\n" for x in items))

    jsonl("episodes.jsonl", episodes)
    jsonl("tasks.jsonl", [{"task_index": 0, "task": task}])
    jsonl("episodes_stats.jsonl", stats_lines)
    _write_json(out / "meta/info.json", _info(V21, store, fps, 1, {
        "total_videos": store.n_episodes * len(feats), "total_chunks": math.ceil(store.n_episodes / CHUNKS_SIZE),
        "data_path": V21_DATA, "video_path": V21_VIDEO}))


# -- reading ------------------------------------------------------------------------------

def _load_info(src: Path, versions: tuple[str, ...]) -> dict:
    path = src / "meta" / "info.json"
    try:
        info = json.loads(read_meta(path))
    except FileNotFoundError:
        raise FormatError(f"{path}: missing; {src} is not a LeRobot dataset.") from None
    except (json.JSONDecodeError, UnicodeDecodeError) as e:
        raise FormatError(f"{path}: not valid JSON ({e}).") from None
    if not isinstance(info, dict):
        raise FormatError(f"{path}: expected a JSON object.")
    version = info.get("codebase_version")
    if not isinstance(version, str) or not version.startswith(versions):
        raise FormatError(f"{where(path, 'codebase_version')}: {version!r}, expected {' or '.join(versions)}.")
    for key, kind in (("fps", (int, float)), ("features", dict)):
        if not isinstance(info.get(key), kind):
            raise FormatError(f"{where(path, key)}: missing or of the wrong type.")
    if isinstance(info["fps"], bool) or positive_int(info["fps"]) is None:
        raise FormatError(f"{where(path, 'fps')}: {info['fps']!r}, expected a positive number of frames a second.")
    for key in (STATE, ACTION):
        if key not in info["features"]:
            raise FormatError(f"{where(path, 'features')}: no '{key}' feature; features are "
                              f"{sorted(info['features'])}.")
        dtype = info["features"][key].get("dtype") if isinstance(info["features"][key], dict) else None
        if dtype not in FLOAT_DTYPES:
            raise FormatError(f"{where(path, f'features.{key}.dtype')}: {dtype!r}, expected one of "
                              f"{', '.join(FLOAT_DTYPES)}.")
    return info


def _cameras(info: dict, src: Path, camera: str | None) -> SourceViews:
    """The camera features to read: ``camera`` (a feature, or ``<name>`` of
    ``observation.images.<name>``), else every video or image feature in info.json's order;
    view names by :func:`~iwsim.data.formats.common.view_name` (``observation.images.wrist``
    -> ``wrist``)."""
    cams = [k for k, f in info["features"].items() if isinstance(f, dict) and f.get("dtype") in ("video", "image")]
    if camera is not None:
        full = camera if camera in cams else f"{IMAGES}.{camera}"
        if full not in cams:
            raise FormatError(f"{src}: no camera {camera!r}; cameras are {cams}.")
        cams = [full]
    if not cams:
        raise FormatError(f"{where(src / 'meta' / 'info.json', 'features')}: no camera (a feature of dtype video or "
                          "image).")
    return SourceViews.of(cams)


def _read_parquet(path: Path):
    import pyarrow as pa
    import pyarrow.parquet as pq

    try:
        return pq.read_table(path)
    except FileNotFoundError:
        raise FormatError(f"{path}: missing.") from None
    except (pa.ArrowException, OSError) as e:
        raise FormatError(f"{path}: not a readable parquet file ({' '.join(str(e).split())[:120]}).") from None


def _column(table, key: str, path: Path, episode: int | None = None) -> np.ndarray:
    if key not in table.column_names:
        raise FormatError(f"{where(path, key, episode)}: column missing.")
    import pyarrow as pa

    col = table.column(key).combine_chunks()
    try:
        if pa.types.is_list(col.type) or pa.types.is_fixed_size_list(col.type) or pa.types.is_large_list(col.type):
            if col.null_count:
                raise InputError("null rows")
            lengths = set(np.asarray(col.value_lengths().to_numpy(zero_copy_only=False)).tolist())
            if len(lengths) > 1:
                raise InputError(f"rows of different lengths {sorted(lengths)}")
            values = np.asarray(col.flatten().to_numpy(zero_copy_only=False))
            return values.reshape(len(col), -1)
        return np.asarray(col.to_numpy(zero_copy_only=False))
    except (ValueError, TypeError) as e:
        raise FormatError(f"{where(path, key, episode)}: unexpected values ({e}).") from None


def _images(table, key: str, path: Path, episode: int) -> np.ndarray:
    """Frames of an 'image' feature stored in parquet as {bytes, path} (PNG/JPEG), decoded
    within bounds (:func:`~iwsim.data.formats.common.decode_images`)."""
    if key not in table.column_names:
        raise FormatError(f"{where(path, key, episode)}: column missing.")
    try:
        cells = [cell["bytes"] for cell in table.column(key).to_pylist()]
    except (TypeError, KeyError):
        raise FormatError(f"{where(path, key, episode)}: an image cell is not an encoded image.") from None
    return decode_images(cells, where(path, key, episode))


def _episode_from_rows(table, path: Path, e: int, cams: SourceViews, frames: dict[str, np.ndarray],
                       length: object = None) -> dict[str, np.ndarray]:
    """Episode ``e`` from its rows of a data file and the decoded ``frames`` of its video
    features (image features are decoded from the rows); ``length``: what the episode
    metadata says."""
    if length is not None and (not isinstance(length, int) or length != table.num_rows):
        raise FormatError(f"{where(path, episode=e)}: the episode metadata says length {str(length)[:40]}, the data "
                          f"file holds {table.num_rows} rows.")
    index = _column(table, "episode_index", path, e)
    if not (index == e).all():
        raise FormatError(f"{where(path, 'episode_index', e)}: rows of episode(s) "
                          f"{sorted(set(index.tolist()) - {e})[:3]} among episode {e}'s.")
    order = np.argsort(_column(table, "frame_index", path, e), kind="stable")
    ep = {"state": _column(table, STATE, path, e)[order], "action": _column(table, ACTION, path, e)[order]}
    for cam, key in cams.keys.items():
        ep[key] = frames[cam] if cam in frames else _images(table, cam, path, e)[order]
    return check_episode(ep, where(path, episode=e), tuple(cams.keys.values()))


def _attrs(info: dict, tasks: list[str], cams: SourceViews) -> dict[str, Any]:
    f = info["features"]
    attrs = {"task": tasks[0] if tasks else "", "tasks": tasks, "fps": info["fps"], **cams.attrs(),
             "action_names": f[ACTION].get("names"), "state_names": f[STATE].get("names"),
             "robot_type": info.get("robot_type")}
    hwc = _declared_hwc(f[cams.sources[0]]) if isinstance(f[cams.sources[0]].get("shape"), list) else ()
    if len(hwc) == 3 and all(isinstance(v, int) and not isinstance(v, bool) for v in hwc):
        # the frames' size as declared (an import that resizes sets its own)
        attrs["image_size"] = hwc[0] if hwc[0] == hwc[1] else [hwc[0], hwc[1]]
    return attrs


def _tasks_v3(path: Path) -> list[str]:
    """meta/tasks.parquet's task strings in ``task_index`` order. LeRobot writes a frame of
    ``task_index`` indexed by the task (``write_tasks``: ``tasks.to_parquet(path)``), an index
    it leaves unnamed, so the file calls it ``__index_level_0__``; pandas' own metadata says
    which column is the index. A plain ``task`` column is read too."""
    from pandas.api.types import is_string_dtype

    table = _read_parquet(path)
    try:
        frame = table.to_pandas()
    except (ValueError, TypeError, KeyError) as e:
        raise FormatError(f"{path}: not a table of tasks ({' '.join(str(e).split())[:120]}).") from None
    if "task" in frame.columns:
        names = frame["task"]
    elif is_string_dtype(frame.index):
        names = frame.index.to_series()
    else:
        return []  # no task strings (the index is a plain row number)
    if "task_index" in frame.columns:
        try:
            names = names.iloc[np.argsort(frame["task_index"].to_numpy(np.int64), kind="stable")]
        except (ValueError, TypeError):
            raise FormatError(f"{where(path, 'task_index')}: {frame['task_index'].tolist()[:3]!r} are not "
                              "integers.") from None
    return [str(x) for x in names]


def _slice(frames: np.ndarray, first: int, n: int, path: Path, e: int) -> np.ndarray:
    if first < 0 or first + n > len(frames):
        raise FormatError(f"{where(path, episode=e)}: frames {first}..{first + n - 1} asked, the video has "
                          f"{len(frames)}.")
    return frames[first:first + n]


def read_v3(src: Path, *, camera: str | None) -> tuple[dict, int, Iterator[tuple[dict, int | None]]]:
    """A LeRobotDataset v3.0 directory as (attrs, episodes, iterator of (episode, None))."""
    info = _load_info(src, ("v3",))
    cams = _cameras(info, src, camera)
    video_cams = [c for c in cams.sources if info["features"][c]["dtype"] == "video"]
    meta_files = sorted((src / "meta" / "episodes").glob("*/*.parquet"))
    if not meta_files:
        raise FormatError(f"{src / 'meta' / 'episodes'}: no episode metadata files.")
    import pyarrow as pa

    meta = pa.concat_tables([_read_parquet(p) for p in meta_files]).to_pylist()
    meta.sort(key=lambda m: m.get("episode_index", -1))
    tasks_path = src / "meta" / "tasks.parquet"
    tasks = _tasks_v3(tasks_path) if tasks_path.exists() else []
    data_path, video_path = _templates(info, src, V3_DATA, V3_VIDEO, ("chunk_index", "file_index"),
                                       ("video_key", "chunk_index", "file_index"))

    def episodes() -> Iterator[tuple[dict, int | None]]:
        tables: dict[Path, Any] = {}
        videos: dict[str, tuple[Path, np.ndarray]] = {}  # per camera, its video file read last
        for m in meta:
            e = m.get("episode_index")
            try:
                path = data_path.resolve(src, chunk_index=m["data/chunk_index"], file_index=m["data/file_index"])
                lo, hi = int(m["dataset_from_index"]), int(m["dataset_to_index"])
            except FormatError:
                raise
            except (KeyError, TypeError, ValueError):
                raise FormatError(f"{where(meta_files[0], episode=e)}: episode row lacks its data file or "
                                  "index range.") from None
            if path not in tables:
                tables = {path: _read_parquet(path)}  # files are read one at a time, in order
            table = tables[path]
            index = _column(table, "index", path, e)
            rows = table.filter(pa.array((index >= lo) & (index < hi)))
            if rows.num_rows != hi - lo or hi <= lo:
                raise FormatError(f"{where(path, 'index', e)}: {rows.num_rows} rows for the range {lo}..{hi}.")
            frames = {}
            for cam in video_cams:
                try:
                    vpath = video_path.resolve(src, video_key=cam, chunk_index=m[f"videos/{cam}/chunk_index"],
                                               file_index=m[f"videos/{cam}/file_index"])
                    first = round(float(m[f"videos/{cam}/from_timestamp"]) * info["fps"])
                except FormatError:
                    raise
                except (KeyError, TypeError, ValueError):
                    raise FormatError(f"{where(meta_files[0], f'videos/{cam}', e)}: missing video location.") from None
                if cam not in videos or videos[cam][0] != vpath:
                    videos[cam] = (vpath, read_video(vpath))  # each camera's files are read one at a time
                frames[cam] = _slice(videos[cam][1], first, hi - lo, vpath, e)
            yield _episode_from_rows(rows, path, e, cams, frames, m.get("length")), None

    return _attrs(info, tasks, cams), len(meta), episodes()


def _jsonl(path: Path) -> list[dict]:
    try:
        lines = read_meta(path).splitlines()
    except FileNotFoundError:
        raise FormatError(f"{path}: missing.") from None
    except UnicodeDecodeError:
        raise FormatError(f"{path}: not UTF-8 text.") from None
    out = []
    for i, line in enumerate(lines):
        if line.strip():
            try:
                out.append(json.loads(line))
            except json.JSONDecodeError:
                raise FormatError(f"{path}: line {i + 1} is not valid JSON.") from None
    return out


def read_v21(src: Path, *, camera: str | None) -> tuple[dict, int, Iterator[tuple[dict, int | None]]]:
    """A LeRobotDataset v2.1 (or v2.0) directory as (attrs, episodes, iterator of (episode, None))."""
    info = _load_info(src, ("v2.",))
    cams = _cameras(info, src, camera)
    video_cams = [c for c in cams.sources if info["features"][c]["dtype"] == "video"]
    meta = sorted(_jsonl(src / "meta" / "episodes.jsonl"), key=lambda m: m.get("episode_index", -1))
    tasks = [str(t.get("task")) for t in _jsonl(src / "meta" / "tasks.jsonl")] if (src / "meta/tasks.jsonl").exists() \
        else []
    chunks = positive_int(info.get("chunks_size", CHUNKS_SIZE))
    if chunks is None:
        raise FormatError(f"{where(src / 'meta' / 'info.json', 'chunks_size')}: {info.get('chunks_size')!r}, "
                          "expected a positive integer.")
    data_path, video_path = _templates(info, src, V21_DATA, V21_VIDEO, ("episode_chunk", "episode_index"),
                                       ("episode_chunk", "video_key", "episode_index"))

    def episodes() -> Iterator[tuple[dict, int | None]]:
        for m in meta:
            e = m.get("episode_index")
            if not isinstance(e, int):
                raise FormatError(f"{src / 'meta/episodes.jsonl'}: an entry without an integer episode_index.")
            path = data_path.resolve(src, episode_chunk=e // chunks, episode_index=e)
            table = _read_parquet(path)
            frames = {}
            for cam in video_cams:
                vpath = video_path.resolve(src, episode_chunk=e // chunks, video_key=cam, episode_index=e)
                frames[cam] = _slice(read_video(vpath), 0, table.num_rows, vpath, e)
            yield _episode_from_rows(table, path, e, cams, frames, m.get("length")), None

    return _attrs(info, tasks, cams), len(meta), episodes()


# -- validation ---------------------------------------------------------------------------

def _declared_hwc(feature: dict) -> tuple:
    """(height, width, channels) of a camera feature's declared shape, read by its names
    when they say which axis is which (LeRobot writes [h, w, 3] with names
    height, width, channels)."""
    shape, names = list(feature["shape"]), feature.get("names")
    if isinstance(names, list) and len(names) == len(shape) and {"height", "width", "channels"} <= set(names):
        return tuple(shape[names.index(k)] for k in ("height", "width", "channels"))
    return tuple(shape)


def validate_lerobot(path: Path) -> tuple[str, list[str]]:
    """(kind, problems) of a LeRobot dataset directory: the schema of info.json and of every
    metadata, data and video file, and that they agree with each other."""
    problems: list[str] = []
    try:
        raw = json.loads(read_meta(path / "meta/info.json"))
    except (OSError, json.JSONDecodeError, UnicodeDecodeError, FormatError) as e:
        return "LeRobot dataset", [f"{path / 'meta/info.json'}: unreadable ({e})."]
    version = raw.get("codebase_version") if isinstance(raw, dict) else None
    kind = f"LeRobot dataset {version}"
    v3 = isinstance(version, str) and version.startswith("v3")
    if not (isinstance(version, str) and version.startswith(("v3", "v2."))):
        return kind, [f"{where(path / 'meta/info.json', 'codebase_version')}: {version!r}, expected v3.0 or v2.x."]
    info_path = path / "meta/info.json"
    required: dict[str, type | tuple[type, ...]] = {
        "fps": (int, float), "features": dict, "total_episodes": int, "total_frames": int, "total_tasks": int,
        "chunks_size": int, "splits": dict, "data_path": str}
    if v3:
        required |= {"data_files_size_in_mb": (int, float), "video_files_size_in_mb": (int, float)}
    else:
        required |= {"total_videos": int, "total_chunks": int}
    for key, kind_ in required.items():
        if not isinstance(raw.get(key), kind_):
            problems.append(f"{where(info_path, key)}: missing or not {getattr(kind_, '__name__', kind_)}.")
    feats = raw.get("features") if isinstance(raw.get("features"), dict) else {}
    for key, f in feats.items():
        if not isinstance(f, dict) or not isinstance(f.get("dtype"), str) or not isinstance(f.get("shape"), list) \
                or "names" not in f:
            problems.append(f"{where(info_path, f'features.{key}')}: needs dtype (str), shape (list) and names.")
        elif f["dtype"] == "video":
            missing = {"video.codec", "video.pix_fmt", "video.fps"} - set(f.get("info") or {})
            if missing:
                problems.append(f"{where(info_path, f'features.{key}.info')}: missing {sorted(missing)}.")
            if raw.get("video_path") is None:
                problems.append(f"{where(info_path, 'video_path')}: a video feature needs a video_path template.")
    for key in (STATE, ACTION, *INDEX_FEATURES):
        if key not in feats:
            problems.append(f"{where(info_path, 'features')}: no '{key}' feature.")
    if problems:
        return kind, problems
    for name in (["stats.json", "tasks.parquet"] if v3 else ["episodes.jsonl", "tasks.jsonl", "episodes_stats.jsonl"]):
        if not (path / "meta" / name).is_file():
            problems.append(f"{path / 'meta' / name}: missing.")
    if v3:
        stats_path = path / "meta/stats.json"
        if stats_path.is_file():
            try:
                stats = json.loads(read_meta(stats_path))
                for key, s in stats.items():
                    lack = {"min", "max", "mean", "std", "count", *QUANTILES} - set(s)
                    if lack:
                        problems.append(f"{where(stats_path, key)}: missing {sorted(lack)}.")
            except FormatError as e:
                problems.append(str(e))
            except (json.JSONDecodeError, UnicodeDecodeError, AttributeError, TypeError):
                problems.append(f"{stats_path}: not a JSON object of per-feature stats.")
    # Reading every episode checks the files, their columns and the frame counts; each camera
    # is read on its own, so that what is wrong with one does not hide what is wrong with another.
    reader = read_v3 if v3 else read_v21
    try:
        cams = _cameras(raw, path, None).sources
    except FormatError as e:
        return kind, [*problems, str(e)]
    frames = episodes = 0
    failed = False
    for c, cam in enumerate(cams):
        found: list[str] = []
        try:
            _, n, eps = reader(path, camera=cam)
            declared = _declared_hwc(feats[cam])
            for i, (ep, _) in enumerate(eps):
                want = feats[STATE]["shape"][0], feats[ACTION]["shape"][0]
                got = ep["state"].shape[1], ep["action"].shape[1]
                if got != want and c == 0:
                    found.append(f"{where(path, episode=i)}: state/action sizes {got}, info.json says {want}.")
                if tuple(ep["img"].shape[1:]) != declared:
                    found.append(f"{where(path, episode=i)}: {cam} frames are (H, W, C) = "
                                 f"{tuple(ep['img'].shape[1:])}, info.json says {declared}.")
                if c == 0:
                    frames += len(ep["img"])
                    episodes += 1
        except FormatError as e:
            found.append(str(e))
            failed = True
        problems += [p for p in found if p not in problems]  # a data file's fault shows once, not per camera
    if failed:
        return kind, problems
    if episodes != raw["total_episodes"]:
        problems.append(f"{where(info_path, 'total_episodes')}: {raw['total_episodes']}, the files hold {episodes}.")
    if frames != raw["total_frames"]:
        problems.append(f"{where(info_path, 'total_frames')}: {raw['total_frames']}, the files hold {frames}.")
    return kind, problems
