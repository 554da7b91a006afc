"""LeRobotDataset v3.0 and v2.1: round trips through the episode store, every written file
against the format's schema, hand-written fixtures, validation, and bad input."""

import json
import shutil
from pathlib import Path

import numpy as np
import pandas as pd
import pyarrow as pa
import pyarrow.parquet as pq
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from iwsim.cli import main
from iwsim.core.lock import DirLock
from iwsim.data.formats import FormatError, export, import_, validate
from iwsim.data.formats.lerobot import QUANTILES, PathTemplate, read_v3
from iwsim.data.formats.video import probe, write_episode_video
from iwsim.data.store import EpisodeStore

FRAME_TOLERANCE = 4.0  # mean absolute error of a frame after H.264 in yuv420p (0..255)


@pytest.fixture(scope="module")
def exports(play_store, tmp_path_factory) -> dict[str, Path]:
    root = tmp_path_factory.mktemp("lerobot")
    return {fmt: export(fmt, play_store, root / fmt, task="push the T", progress=False)
            for fmt in ("lerobot-v3", "lerobot-v2.1")}


@pytest.mark.parametrize("fmt", ["lerobot-v3", "lerobot-v2.1"])
def test_round_trip(play_store, exports, tmp_path, fmt):
    back = import_(fmt, exports[fmt], tmp_path / "back.zarr", image_size=64, progress=False)
    src = EpisodeStore.open(play_store)
    assert back.n_episodes == src.n_episodes
    np.testing.assert_array_equal(back.episode_ends, src.episode_ends)
    for i in range(src.n_episodes):
        a, b = src.episode(i), back.episode(i)
        np.testing.assert_array_equal(b["state"], a["state"])
        np.testing.assert_array_equal(b["action"], a["action"])
        err = np.abs(b["img"].astype(int) - a["img"]).mean(axis=(1, 2, 3))
        assert err.max() < FRAME_TOLERANCE, (i, err.max())
    assert back.attrs["task"] == "push the T" and back.attrs["fps"] == 10
    assert back.attrs["action_names"] == ["left_x", "left_y", "right_x", "right_y"]
    assert validate(tmp_path / "back.zarr") == ("episode store", [])


def test_v3_files_follow_the_specification(play_store, exports):
    root = exports["lerobot-v3"]
    src = EpisodeStore.open(play_store)
    n, e = src.n_frames, src.n_episodes
    info = json.loads((root / "meta/info.json").read_text())
    assert info["codebase_version"] == "v3.0" and info["fps"] == 10
    assert (info["total_episodes"], info["total_frames"], info["total_tasks"]) == (e, n, 1)
    assert info["chunks_size"] == 1000 and info["data_files_size_in_mb"] == 100
    assert info["video_files_size_in_mb"] == 500 and info["splits"] == {"train": f"0:{e}"}
    assert info["data_path"] == "data/chunk-{chunk_index:03d}/file-{file_index:03d}.parquet"
    assert info["video_path"] == "videos/{video_key}/chunk-{chunk_index:03d}/file-{file_index:03d}.mp4"
    f = info["features"]
    assert f["observation.image"]["dtype"] == "video" and f["observation.image"]["shape"] == [64, 64, 3]
    assert f["observation.image"]["names"] == ["height", "width", "channels"]
    assert f["observation.image"]["info"] == {
        "video.height": 64, "video.width": 64, "video.codec": "h264", "video.pix_fmt": "yuv420p",
        "video.is_depth_map": False, "video.fps": 10, "video.channels": 3, "has_audio": False}
    for key, dim in (("observation.state", 4), ("action", 4)):
        assert f[key] == {"dtype": "float32", "shape": [dim], "names": ["left_x", "left_y", "right_x", "right_y"]}
    for key, dtype in (("timestamp", "float32"), ("frame_index", "int64"), ("episode_index", "int64"),
                       ("index", "int64"), ("task_index", "int64")):
        assert f[key] == {"dtype": dtype, "shape": [1], "names": None}

    stats = json.loads((root / "meta/stats.json").read_text())
    assert set(stats) == set(f)
    for key, s in stats.items():
        assert set(s) == {"min", "max", "mean", "std", "count", *QUANTILES}
        shape = (3, 1, 1) if key == "observation.image" else tuple(f[key]["shape"])
        assert all(np.shape(s[k]) == shape for k in s if k != "count"), key
    assert stats["action"]["count"] == [n]
    np.testing.assert_allclose(stats["action"]["mean"], src.array("action")[:n].mean(0), rtol=1e-5)
    assert 0 <= np.min(stats["observation.image"]["min"]) <= np.max(stats["observation.image"]["max"]) <= 1

    tasks = pd.read_parquet(root / "meta/tasks.parquet")
    assert tasks.index.name == "task" and list(tasks.index) == ["push the T"]
    assert list(tasks["task_index"]) == [0]

    eps = pq.read_table(root / "meta/episodes/chunk-000/file-000.parquet")
    rows = eps.to_pylist()
    assert [r["episode_index"] for r in rows] == list(range(e))
    ends = src.episode_ends
    for r, lo, hi in zip(rows, np.concatenate([[0], ends[:-1]]), ends):
        assert (r["dataset_from_index"], r["dataset_to_index"], r["length"]) == (lo, hi, hi - lo)
        assert r["tasks"] == ["push the T"] and r["data/chunk_index"] == r["data/file_index"] == 0
        assert r["videos/observation.image/from_timestamp"] == pytest.approx(lo / 10)
        assert r["videos/observation.image/to_timestamp"] == pytest.approx(hi / 10)
        assert r["stats/action/count"] == [hi - lo] and len(r["stats/action/q50"]) == 4
    assert eps.schema.field("tasks").type == pa.list_(pa.string())

    data = pq.read_table(root / "data/chunk-000/file-000.parquet")
    assert set(data.column_names) == {"observation.state", "action", "timestamp", "frame_index", "episode_index",
                                      "index", "task_index"}
    assert data.schema.field("action").type == pa.list_(pa.float32(), 4)
    assert data.schema.field("timestamp").type == pa.float32()
    for key in ("frame_index", "episode_index", "index", "task_index"):
        assert data.schema.field(key).type == pa.int64()
    assert data.column("index").to_pylist() == list(range(n))

    video = probe(root / "videos/observation.image/chunk-000/file-000.mp4")
    assert video == {"codec": "h264", "pix_fmt": "yuv420p", "height": 64, "width": 64, "frames": n}


