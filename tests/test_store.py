"""Episode store: round trips, on-disk layout, crash atomicity, bad paths."""

from __future__ import annotations

import json
import os
import random
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import zarr

from iwsim.data.store import EpisodeStore, StoreError, attrs_mismatch, chunk_frames


def fake_episode(j: int, size: int = 16) -> dict[str, np.ndarray]:
    """A deterministic episode of 5 + j % 4 frames, its content a function of j."""
    rng = np.random.default_rng(j)
    t = 5 + j % 4
    return {
        "img": rng.integers(0, 256, (t, size, size, 3), dtype=np.uint8),
        "state": rng.standard_normal((t, 4)).astype(np.float32),
        "action": rng.standard_normal((t, 4)).astype(np.float32),
        "n_contacts": np.full(t, j, np.int32),
    }


def assert_episodes(store: EpisodeStore, size: int = 16) -> None:
    """Every stored episode j equals fake_episode(j) and carries seed j."""
    assert store.seeds == list(range(store.n_episodes))
    for j in range(store.n_episodes):
        got, want = store.episode(j), fake_episode(j, size)
        assert got.keys() == want.keys()
        for k in want:
            np.testing.assert_array_equal(got[k], want[k])


@pytest.fixture
def store_path(tmp_path: Path) -> Path:
    return tmp_path / "eps.zarr"


def test_round_trip(store_path: Path) -> None:
    store = EpisodeStore.create(store_path, {"task": "pusht", "fps": 10, "image_size": 16, "goal": [0.0, 0.1]})
    assert (store.n_episodes, store.n_frames) == (0, 0)
    for j in range(3):
        store.append(fake_episode(j), seed=j)
    lengths = [len(fake_episode(j)["img"]) for j in range(3)]

    store = EpisodeStore.open(store_path)
    assert store.n_episodes == len(store) == 3
    np.testing.assert_array_equal(store.episode_ends, np.cumsum(lengths))
    assert store.episode_ends.dtype == np.int64
    assert store.n_frames == sum(lengths)
    assert_episodes(store)
    np.testing.assert_array_equal(store.episode(-1)["img"], fake_episode(2)["img"])
    with pytest.raises(IndexError):
        store.episode(3)
    assert store.attrs["goal"] == [0.0, 0.1] and store.attrs["seeds"] == [0, 1, 2]

    info = store.info()
    assert (info["episodes"], info["frames"], info["fps"], info["task"], info["image_size"]) == (
        3,
        sum(lengths),
        10,
        "pusht",
        16,
    )
    assert info["arrays"]["img"]["shape"] == (sum(lengths), 16, 16, 3)
    assert info["arrays"]["img"]["dtype"] == "uint8"
    assert info["arrays"]["n_contacts"] == {"shape": (sum(lengths),), "dtype": "int32", "chunks": (4096,)}
    assert info["bytes_on_disk"] > 0


def test_zarr_format_2_layout_readable_by_plain_zarr(store_path: Path) -> None:
    store = EpisodeStore.create(store_path, {"task": "pusht"})
    store.append(fake_episode(0), seed=0)
    store.append(fake_episode(1), seed=1)
    for f in (".zgroup", ".zattrs", "data/.zgroup", "meta/.zgroup", "meta/episode_ends/.zarray", "data/img/.zarray"):
        assert (store_path / f).is_file(), f
    assert not list(store_path.rglob("zarr.json"))
    zarray = json.loads((store_path / "data/img/.zarray").read_text())
    assert zarray["zarr_format"] == 2
    assert zarray["compressor"]["id"] == "blosc" and zarray["compressor"]["cname"] == "zstd"
    assert json.loads((store_path / "meta/episode_ends/.zarray").read_text())["dtype"] == "<i8"

    root = zarr.open(store_path, mode="r")  # what Diffusion Policy's ReplayBuffer does
    ends = root["meta/episode_ends"][:]
    np.testing.assert_array_equal(ends, store.episode_ends)
    for name, arr in root["data"].arrays():
        assert arr.shape[0] == ends[-1], name  # ReplayBuffer asserts this
    np.testing.assert_array_equal(root["data/img"][: ends[0]], fake_episode(0)["img"])
    assert root.attrs["seeds"] == [0, 1]