def test_v21_files_follow_the_specification(play_store, exports):
    root = exports["lerobot-v2.1"]
    src = EpisodeStore.open(play_store)
    e = src.n_episodes
    info = json.loads((root / "meta/info.json").read_text())
    assert info["codebase_version"] == "v2.1"
    assert (info["total_episodes"], info["total_videos"], info["total_chunks"]) == (e, e, 1)
    assert info["data_path"] == "data/chunk-{episode_chunk:03d}/episode_{episode_index:06d}.parquet"
    assert info["video_path"] == "videos/chunk-{episode_chunk:03d}/{video_key}/episode_{episode_index:06d}.mp4"
    lines = [json.loads(x) for x in (root / "meta/episodes.jsonl").read_text().splitlines()]
    assert lines == [{"episode_index": i, "tasks": ["push the T"], "length": int(len(src.episode(i)["img"]))}
                     for i in range(e)]
    assert [json.loads(x) for x in (root / "meta/tasks.jsonl").read_text().splitlines()] == \
        [{"task_index": 0, "task": "push the T"}]
    stats = [json.loads(x) for x in (root / "meta/episodes_stats.jsonl").read_text().splitlines()]
    assert [s["episode_index"] for s in stats] == list(range(e))
    assert set(stats[0]["stats"]["action"]) == {"min", "max", "mean", "std", "count"}
    for i in range(e):
        t = pq.read_table(root / f"data/chunk-000/episode_{i:06d}.parquet")
        assert t.num_rows == lines[i]["length"] and t.column("episode_index").to_pylist() == [i] * t.num_rows
        v = probe(root / f"videos/chunk-000/observation.image/episode_{i:06d}.mp4")
        assert v["frames"] == t.num_rows and v["pix_fmt"] == "yuv420p"
    assert validate(root) == ("LeRobot dataset v2.1", [])


def handwritten_v3(root: Path, action_dim: int = 6, image_dtype: str = "video") -> dict[str, np.ndarray]:
    """A small v3 dataset written without our exporter: two cameras, 2 episodes of 5 and 3
    frames, a ``action_dim``-D action. Returns the 'top' and 'wrist' frames and the actions."""
    rng = np.random.default_rng(0)
    lengths, n = [5, 3], 8
    frames = {cam: np.repeat(rng.integers(0, 256, (n, 1, 1, 3), dtype=np.uint8), 32, 1).repeat(32, 2)
              for cam in ("top", "wrist")}
    action = rng.normal(size=(n, action_dim)).astype(np.float32)
    state = rng.normal(size=(n, 3)).astype(np.float32)
    feats = {"observation.state": {"dtype": "float32", "shape": [3], "names": None},
             "action": {"dtype": "float32", "shape": [action_dim], "names": None},
             "timestamp": {"dtype": "float32", "shape": [1], "names": None},
             **{k: {"dtype": "int64", "shape": [1], "names": None}
                for k in ("frame_index", "episode_index", "index", "task_index")}}
    for cam in frames:
        feats[f"observation.images.{cam}"] = {"dtype": image_dtype, "shape": [32, 32, 3],
                                              "names": ["height", "width", "channels"],
                                              "info": {"video.fps": 10, "video.codec": "h264",
                                                       "video.pix_fmt": "yuv420p"}}
    (root / "meta/episodes/chunk-000").mkdir(parents=True)
    (root / "data/chunk-000").mkdir(parents=True)
    (root / "meta/info.json").write_text(json.dumps({
        "codebase_version": "v3.0", "fps": 10, "features": feats, "total_episodes": 2, "total_frames": n,
        "total_tasks": 1, "chunks_size": 1000, "data_files_size_in_mb": 100, "video_files_size_in_mb": 500,
        "splits": {"train": "0:2"}, "data_path": "data/chunk-{chunk_index:03d}/file-{file_index:03d}.parquet",
        "video_path": "videos/{video_key}/chunk-{chunk_index:03d}/file-{file_index:03d}.mp4"}))
    ep = np.repeat([0, 1], lengths)
    frame = np.concatenate([np.arange(k) for k in lengths])
    cols = {"observation.state": pa.array(state.tolist(), pa.list_(pa.float32())),  # variable lists, as older writers
            "action": pa.array(action.tolist(), pa.list_(pa.float32())),
            "timestamp": pa.array(frame / 10, pa.float32()), "frame_index": pa.array(frame, pa.int64()),
            "episode_index": pa.array(ep, pa.int64()), "index": pa.array(np.arange(n), pa.int64()),
            "task_index": pa.array(np.zeros(n, np.int64))}
    if image_dtype == "image":
        import io

        from PIL import Image

        for cam, x in frames.items():
            cells = []
            for f in x:
                buf = io.BytesIO()
                Image.fromarray(f).save(buf, format="PNG")
                cells.append({"bytes": buf.getvalue(), "path": None})
            cols[f"observation.images.{cam}"] = pa.array(cells)
    else:
        for cam, x in frames.items():
            write_episode_video(root / f"videos/observation.images.{cam}/chunk-000/file-000.mp4", x, 10)
    pq.write_table(pa.table(cols), root / "data/chunk-000/file-000.parquet")
    rows = []
    for i, (lo, hi) in enumerate([(0, 5), (5, 8)]):
        row = {"episode_index": i, "tasks": ["stack"], "length": hi - lo, "data/chunk_index": 0,
               "data/file_index": 0, "dataset_from_index": lo, "dataset_to_index": hi}
        for cam in frames:
            row |= {f"videos/observation.images.{cam}/chunk_index": 0,
                    f"videos/observation.images.{cam}/file_index": 0,
                    f"videos/observation.images.{cam}/from_timestamp": lo / 10,
                    f"videos/observation.images.{cam}/to_timestamp": hi / 10}
        rows.append(row)
    pq.write_table(pa.Table.from_pylist(rows), root / "meta/episodes/chunk-000/file-000.parquet")
    pd.DataFrame({"task_index": [0]}, index=pd.Index(["stack"], name="task")).to_parquet(root / "meta/tasks.parquet")
    return {"top": frames["top"], "wrist": frames["wrist"], "action": action}


@pytest.mark.parametrize("image_dtype", ["video", "image"])
def test_import_a_handwritten_v3_dataset(tmp_path, image_dtype):
    src = tmp_path / "ds"
    want = handwritten_v3(src, image_dtype=image_dtype)
    both = import_("lerobot-v3", src, tmp_path / "x.zarr", image_size=None, progress=False)
    assert both.attrs["cameras"] == ["top", "wrist"] and "camera" not in both.attrs
    assert both.attrs["source_cameras"] == ["observation.images.top", "observation.images.wrist"]
    for view, key in (("top", "img"), ("wrist", "img_wrist")):
        got = np.concatenate([both.episode(i)[key] for i in range(2)]).astype(int)
        assert np.abs(got - want[view]).mean() < FRAME_TOLERANCE, view
    assert validate(both.path) == ("episode store", [])
    back = import_("lerobot-v3", src, tmp_path / "s.zarr", camera="wrist", image_size=None, progress=False)
    assert back.n_episodes == 2 and list(back.episode_ends) == [5, 8]
    np.testing.assert_array_equal(np.concatenate([back.episode(i)["action"] for i in range(2)]), want["action"])
    got = np.concatenate([back.episode(i)["img"] for i in range(2)]).astype(int)
    assert np.abs(got - want["wrist"]).mean() < FRAME_TOLERANCE  # flat colours: the camera asked for
    assert back.attrs["task"] == "stack" and back.array("action").shape[1] == 6
    assert "img_wrist" not in back.keys and back.attrs["camera"] == "observation.images.wrist"
    small = import_("lerobot-v3", src, tmp_path / "s16.zarr", camera="observation.images.top", image_size=16,
                    progress=False)
    assert small.array("img").shape[1:] == (16, 16, 3)


def test_validate_finds_what_is_wrong(exports, tmp_path):
    assert validate(exports["lerobot-v3"]) == ("LeRobot dataset v3.0", [])
    root = tmp_path / "v3"
    shutil.copytree(exports["lerobot-v3"], root)
    info = json.loads((root / "meta/info.json").read_text())
    info["total_frames"] += 1
    del info["features"]["observation.image"]["info"]["video.pix_fmt"]
    (root / "meta/info.json").write_text(json.dumps(info))
    stats = json.loads((root / "meta/stats.json").read_text())
    del stats["action"]["q99"]
    (root / "meta/stats.json").write_text(json.dumps(stats))
    _, problems = validate(root)
    text = "\n".join(problems)
    assert "features.observation.image.info" in text and "video.pix_fmt" in text
    (root / "meta/info.json").write_text(json.dumps({**info, "features": json.loads(
        (exports["lerobot-v3"] / "meta/info.json").read_text())["features"]}))
    _, problems = validate(root)
    text = "\n".join(problems)
    assert "stats.json key 'action'" in text and "q99" in text
    assert "total_frames" in text
    (root / "videos/observation.image/chunk-000/file-000.mp4").unlink()
    _, problems = validate(root)
    assert any("file-000.mp4: video file is missing" in p for p in problems)
    assert main(["data", "validate", str(root)]) == 1


def test_cli_export_import_validate(play_store, tmp_path, capsys):
    out = tmp_path / "lr"
    assert main(["data", "export", "--format", "lerobot-v3", "--in", str(play_store), "--out", str(out),
                 "--no-progress"]) == 0
    assert main(["data", "export", "--format", "lerobot-v3", "--in", str(play_store), "--out", str(out),
                 "--no-progress"]) == 1
    assert "already exists" in capsys.readouterr().err
    assert main(["data", "validate", str(out)]) == 0
    assert main(["data", "import", "--format", "lerobot-v3", "--in", str(out), "--out", str(tmp_path / "s.zarr"),
                 "--image-size", "32", "--no-progress"]) == 0
    assert EpisodeStore.open(tmp_path / "s.zarr").array("img").shape[1:] == (32, 32, 3)
    assert main(["data", "import", "--format", "lerobot-v2.1", "--in", str(out), "--out",
                 str(tmp_path / "t.zarr"), "--no-progress"]) == 1
    assert "codebase_version" in capsys.readouterr().err and not (tmp_path / "t.zarr").exists()