def test_chunks_hold_about_a_mebibyte_of_frames() -> None:
    assert chunk_frames((64, 64, 3), np.uint8) == 64
    assert chunk_frames((128, 128, 3), np.uint8) == 16
    assert chunk_frames((4,), np.float32) == 4096


def test_crash_before_commit_leaves_whole_episodes(store_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    store = EpisodeStore.create(store_path)
    store.append(fake_episode(0), seed=0)

    def crash(self: EpisodeStore, end: int) -> None:
        raise RuntimeError("simulated crash before episode_ends is written")

    with monkeypatch.context() as m:
        m.setattr(EpisodeStore, "_commit", crash)
        with pytest.raises(RuntimeError):
            store.append(fake_episode(1), seed=1)
    store.close()  # the crashed writer is gone, and its lock with it
    raw = zarr.open(store_path, mode="r")
    assert raw["data/img"].shape[0] > raw["meta/episode_ends"][-1]  # frames were written

    reader = EpisodeStore.open(store_path, "r")
    assert (reader.n_episodes, reader.n_frames) == (1, len(fake_episode(0)["img"]))
    assert_episodes(reader)

    writer = EpisodeStore.open(store_path, "a")  # truncates the uncommitted frames
    assert zarr.open(store_path, mode="r")["data/img"].shape[0] == writer.n_frames
    writer.append(fake_episode(1), seed=1)
    writer.append(fake_episode(2), seed=2)
    assert_episodes(EpisodeStore.open(store_path))
    assert EpisodeStore.open(store_path).n_episodes == 3


def test_crash_between_growing_and_writing_episode_ends(store_path: Path) -> None:
    store = EpisodeStore.create(store_path)
    for j in range(2):
        store.append(fake_episode(j), seed=j)
    store.close()
    zarr.open_array(store_path / "meta/episode_ends", mode="r+").resize((3,))  # reads back as 0

    assert EpisodeStore.open(store_path).n_episodes == 2
    writer = EpisodeStore.open(store_path, "a")
    assert zarr.open(store_path, mode="r")["meta/episode_ends"].shape == (2,)
    writer.append(fake_episode(2), seed=2)
    assert_episodes(EpisodeStore.open(store_path))


_APPENDER = """
import sys
sys.path.insert(0, sys.argv[2])
from test_store import fake_episode
from iwsim.data.store import EpisodeStore
store = EpisodeStore.open(sys.argv[1], "a")
while True:
    j = store.n_episodes
    store.append(fake_episode(j, size=64), seed=j)
    print(j, flush=True)
"""


def test_sigkill_mid_append_leaves_whole_episodes(store_path: Path) -> None:
    EpisodeStore.create(store_path).close()
    rng = random.Random(0)
    for _ in range(3):  # each round resumes from what the previous kill left
        proc = subprocess.Popen(
            [sys.executable, "-c", _APPENDER, str(store_path), str(Path(__file__).parent)],
            stdout=subprocess.PIPE,
            text=True,
        )
        for _ in range(2):
            assert proc.stdout.readline(), "appender died"
        time.sleep(rng.uniform(0.0, 0.02))
        os.kill(proc.pid, signal.SIGKILL)
        proc.wait()
        proc.stdout.close()
        store = EpisodeStore.open(store_path, "r")
        assert store.n_episodes >= 2
        assert_episodes(store, size=64)

    store = EpisodeStore.open(store_path, "a")
    n = store.n_episodes
    store.append(fake_episode(n, size=64), seed=n)
    root = zarr.open(store_path, mode="r")
    for _, arr in root["data"].arrays():
        assert arr.shape[0] == root["meta/episode_ends"][-1]
    assert not list(store_path.rglob("*.partial"))
    assert_episodes(EpisodeStore.open(store_path), size=64)


def test_append_rejects_mismatched_episodes(store_path: Path) -> None:
    store = EpisodeStore.create(store_path)
    store.append(fake_episode(0), seed=0)
    bad = fake_episode(1)
    del bad["action"]
    with pytest.raises(StoreError, match="keys"):
        store.append(bad, seed=1)
    with pytest.raises(StoreError, match="img"):
        store.append(fake_episode(1, size=8), seed=1)
    bad = fake_episode(1)
    bad["state"] = bad["state"][:-1]
    with pytest.raises(StoreError, match="leading length"):
        store.append(bad, seed=1)
    with pytest.raises(StoreError, match="read-only"):
        EpisodeStore.open(store_path, "r").append(fake_episode(1), seed=1)
    assert_episodes(EpisodeStore.open(store_path))


def test_attributes_are_set_by_the_writer_only(tmp_path: Path) -> None:
    for bad, match in (({"seeds": []}, "must not set 'seeds'"), ({"a": {1, 2}}, "JSON-serialisable")):
        with pytest.raises(ValueError, match=match):
            EpisodeStore.create(tmp_path / "bad.zarr", bad)
    assert not (tmp_path / "bad.zarr").exists()
    with EpisodeStore.create(tmp_path / "s.zarr", {"a": 1}) as store:
        store.update_attrs({"a": 2, "b": [1.5]})
        for bad, match in (({"store_version": 2}, "must not set 'seeds'"), ({"b": object()}, "JSON-serialisable")):
            with pytest.raises(ValueError, match=match):
                store.update_attrs(bad)
    store = EpisodeStore.open(tmp_path / "s.zarr")
    assert (store.attrs["a"], store.attrs["b"]) == (2, [1.5])
    with pytest.raises(ValueError, match="read-only"):
        store.update_attrs({"a": 3})
    assert attrs_mismatch(store, {"a": 2, "b": [1.5], "c": 0}, ("a", "b")) is None
    assert attrs_mismatch(store, {"a": 3, "b": [1.5], "c": 0}, ("a", "b", "c")) == "a=2, c=None, not a=3, c=0"


def test_create_refuses_existing_path(store_path: Path) -> None:
    EpisodeStore.create(store_path)
    with pytest.raises(StoreError, match="already exists"):
        EpisodeStore.create(store_path)
    assert not [p for p in store_path.parent.iterdir() if p.name.endswith(".tmp")]


def _not_stores(tmp_path: Path) -> dict[str, Path]:
    (tmp_path / "file.zarr").write_text("not a store")
    (tmp_path / "empty.zarr").mkdir()
    zarr.open_group(tmp_path / "group.zarr", mode="w", zarr_format=2).require_group("data")
    zarr.open_group(tmp_path / "v3.zarr", mode="w", zarr_format=3)
    return {
        "missing": tmp_path / "missing.zarr",
        "file": tmp_path / "file.zarr",
        "empty dir": tmp_path / "empty.zarr",
        "group without episode_ends": tmp_path / "group.zarr",
        "zarr v3 group": tmp_path / "v3.zarr",
    }


@pytest.mark.parametrize("kind", ["missing", "file", "empty dir", "group without episode_ends", "zarr v3 group"])
@pytest.mark.parametrize("mode", ["r", "a"])
def test_open_not_a_store(tmp_path: Path, kind: str, mode: str) -> None:
    path = _not_stores(tmp_path)[kind]
    with pytest.raises(StoreError) as e:
        EpisodeStore.open(path, mode)
    msg = str(e.value)
    assert str(path) in msg and "episode store" in msg and "\n" not in msg


def test_merge_concatenates_stores_and_refuses_mismatches(tmp_path: Path) -> None:
    from iwsim.core.errors import InputError
    from iwsim.data.formats import merge

    def make(name: str, episodes: range, **attrs) -> Path:
        store = EpisodeStore.create(tmp_path / name, {"task": "pusht", "fps": 10, "image_size": 16, **attrs})
        for j in episodes:
            store.append(fake_episode(j), seed=j)
        store.close()
        return tmp_path / name

    a, b = make("a.zarr", range(2), policy="play"), make("b.zarr", range(2, 5), policy="expert")
    merged = merge([a, b], tmp_path / "ab.zarr", progress=False)
    assert merged.n_episodes == 5 and merged.attrs["policy"] == "play+expert"
    assert merged.attrs["sources"] == [str(a), str(b)]
    assert_episodes(merged)
    with pytest.raises(FileExistsError, match="already exists"):
        merge([a, b], tmp_path / "ab.zarr", progress=False)
    assert_episodes(EpisodeStore.open(tmp_path / "ab.zarr"))  # untouched
    with pytest.raises(InputError, match="fps 20 differs"):
        merge([a, make("c.zarr", range(1), fps=20)], tmp_path / "ac.zarr", progress=False)
    assert not (tmp_path / "ac.zarr").exists()
    # issue 26: an output inside an input would nest a store in its data
    for inside in (a / "data" / "merged.zarr", b / "x.zarr"):
        with pytest.raises(InputError, match="inside the input"):
            merge([a, b], inside, progress=False)
        assert not inside.exists()
    assert_episodes(EpisodeStore.open(a))


def test_merge_refuses_stores_of_other_cameras(tmp_path: Path) -> None:
    from conftest import make_two_view_store

    from iwsim.core.errors import InputError
    from iwsim.data.formats import merge

    a = make_two_view_store(tmp_path / "a.zarr", policy="play")
    b = make_two_view_store(tmp_path / "b.zarr", episodes=1, policy="expert")
    merged = merge([a, b], tmp_path / "ab.zarr", progress=False)
    assert merged.attrs["cameras"] == ["top", "side"] and merged.n_episodes == 3
    np.testing.assert_array_equal(merged.episode(2)["img_side"], EpisodeStore.open(b).episode(0)["img_side"])
    one = EpisodeStore.create(tmp_path / "one.zarr", {"task": "pusht", "fps": 10, "image_size": 32})
    one.append({k: v for k, v in EpisodeStore.open(a).episode(0).items() if k != "img_side"}, seed=0)
    one.close()
    swapped = make_two_view_store(tmp_path / "swapped.zarr", cameras=("side", "top"))
    other = make_two_view_store(tmp_path / "other.zarr", cameras=("top", "wrist"))
    for src, have in ((one.path, ["top"]), (swapped, ["side", "top"]), (other, ["top", "wrist"])):
        with pytest.raises(InputError) as e:
            merge([a, src], tmp_path / "x.zarr", progress=False)
        assert str(e.value) == f"cannot merge {src} into {a}: cameras {have} differ from ['top', 'side']."
        assert not (tmp_path / "x.zarr").exists() and not list(tmp_path.glob(".x.zarr*"))
    assert EpisodeStore.open(a).n_episodes == 2  # untouched


def test_validate_checks_every_view(tmp_path: Path) -> None:
    from conftest import make_two_view_store

    from iwsim.data.formats import validate

    path = make_two_view_store(tmp_path / "two.zarr")
    assert validate(path) == ("episode store", [])
    root = zarr.open_group(path, mode="r+")
    root.attrs["cameras"] = ["top", "side", "front"]  # a view it does not hold
    root.attrs["image_size"] = 16
    _, problems = validate(path)
    assert f"{path} key 'data/img_front': missing (camera 'front' of top, side, front)." in problems
    for key in ("img", "img_side"):
        assert f"{path}: attribute 'image_size' is 16; data/{key} holds 32x32 frames." in problems
    root.attrs["cameras"] = ["top", "Side"]
    _, problems = validate(path)
    assert any("camera name 'Side' must be" in p for p in problems), problems