@pytest.mark.parametrize("fmt", ["lerobot-v3", "lerobot-v2.1"])
def test_bad_input_names_the_file_and_leaves_nothing(exports, tmp_path, fmt):
    root = tmp_path / "ds"
    shutil.copytree(exports[fmt], root)
    data = sorted((root / "data").rglob("*.parquet"))[0]
    data.write_bytes(data.read_bytes()[: data.stat().st_size // 2])  # truncated
    with pytest.raises(FormatError, match=data.name):
        import_(fmt, root, tmp_path / "out.zarr", image_size=64, progress=False)
    assert not (tmp_path / "out.zarr").exists()
    assert not list(tmp_path.glob(".out.zarr*"))


FILES = {
    "lerobot-v3": ["meta/info.json", "data/chunk-000/file-000.parquet", "meta/episodes/chunk-000/file-000.parquet",
                   "meta/tasks.parquet", "videos/observation.image/chunk-000/file-000.mp4"],
    "lerobot-v2.1": ["meta/info.json", "meta/episodes.jsonl", "data/chunk-000/episode_000001.parquet",
                     "videos/chunk-000/observation.image/episode_000001.mp4"],
}


@settings(max_examples=25, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(file=st.sampled_from([(fmt, f) for fmt, files in FILES.items() for f in files]), cut=st.floats(0, 1),
       flips=st.lists(st.integers(0, 10**9), max_size=8))
def test_corrupted_files_fail_cleanly(exports, tmp_path_factory, file, cut, flips):
    """Truncated or bit-flipped files of either version: a valid store, or a one-line
    ValueError/OSError and no output at all."""
    fmt, name = file
    tmp = tmp_path_factory.mktemp("corrupt")
    root = tmp / "ds"
    shutil.copytree(exports[fmt], root)
    path = root / name
    raw = bytearray(path.read_bytes())
    raw = raw[: max(1, int(len(raw) * cut))] if cut < 0.98 else raw
    for f in flips:
        raw[f % len(raw)] ^= 0xFF
    path.write_bytes(bytes(raw))
    out = tmp / "out.zarr"
    try:
        store = import_(fmt, root, out, image_size=64, progress=False)
    except (ValueError, OSError) as e:
        assert "\n" not in str(e).strip() and str(e)
        assert not out.exists()
    else:
        assert validate(store.path)[1] == []


def test_v3_rolls_over_to_new_files_and_chunks(play_store, tmp_path, monkeypatch):
    """With tiny file limits every episode gets its own data and video file, two files per
    chunk directory; the import reads them all back."""
    from iwsim.data.formats import lerobot

    monkeypatch.setattr(lerobot, "DATA_FILE_MB", 1e-9)
    monkeypatch.setattr(lerobot, "VIDEO_FILE_MB", 1e-9)
    monkeypatch.setattr(lerobot, "CHUNKS_SIZE", 2)
    root = export("lerobot-v3", play_store, tmp_path / "ds", progress=False)
    src = EpisodeStore.open(play_store)
    e = src.n_episodes
    data = sorted(p.relative_to(root).as_posix() for p in (root / "data").rglob("*.parquet"))
    assert data == [f"data/chunk-{i // 2:03d}/file-{i % 2:03d}.parquet" for i in range(e)]
    assert len(list((root / "videos").rglob("*.mp4"))) == e
    rows = pq.read_table(root / "meta/episodes/chunk-000/file-000.parquet").to_pylist()
    assert [(r["data/chunk_index"], r["data/file_index"]) for r in rows] == [(i // 2, i % 2) for i in range(e)]
    assert all(r["videos/observation.image/from_timestamp"] == 0 for r in rows)
    back = import_("lerobot-v3", root, tmp_path / "back.zarr", image_size=64, progress=False)
    np.testing.assert_array_equal(back.array("action")[:], src.array("action")[:src.n_frames])
    assert validate(root) == ("LeRobot dataset v3.0", [])


def test_hf_datasets_loads_the_v3_files_as_lerobot_does(exports, tmp_path, monkeypatch):
    """LeRobot loads data files with Hugging Face datasets, its features built from
    info.json (shape [1] -> Value, [D] -> Sequence(length=D)); ours must load that way."""
    monkeypatch.setenv("HF_DATASETS_OFFLINE", "1")
    monkeypatch.setenv("HF_HUB_OFFLINE", "1")
    datasets = pytest.importorskip("datasets")
    root = exports["lerobot-v3"]
    info = json.loads((root / "meta/info.json").read_text())
    feats = {k: datasets.Value(f["dtype"]) if f["shape"] == [1] else
             datasets.Sequence(length=f["shape"][0], feature=datasets.Value(f["dtype"]))
             for k, f in info["features"].items() if f["dtype"] != "video"}
    ds = datasets.Dataset.from_parquet(str(root / "data/chunk-000/file-000.parquet"),
                                       features=datasets.Features(feats), cache_dir=str(tmp_path / "hf"))
    assert ds.num_rows == info["total_frames"] and set(ds.column_names) == set(feats)
    table = pq.read_table(root / "data/chunk-000/file-000.parquet")
    assert ds[7]["action"] == pytest.approx(table.column("action")[7].as_py())
    eps = datasets.Dataset.from_parquet(str(root / "meta/episodes/chunk-000/file-000.parquet"),
                                        cache_dir=str(tmp_path / "hf"))
    assert eps.num_rows == info["total_episodes"] and eps[0]["tasks"] == ["push the T"]


HOSTILE_TEMPLATES = {
    "absolute": ("data_path", "/etc/chunk-{chunk_index:03d}/file-{file_index:03d}.parquet", "not allowed"),
    "parent": ("data_path", "../outside/chunk-{chunk_index:03d}/file-{file_index:03d}.parquet", "not allowed"),
    "inner parent": ("data_path", "data/../../x/{chunk_index}/{file_index}.parquet", "not allowed"),
    "attribute": ("data_path", "data/{chunk_index.__class__.__mro__}/{file_index}.parquet", "not allowed"),
    "index": ("data_path", "data/{chunk_index[0]}/{file_index}.parquet", "not allowed"),
    "unknown field": ("data_path", "data/{episode_index:03d}/{file_index}.parquet", "has the field"),
    "conversion": ("data_path", "data/{chunk_index!r}/{file_index}.parquet", "not allowed"),
    "format spec": ("data_path", "data/{chunk_index:>999}/{file_index}.parquet", "not allowed"),
    "width on text": ("video_path", "videos/{video_key:03d}/chunk-{chunk_index:03d}/file-{file_index:03d}.mp4",
                      "has the field"),
    "not text": ("video_path", ["videos"], "not a path template"),
}


@pytest.mark.parametrize("name", HOSTILE_TEMPLATES)
def test_hostile_path_templates_are_refused(exports, tmp_path, capsys, name):
    """Templates are parsed strictly, never str.format-ted, and never lead outside the dataset."""
    key, template, match = HOSTILE_TEMPLATES[name]
    root = tmp_path / "v3"
    shutil.copytree(exports["lerobot-v3"], root)
    shutil.copytree(root / "data", tmp_path / "outside")  # what ../ would reach
    info = json.loads((root / "meta/info.json").read_text())
    (root / "meta/info.json").write_text(json.dumps({**info, key: template}))
    with pytest.raises(FormatError, match=match) as refused:
        list(read_v3(root, camera=None)[2])
    assert f"key '{key}'" in str(refused.value) and "mro" not in str(refused.value).replace(str(template), "")
    _, problems = validate(root)
    assert len(problems) == 1 and f"key '{key}'" in problems[0]
    assert main(["data", "import", "--format", "lerobot-v3", "--in", str(root), "--out", str(tmp_path / "x.zarr"),
                 "--no-progress"]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and f"key '{key}'" in err[0]
    assert not (tmp_path / "x.zarr").exists()


def test_resolved_paths_stay_inside_the_dataset(exports, tmp_path):
    """A template that parses may still be led out by a value (a camera named '..') or a
    symlink; both are refused, and validate no longer calls such a dataset valid."""
    root = tmp_path / "v3"
    shutil.copytree(exports["lerobot-v3"], root)
    elsewhere = tmp_path / "elsewhere"
    shutil.move(root / "data", elsewhere)
    (root / "data").symlink_to(elsewhere)
    _, problems = validate(root)
    assert len(problems) == 1 and "outside the dataset" in problems[0]
    t = PathTemplate.parse("videos/{video_key}/file-{file_index:03d}.mp4", ("video_key", "file_index"), "t")
    want = root / "videos/observation.image/file-007.mp4"
    assert t.resolve(root, video_key="observation.image", file_index=7) == want
    with pytest.raises(FormatError, match="outside the dataset"):
        t.resolve(root, video_key="../..", file_index=0)


def test_a_killed_exports_temporary_directory_is_removed_by_the_next_run(play_store, tmp_path):
    out = tmp_path / "lr"
    stale = tmp_path / ".lr.0123abcd.tmp"  # what a killed export leaves (its lock died with it)
    (stale / "data").mkdir(parents=True)
    (stale / ".iwsim.lock").write_text("pid 1 (iwsim data export), writing since ...")
    live = tmp_path / ".lr.89abcdef.tmp"  # one another run is writing right now
    live.mkdir()
    with DirLock(live):
        export("lerobot-v3", play_store, out, progress=False)
        assert not stale.exists() and live.exists()
    assert validate(out)[1] == [] and not (out / ".iwsim.lock").exists()
    assert [p.name for p in tmp_path.iterdir() if p.name.endswith(".tmp")] == [live.name]


@pytest.mark.parametrize("fmt", ["lerobot-v3", "lerobot-v2.1"])
def test_validate_finds_frames_of_another_shape_than_info_declares(exports, tmp_path, fmt):
    """Issue 26: a dataset whose info.json declares a frame shape its videos do not have
    was called valid."""
    root = tmp_path / "ds"
    shutil.copytree(exports[fmt], root)
    info = json.loads((root / "meta/info.json").read_text())
    h, w, c = info["features"]["observation.image"]["shape"]
    info["features"]["observation.image"]["shape"] = [h * 2, w, c]
    (root / "meta/info.json").write_text(json.dumps(info))
    _, problems = validate(root)
    assert any(f"info.json says {(h * 2, w, c)}" in p and f"{(h, w, c)}" in p for p in problems), problems


def _png(array: np.ndarray) -> bytes:
    import io

    from PIL import Image

    buf = io.BytesIO()
    Image.fromarray(array).save(buf, format="PNG")
    return buf.getvalue()


@pytest.mark.parametrize("bad, message", [
    ("huge", "is 5000 x 5000 pixels, more than a camera frame"),      # issue 65 row 3 (9.3 GB before)
    ("sizes", "frame 1 is 16 x 16 pixels, the first is 32 x 32"),     # row 4 (a ValueError traceback)
    ("bomb", "frame 0 declares more pixels than a camera frame"),     # row 5 (PIL's DecompressionBombError)
    ("16bit", "has 'I;16' pixels; expected 8 bits a channel"),         # row 6 (stored as 255, silently)
])
def test_image_cells_are_bounded_before_decoding(tmp_path, bad, message):
    """Every image a LeRobot import decodes is bounded by its declared size first, of one
    size and 8 bits a channel; a bad one is one line naming the frame, nothing written."""
    src = tmp_path / "ds"
    handwritten_v3(src, image_dtype="image")
    data = src / "data/chunk-000/file-000.parquet"
    table = pq.read_table(data)
    key = "observation.images.wrist"
    cells = table.column(key).to_pylist()
    if bad == "huge":
        cells[0] = {"bytes": _png(np.zeros((5000, 5000, 3), np.uint8)), "path": None}
    elif bad == "sizes":
        cells[1] = {"bytes": _png(np.zeros((16, 16, 3), np.uint8)), "path": None}
    elif bad == "bomb":
        cells[0] = {"bytes": _png(np.zeros((15000, 15000), np.uint8)), "path": None}
    else:
        cells = [{"bytes": _png(np.full((32, 32), 40000, np.uint16)), "path": None} for _ in cells]
    table = table.set_column(table.column_names.index(key), key, pa.array(cells))
    pq.write_table(table, data)
    with pytest.raises(FormatError, match=message):
        import_("lerobot-v3", src, tmp_path / "s.zarr", camera="wrist", image_size=64, progress=False)
    assert not (tmp_path / "s.zarr").exists()


# -- several cameras -----------------------------------------------------------------------------

@pytest.fixture(scope="module")
def two_view_exports(two_view_store, tmp_path_factory) -> dict[str, Path]:
    root = tmp_path_factory.mktemp("lerobot_views")
    return {fmt: export(fmt, two_view_store, root / fmt, progress=False) for fmt in ("lerobot-v3", "lerobot-v2.1")}


def assert_views_close(back: EpisodeStore, src: EpisodeStore, keys: dict[str, str]) -> None:
    """Each of ``back``'s arrays (``keys``: back's -> src's) within the codec's error of the
    view it came from and far from the other view: the views were not mixed up."""
    for i in range(src.n_episodes):
        a, b = src.episode(i), back.episode(i)
        for got, want in keys.items():
            err = np.abs(b[got].astype(int) - a[want]).mean(axis=(1, 2, 3))
            assert err.max() < FRAME_TOLERANCE, (i, got, err.max())
            other = "img_side" if want == "img" else "img"
            assert np.abs(b[got].astype(int) - a[other]).mean() > 20, (i, got)


@pytest.mark.parametrize("fmt", ["lerobot-v3", "lerobot-v2.1"])
def test_two_views_round_trip(two_view_store, two_view_exports, tmp_path, fmt):
    root = two_view_exports[fmt]
    src = EpisodeStore.open(two_view_store)
    info = json.loads((root / "meta/info.json").read_text())
    cams = ["observation.images.top", "observation.images.side"]
    assert [k for k, f in info["features"].items() if f["dtype"] == "video"] == cams  # in view order
    assert "observation.image" not in info["features"]
    for cam in cams:
        assert info["features"][cam]["shape"] == [32, 32, 3] and info["features"][cam]["info"]["video.height"] == 32
    if fmt == "lerobot-v3":
        for cam in cams:
            video = probe(root / f"videos/{cam}/chunk-000/file-000.mp4")
            assert video["frames"] == src.n_frames and (video["height"], video["width"]) == (32, 32)
        rows = pq.read_table(root / "meta/episodes/chunk-000/file-000.parquet").to_pylist()
        for r, lo in zip(rows, [0, 5]):
            for cam in cams:
                assert (r[f"videos/{cam}/chunk_index"], r[f"videos/{cam}/file_index"]) == (0, 0)
                assert r[f"videos/{cam}/from_timestamp"] == pytest.approx(lo / 10)
                assert np.shape(r[f"stats/{cam}/mean"]) == (3, 1, 1)
        stats = json.loads((root / "meta/stats.json").read_text())
        assert set(cams) <= set(stats)
        assert validate(root) == ("LeRobot dataset v3.0", [])
    else:
        assert info["total_videos"] == 2 * src.n_episodes
        for i in range(src.n_episodes):
            for cam in cams:
                assert probe(root / f"videos/chunk-000/{cam}/episode_{i:06d}.mp4")["frames"] == 5 + i
        assert validate(root) == ("LeRobot dataset v2.1", [])

    back = import_(fmt, root, tmp_path / "back.zarr", image_size=None, progress=False)
    assert back.attrs["cameras"] == ["top", "side"] and back.attrs["source_cameras"] == cams
    assert sorted(back.keys) == ["action", "img", "img_side", "state"]
    np.testing.assert_array_equal(back.episode_ends, src.episode_ends)
    for i in range(src.n_episodes):
        np.testing.assert_array_equal(back.episode(i)["action"], src.episode(i)["action"])
        np.testing.assert_array_equal(back.episode(i)["state"], src.episode(i)["state"])
    assert_views_close(back, src, {"img": "img", "img_side": "img_side"})
    assert validate(back.path) == ("episode store", [])

    side = import_(fmt, root, tmp_path / "side.zarr", camera="side", image_size=16, progress=False)
    assert sorted(side.keys) == ["action", "img", "state"] and "cameras" not in side.attrs
    assert side.attrs["camera"] == "observation.images.side" and side.array("img").shape[1:] == (16, 16, 3)
    assert validate(side.path) == ("episode store", [])


def test_two_views_through_the_cli(two_view_exports, tmp_path, capsys):
    out = tmp_path / "s.zarr"
    assert main(["data", "import", "--format", "lerobot-v3", "--in", str(two_view_exports["lerobot-v3"]), "--out",
                 str(out), "--image-size", "16", "--no-progress"]) == 0
    back = EpisodeStore.open(out)
    assert back.attrs["cameras"] == ["top", "side"]
    assert back.array("img").shape[1:] == back.array("img_side").shape[1:] == (16, 16, 3)
    assert main(["data", "import", "--format", "lerobot-v3", "--in", str(two_view_exports["lerobot-v3"]), "--out",
                 str(tmp_path / "x.zarr"), "--camera", "front", "--no-progress"]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "no camera 'front'" in err[0] and not (tmp_path / "x.zarr").exists()


@pytest.mark.parametrize("fmt", ["lerobot-v3", "lerobot-v2.1"])
def test_validate_lists_what_is_wrong_with_each_view(two_view_exports, tmp_path, fmt):
    root = tmp_path / "ds"
    shutil.copytree(two_view_exports[fmt], root)
    info = json.loads((root / "meta/info.json").read_text())
    for cam in ("observation.images.top", "observation.images.side"):
        info["features"][cam]["shape"] = [48, 32, 3]
    (root / "meta/info.json").write_text(json.dumps(info))
    _, problems = validate(root)
    for cam in ("observation.images.top", "observation.images.side"):
        assert any(f"{cam} frames are (H, W, C) = (32, 32, 3), info.json says (48, 32, 3)" in p for p in problems), \
            (cam, problems)
    # a video of one camera gone: the import names it and writes nothing; validate still checks the other
    shutil.copytree(two_view_exports[fmt], root, dirs_exist_ok=True)
    video = sorted((root / "videos").rglob("*.mp4"))
    side = [v for v in video if "observation.images.side" in v.as_posix()][0]
    side.unlink()
    with pytest.raises(FormatError, match=f"{side.name}: video file is missing"):
        import_(fmt, root, tmp_path / "out.zarr", image_size=None, progress=False)
    assert not (tmp_path / "out.zarr").exists() and not list(tmp_path.glob(".out.zarr*"))
    _, problems = validate(root)
    assert len(problems) == 1 and "video file is missing" in problems[0], problems
    assert import_(fmt, root, tmp_path / "top.zarr", camera="top", image_size=None, progress=False).n_episodes == 2


def test_views_of_other_frame_counts_are_refused(tmp_path):
    """A handwritten v3 dataset whose second camera's video misses frames: one line, nothing written."""
    src = tmp_path / "ds"
    want = handwritten_v3(src)
    write_episode_video(src / "videos/observation.images.wrist/chunk-000/file-000.mp4", want["wrist"][:6], 10)
    with pytest.raises(FormatError, match=r"frames 5..7 asked, the video has 6"):
        import_("lerobot-v3", src, tmp_path / "x.zarr", image_size=None, progress=False)
    assert not (tmp_path / "x.zarr").exists()


LEROBOT_FIXTURE = Path(__file__).resolve().parent / "data" / "lerobot_two_cameras"
AV1_TOLERANCE = 6.0  # mean absolute error of a frame after LeRobot's default AV1 at crf 30 (0..255)


def square_centres(frames: np.ndarray, colour: np.ndarray) -> np.ndarray:
    """(T, 2) row and column of the pixels of ``colour`` (within the codec's error) in (T, H, W, 3) frames."""
    mask = np.abs(frames.astype(int) - colour).sum(-1) < 90
    rows, cols = np.indices(mask.shape[1:])
    n = mask.sum((1, 2))
    assert n.all(), "a frame without the square"
    return np.stack([(mask * rows).sum((1, 2)) / n, (mask * cols).sum((1, 2)) / n], 1)


def test_a_dataset_written_by_lerobot_imports_with_both_views(tmp_path):
    """tests/data/lerobot_two_cameras was written by LeRobot 0.4.4's own writer
    (scripts/lerobot_two_camera_fixture.py): AV1 video, an unnamed pandas index in tasks.parquet.
    Both cameras come back named, in order, frame by frame, and not swapped."""
    want = np.load(LEROBOT_FIXTURE.with_suffix(".npz"))
    assert validate(LEROBOT_FIXTURE) == ("LeRobot dataset v3.0", [])
    out = tmp_path / "both.zarr"
    assert main(["data", "import", "--format", "lerobot-v3", "--in", str(LEROBOT_FIXTURE), "--out", str(out),
                 "--image-size", "0", "--no-progress"]) == 0
    both = EpisodeStore.open(out)
    assert both.attrs["cameras"] == ["top", "side"]
    assert both.attrs["source_cameras"] == ["observation.images.top", "observation.images.side"]
    assert sorted(both.keys) == ["action", "img", "img_side", "state"]
    assert both.attrs["task"] == str(want["task"]) and both.attrs["fps"] == 10
    assert list(both.episode_ends) == [12, 24]
    for e in range(2):
        ep = both.episode(e)
        np.testing.assert_array_equal(ep["action"], want["action"][e])
        np.testing.assert_array_equal(ep["state"], want["state"][e])
        for key, view, other in (("img", "top", "side"), ("img_side", "side", "top")):
            assert ep[key].shape == (12, 64, 64, 3) and ep[key].dtype == np.uint8
            err = np.abs(ep[key].astype(int) - want[view][e]).mean(axis=(1, 2, 3))
            assert err.max() < AV1_TOLERANCE, (e, view, err.max())
            assert np.abs(ep[key].astype(int) - want[other][e]).mean() > 20, (e, view)  # not swapped
            # each frame from its own time step: the square moves 4-5 px a frame
            first = want[view][e, 0]
            colour = first[(first != first[0, 0]).any(-1)][0]  # the square's (the corner is background)
            shift = np.abs(square_centres(ep[key], colour) - square_centres(want[view][e], colour)).max()
            assert shift < 1.5, (e, view, shift)
    assert validate(out) == ("episode store", [])

    assert main(["data", "import", "--format", "lerobot-v3", "--in", str(LEROBOT_FIXTURE), "--out",
                 str(tmp_path / "side.zarr"), "--camera", "side", "--image-size", "0", "--no-progress"]) == 0
    side = EpisodeStore.open(tmp_path / "side.zarr")
    assert sorted(side.keys) == ["action", "img", "state"] and "cameras" not in side.attrs
    assert side.attrs["camera"] == "observation.images.side"
    for e in range(2):
        np.testing.assert_array_equal(side.episode(e)["img"], both.episode(e)["img_side"])


@pytest.mark.parametrize("layout", ["unnamed index", "named index", "column"])
def test_v3_task_strings_are_read_from_every_tasks_parquet_layout(tmp_path, layout):
    """LeRobot's ``write_tasks`` leaves the task index unnamed (``__index_level_0__`` in the
    file); ours names it ``task``; a converter may write a ``task`` column. Tasks come in
    ``task_index`` order."""
    src = tmp_path / "ds"
    handwritten_v3(src)
    tasks = pd.DataFrame({"task_index": [1, 0]}, index=pd.Index(["place", "stack"]))
    if layout == "named index":
        tasks.index.name = "task"
    elif layout == "column":
        tasks = tasks.rename_axis("task").reset_index()
    tasks.to_parquet(src / "meta/tasks.parquet")
    attrs, _, _ = read_v3(src, camera=None)
    assert attrs["tasks"] == ["stack", "place"] and attrs["task"] == "stack"


def test_a_dataset_written_by_lerobot_trains_a_world_model_that_runs_and_plays_both_views(tmp_path):
    """Issue 68's target end to end: LeRobot's own two-camera dataset -> ``data import`` ->
    a tiny world model of both views -> ``iwsim/WorldModel-v0`` and ``iwsim play`` with both."""
    from conftest import train_tiny_world_model

    from iwsim.play import protocol as proto
    from iwsim.play.engine import Engine, PlayConfig
    from iwsim.world_model import WorldModel
    from iwsim.world_model.env import WorldModelEnv

    store = tmp_path / "both.zarr"
    wm_dir = train_tiny_world_model(store, tmp_path, ["data", "import", "--format", "lerobot-v3", "--in",
                                                      str(LEROBOT_FIXTURE), "--out", str(store), "--image-size",
                                                      "64", "--no-progress"])
    wm = WorldModel.load(wm_dir)
    assert wm.cameras == ("top", "side")
    starts = [EpisodeStore.open(store).episode(e) for e in range(2)]  # a store task starts from its episodes
    first = starts[1]
    env = WorldModelEnv(wm_dir)
    obs, _ = env.reset(seed=1)
    assert env.observation_space.contains(obs) and list(obs["pixels"]) == ["top", "side"]
    assert any(np.array_equal(obs["pixels"]["top"], ep["img"][0]) and
               np.array_equal(obs["pixels"]["side"], ep["img_side"][0]) for ep in starts)
    for _ in range(3):
        obs, *_ = env.step(first["action"][0])
        assert env.observation_space.contains(obs) and obs["pixels"]["side"].shape == (64, 64, 3)
    env.close()
    takes = tmp_path / "takes.zarr"
    eng = Engine(wm, PlayConfig(record_to=takes))
    s = eng.open()
    header, views = proto.unpack_frame(eng.frame_message(s))
    assert header["views"] == ["world_model", "world_model:side"] and len(views) == 2
    eng.handle(s, proto.Command("record"))
    for t in range(2):
        eng.handle(s, proto.Action(t, tuple(float(x) for x in first["action"][t])))
        eng.tick()
    eng.handle(s, proto.Command("save"))
    eng.recorder.close()
    eng.shutdown()
    back = EpisodeStore.open(takes)
    assert back.attrs["cameras"] == ["top", "side"] and back.episode(0)["img_side"].shape == (2, 64, 64, 3)
