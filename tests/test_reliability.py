"""Bad flags get one line, not a traceback, and are refused before anything is loaded or
allocated (issue 17): out-of-range episodes, devices this build lacks, negative seeds,
a store named twice, sizes the machine cannot hold; and thread counts are chosen."""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pytest
import torch

from iwsim.cli import main
from iwsim.core.checkpoint import load_json
from iwsim.core.resources import choose_threads

ROOT = Path(__file__).resolve().parents[1]
TINY_COLLECT = ["--task", "pusht", "--policy", "play", "--steps", "3", "--no-progress", "--workers", "1"]


@pytest.fixture(scope="module")
def store(tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("reliability") / "s.zarr"
    assert main(["collect", *TINY_COLLECT, "--episodes", "2", "--out", str(out)]) == 0
    return out


def error_line(capsys: pytest.CaptureFixture[str]) -> str:
    lines = capsys.readouterr().err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("iwsim: error: "), lines
    return lines[0]


@pytest.mark.parametrize("episode", ["2", "99", "-1"])
def test_rollout_refuses_episodes_out_of_range(store, tmp_path, capsys, episode):
    assert main(["rollout", "--checkpoint", str(tmp_path / "unused"), "--data", str(store), "--episode", episode,
                 "--out", str(tmp_path / "v.mp4")]) == 1
    assert f"--episode must be in 0..1 ({store} holds 2 episodes), got {episode}." in error_line(capsys)


def test_a_device_this_build_lacks_is_one_line(store, tmp_path, capsys):
    import torch

    if torch.cuda.is_available():
        pytest.skip("this machine has CUDA")
    assert main(["rollout", "--checkpoint", str(tmp_path / "unused"), "--data", str(store), "--device", "cuda",
                 "--out", str(tmp_path / "v.mp4")]) == 1
    assert "--device cuda: this PyTorch build has no CUDA; use --device cpu (or auto)." in error_line(capsys)
    assert main(["rollout", "--checkpoint", "x", "--data", str(store), "--device", "tpu", "--out", "v.mp4"]) == 1
    assert "unknown device 'tpu'" in error_line(capsys)


@pytest.mark.parametrize("seed", ["-1", str(2**32)])
def test_eval_policy_refuses_seeds_mujoco_cannot_take(tmp_path, capsys, seed):
    assert main(["eval", "policy", "--checkpoint", str(tmp_path / "unused"), "--seed", seed, "--episodes", "2",
                 "--out", str(tmp_path / "e")]) == 1
    assert f"--seed must be in 0..{2**32 - 2} for 2 episodes" in error_line(capsys)
    assert not (tmp_path / "e").exists()


def test_a_store_named_twice_in_a_mixture_is_refused(store, tmp_path, capsys):
    twice = f"{store}:2,{store.parent / '.' / store.name}:1"
    assert main(["train", "policy", "--policy", "dp", "--preset", "tiny-dp", "--data", twice,
                 "--out", str(tmp_path / "run")]) == 1
    assert f"--data names the store {store} twice" in error_line(capsys)
    assert not (tmp_path / "run").exists()


def test_threads_are_chosen_not_inherited(monkeypatch):
    monkeypatch.setattr("os.sched_getaffinity", lambda pid: {0, 1, 2})
    monkeypatch.delenv("OMP_NUM_THREADS", raising=False)
    assert choose_threads() == 3  # the cores this process may use, not the machine's
    monkeypatch.setenv("OMP_NUM_THREADS", "1")
    assert choose_threads() == 1  # the convention is respected
    assert choose_threads(2) == 2  # --threads wins
    with pytest.raises(ValueError, match="--threads must be a positive integer, got 0"):
        choose_threads(0)


def test_every_command_takes_threads(store, tmp_path, capsys, monkeypatch):
    import torch

    monkeypatch.setenv("OMP_NUM_THREADS", "2")
    before = torch.get_num_threads()
    try:
        assert main(["data", "info", str(store), "--threads", "1"]) == 0
        assert torch.get_num_threads() == 1
        assert main(["data", "info", str(store)]) == 0
        assert torch.get_num_threads() == 2
    finally:
        torch.set_num_threads(before)
    from iwsim.cli import _leaf_parsers, build_parser

    for parser in _leaf_parsers(build_parser()):
        assert "--threads" in parser._option_string_actions, parser.prog


@pytest.mark.parametrize("argv, message", [
    (["train", "ae", "--preset", "tiny", "--batch-size", "100000"], "--batch-size 100000 (about 20.0 MiB per sample)"),
    (["train", "dynamics", "--preset", "tiny", "--ae", "unused", "--batch-size", "100000"], "--batch-size 100000"),
    (["train", "policy", "--policy", "dp", "--preset", "tiny-dp", "--batch-size", "100000000"], "--batch-size"),
    (["data", "import", "--format", "zarr", "--image-size", "100000"], "--image-size 100000 (for a single frame)"),
    (["collect", *TINY_COLLECT[:-2], "--workers", "1", "--episodes", "1", "--steps", "99999999999"],
     "episodes of 99999999999 steps at 64x64 with 1 worker(s)"),
    (["eval", "policy", "--checkpoint", "unused", "--steps", "10000000000", "--videos", "4"], "--steps 10000000000"),
    (["demo", "--steps", "10000000000"], "--steps 10000000000"),
    (["demos", "--episodes", "1", "--batch", "16", "--steps", "10000000000"], "--batch 16 of --steps 10000000000"),
])
def test_flags_that_size_memory_are_refused_before_allocating(store, tmp_path, capsys, argv, message):
    out = tmp_path / "out"
    argv = [*argv, "--out", str(out)]
    if argv[0] in ("train",):
        argv += ["--data", str(store)]
    if argv[:2] == ["data", "import"]:
        argv += ["--in", str(store)]
    assert main(argv) == 1
    line = error_line(capsys)
    assert message in line and "would need about" in line and "available" in line
    assert not out.exists()


def test_export_model_force_replaces_only_a_checkpoint_iwsim_wrote(tmp_path, capsys, monkeypatch):
    """Issue 26: ``--force`` deleted any directory; now it refuses anything but a checkpoint
    directory holding only what iwsim writes, and the user's files stay."""
    from tests.test_dynamics import tiny_world_model

    src = tiny_world_model().save(tmp_path / "wm")
    user = tmp_path / "userdata"
    (user / "sub").mkdir(parents=True)
    (user / "sub" / "thesis.txt").write_text("years of work")
    assert main(["export-model", "--run", str(src), "--out", str(user), "--force"]) == 1
    assert "not an iwsim checkpoint" in error_line(capsys)
    assert (user / "sub" / "thesis.txt").read_text() == "years of work"
    monkeypatch.chdir(user)
    assert main(["export-model", "--run", str(src), "--out", ".", "--force"]) == 1
    assert "not an iwsim checkpoint" in error_line(capsys)
    # a checkpoint with a file the user added beside it is not replaced either
    ckpt = tiny_world_model(seed=1).save(tmp_path / "ckpt")
    (ckpt / "notes.txt").write_text("mine")
    assert main(["export-model", "--run", str(src), "--out", str(ckpt), "--force"]) == 1
    assert "holds what a checkpoint does not (notes.txt)" in error_line(capsys)
    assert (ckpt / "notes.txt").read_text() == "mine"
    # a checkpoint iwsim wrote is replaced
    (ckpt / "notes.txt").unlink()
    assert main(["export-model", "--run", str(src), "--out", str(ckpt), "--force"]) == 0
    assert (ckpt / "model.safetensors").read_bytes() == (src / "model.safetensors").read_bytes()
    assert sorted(p.name for p in tmp_path.iterdir() if p.name.startswith(".")) == []


def test_export_model_sets_inference_settings_and_refuses_negative_ones(tmp_path, capsys):
    """The rest rule and the deadband act only at inference: a checkpoint carries its own
    values (recorded beside the run's in its provenance), the weights unchanged."""
    from iwsim.world_model import WorldModel
    from tests.test_dynamics import tiny_world_model

    src = tiny_world_model().save(tmp_path / "wm")
    out = tmp_path / "rest"
    assert main(["export-model", "--run", str(src), "--out", str(out), "--rest-threshold", "0.05",
                 "--delta-deadband", "0.06"]) == 0
    wm = WorldModel.load(out)
    assert (wm.cfg.rest_threshold, wm.cfg.delta_deadband) == (0.05, 0.06)
    assert WorldModel.load(src).cfg.rest_threshold == 0.0
    assert (out / "model.safetensors").read_bytes() == (src / "model.safetensors").read_bytes()
    assert load_json(out / "config.json")["provenance"]["inference"]["rest_threshold"] == [0.0, 0.05]
    assert main(["export-model", "--run", str(src), "--out", str(tmp_path / "bad"), "--rest-threshold", "-1"]) == 1
    assert "rest_threshold must be a finite number >= 0, got -1.0" in error_line(capsys)
    assert not (tmp_path / "bad").exists()
    # issue 65 row 8: an infinite deadband would freeze every frame
    assert main(["export-model", "--run", str(src), "--out", str(tmp_path / "bad"), "--delta-deadband", "inf"]) == 1
    assert "delta_deadband must be a finite number >= 0, got inf" in error_line(capsys)
    assert not (tmp_path / "bad").exists()


@pytest.mark.parametrize("task", ["pusht", "pilesweep"])
def test_demo_refuses_a_negative_seed_in_one_line(task, tmp_path, capsys):
    """Issue 65 row 7: a negative MuJoCo seed is one line, before anything runs."""
    assert main(["demo", "--task", task, "--seed", "-3", "--out", str(tmp_path / "demo")]) == 1
    assert "--seed must be a non-negative integer, got -3" in error_line(capsys)
    assert not (tmp_path / "demo").exists()


@pytest.mark.parametrize("part,size,says", [("codec", 10**5, "of memory"), ("codec", 10**9, "can be built"),
                                            ("dynamics", 10**6, "of memory")])
def test_absurd_sizes_in_a_checkpoint_config_are_one_line_before_allocation(store, tmp_path, capsys, part, size, says):
    """Issue 26: encoder channels of 10^9 in config.json gave a traceback from a 108 GB
    allocation; the sizes are now checked on the meta device first."""
    import json
    import time

    from tests.test_dynamics import tiny_world_model

    ckpt = tiny_world_model().save(tmp_path / "wm")
    config = json.loads((ckpt / "config.json").read_text())
    if part == "codec":
        config["codec"]["config"]["encoder"]["channels"] = [size, 8, 8]
    else:
        config["stage2"]["dynamics"]["channels"] = size
    (ckpt / "config.json").write_text(json.dumps(config))
    t0 = time.perf_counter()
    assert main(["rollout", "--checkpoint", str(ckpt), "--data", str(store),
                 "--out", str(tmp_path / "v.mp4")]) == 1
    line = error_line(capsys)
    assert f"the {part} of {ckpt}" in line and says in line, line
    assert time.perf_counter() - t0 < 30


def test_max_sessions_is_checked_against_memory_before_anything_starts(tmp_path, capsys):
    """Issue 26: --max-sessions had no memory check (60 sessions took 1 GiB)."""
    assert main(["play", "--checkpoint", str(tmp_path / "none"), "--port", "0", "--max-sessions", "1000000"]) == 1
    line = error_line(capsys)
    assert "--max-sessions 1000000 (about" in line and "of memory" in line
    assert main(["play", "--checkpoint", str(tmp_path / "none"), "--port", "0", "--max-sessions", "0"]) == 1
    assert "--max-sessions must be a positive integer" in error_line(capsys)


# -- issue 42 ------------------------------------------------------------------------------


def _wait_saves(eng) -> list:
    import time

    deadline = time.monotonic() + 30
    while time.monotonic() < deadline:
        if done := eng.finished_saves():
            return done
        time.sleep(0.01)
    raise AssertionError("no save finished")


class FullDisk:
    """Zarr's file writes fail with ENOSPC after ``allow`` more writes (None: never)."""

    def __init__(self, monkeypatch: pytest.MonkeyPatch) -> None:
        import zarr.storage._local as local

        self.allow: int | None = None
        real = local._put

        def put(*args, **kwargs):
            if self.allow is not None:
                if self.allow <= 0:
                    import errno

                    raise OSError(errno.ENOSPC, "No space left on device")
                self.allow -= 1
            return real(*args, **kwargs)

        monkeypatch.setattr(local, "_put", put)


@pytest.mark.parametrize("allow", [0, 1, 3, 6])
def test_row1_a_failed_save_keeps_the_take_and_the_store(tmp_path, monkeypatch, allow):
    """Issue 42 row 1: a save on a full disk broke every later save and dropped the take."""
    import json

    import numpy as np

    from iwsim.data.store import EpisodeStore
    from iwsim.play import protocol as proto
    from tests.test_play import engine

    disk = FullDisk(monkeypatch)
    store = tmp_path / "demos.zarr"
    eng = engine(record_to=store)
    s = eng.open()
    takes = []
    for n in (3, 2):  # the first take fails on a fresh store, the second on one that holds it
        eng.handle(s, proto.Command("record"))
        for _ in range(n):
            eng.tick()
        takes.append(np.stack(s.take["img"]))
        disk.allow = allow
        eng.handle(s, proto.Command("save"))
        (_, text), = _wait_saves(eng)
        assert "saving failed" in json.loads(text)["message"] and "is kept" in json.loads(text)["message"]
        assert EpisodeStore.open(store).n_episodes == len(takes) - 1  # the store is as it was
        assert "could not be saved" in json.loads(eng.handle(s, proto.Command("record"))[0])["message"]
        disk.allow = None  # space is freed
        eng.handle(s, proto.Command("save"))
        (_, text), = _wait_saves(eng)
        assert json.loads(text)["type"] == "saved"
        back = EpisodeStore.open(store)
        assert back.n_episodes == len(takes)
        np.testing.assert_array_equal(back.episode(-1)["img"], takes[-1])
    eng.shutdown()
    assert EpisodeStore.open(store).n_episodes == 2


def test_row14_a_lock_that_cannot_be_opened_is_one_error_only(tmp_path, monkeypatch):
    """Issue 42 row 14: a read-only disk gave one line, then 'Exception ignored in DirLock.__del__'."""
    import errno
    import gc
    import sys

    from iwsim.core import lock as lockmod
    from iwsim.data.store import EpisodeStore, StoreError

    store = tmp_path / "s.zarr"
    EpisodeStore.create(store).close()
    unraisable = []
    monkeypatch.setattr(sys, "unraisablehook", unraisable.append)

    def read_only(*args, **kwargs):
        raise OSError(errno.EROFS, "Read-only file system")

    monkeypatch.setattr(lockmod.os, "open", read_only)
    with pytest.raises(StoreError, match="Read-only file system"):
        EpisodeStore.open(store, "a")
    gc.collect()
    assert unraisable == []


def test_row15_the_message_limit_counts_bytes():
    """Issue 42 row 15: 4,096 emoji (16,180 bytes) passed the 4 KiB limit."""
    from iwsim.play import protocol as proto

    msg = '{"type": "action", "seq": 1, "action": [0, 0, 0, 0], "pad": "' + "\U0001F600" * 4096 + '"}'
    assert len(msg) < 4 * proto.MAX_MESSAGE_BYTES
    with pytest.raises(proto.ProtocolError, match="16.* bytes is over the limit of 4096"):
        proto.parse(msg, 4)
    assert proto.parse('{"type": "record", "pad": "' + "é" * 1000 + '"}', 4) == proto.Command("record")


def test_row16_a_websocket_for_a_foreign_host_is_refused():
    """Issue 42 row 16: a WebSocket with Host: evil.example.com:PORT and the token got a session."""
    import socket

    from iwsim.play.server import running
    from tests.test_play import engine

    with running(engine(), token="s3cret-token") as srv:
        host, port = srv.address.rsplit(":", 1)
        for name, status in ((f"evil.example.com:{port}", b"403"), (srv.address, b"101")):
            with socket.create_connection((host, int(port)), timeout=10) as sock:
                sock.sendall((f"GET /ws?token=s3cret-token HTTP/1.1\r\nHost: {name}\r\nUpgrade: websocket\r\n"
                              "Connection: Upgrade\r\nSec-WebSocket-Key: dGhlIHNhbXBsZSBub25jZQ==\r\n"
                              "Sec-WebSocket-Version: 13\r\n\r\n").encode())
                assert sock.recv(64).split()[1] == status


def _store_of(tmp_path: Path, n: int = 4, name: str = "s.zarr") -> Path:
    """A store of ``n`` fake episodes of 30 frames of 64 x 64 (64 frames per image chunk)."""
    import numpy as np

    from iwsim.data.store import EpisodeStore
    from tests.test_store import fake_episode

    path = tmp_path / name
    with EpisodeStore.create(path, {"task": "pusht", "fps": 10, "image_size": 64}) as s:
        for j in range(n):
            ep = fake_episode(j, size=64)
            s.append({k: np.concatenate([v] * 6)[:30] for k, v in ep.items()}, seed=j)
    return path


def one_error(capsys: pytest.CaptureFixture[str]) -> str:
    """The one error line of a command that may also have drawn progress bars; no traceback."""
    err = capsys.readouterr().err
    errors = [line for line in err.splitlines() if line.startswith("iwsim: error: ")]
    assert len(errors) == 1 and "Traceback" not in err, err[-2000:]
    return errors[0]


def _snapshot(path: Path) -> dict[str, bytes]:
    return {str(p.relative_to(path)): p.read_bytes() for p in sorted(path.rglob("*"))
            if p.is_file() and p.name != ".iwsim.lock"}


@pytest.mark.parametrize("ends", [[15, 30, 5, 60], [20, 40, 30, 80]])
def test_row2_an_inconsistent_store_is_refused_not_cut(tmp_path, capsys, ends):
    """Issue 42 row 2: episode_ends [15, 30, 5, 60] was 'repaired' to [15, 30], deleting two takes."""
    import zarr

    from iwsim.data.store import EpisodeStore, StoreError

    path = _store_of(tmp_path)
    zarr.open_array(path / "meta/episode_ends", mode="r+")[:] = ends
    before = _snapshot(path)
    for mode in ("r", "a"):
        with pytest.raises(StoreError, match=r"damaged: meta/episode_ends must increase strictly, but entry 2"):
            EpisodeStore.open(path, mode)
    assert main(["collect", *TINY_COLLECT, "--episodes", "6", "--out", str(path)]) == 1
    assert "must increase strictly" in error_line(capsys)
    assert main(["data", "validate", str(path)]) != 0
    assert _snapshot(path) == before
    # a real interrupted append (one unwritten trailing end, frames past the last end) is still tidied
    zarr.open_array(path / "meta/episode_ends", mode="r+")[:] = [15, 30, 45, 60]
    zarr.open_array(path / "meta/episode_ends", mode="r+").resize((5,))
    with EpisodeStore.open(path, "a") as s:
        assert s.n_episodes == 4
    assert zarr.open_array(path / "meta/episode_ends", mode="r").shape == (4,)


def test_row3_a_missing_chunk_is_named_and_refused(tmp_path, capsys):
    """Issue 42 row 3: a deleted data/img chunk read as black frames, validate said valid and
    merge wrote the black frames for good."""
    path = _store_of(tmp_path)
    chunks = sorted(p for p in (path / "data" / "img").iterdir() if not p.name.startswith("."))
    assert len(chunks) > 1
    chunks[1].unlink()
    assert main(["data", "validate", str(path)]) == 1
    out = capsys.readouterr()
    assert "chunk file of data/img holding frames" in out.out + out.err and "is missing" in out.out + out.err
    other = _store_of(tmp_path, 2, "t.zarr")
    for argv in (["data", "export", "--format", "lerobot-v3", "--in", str(path), "--out", str(tmp_path / "x")],
                 ["data", "merge", str(other), str(path), "--out", str(tmp_path / "m.zarr")]):
        assert main(argv) == 1
        assert "is missing" in one_error(capsys)
    assert not (tmp_path / "m.zarr").exists() and not (tmp_path / "x").exists()


def test_row3_stores_write_every_chunk(tmp_path):
    """A chunk of fill values is written too, so a missing chunk file is always damage."""
    import numpy as np

    from iwsim.data.store import EpisodeStore

    path = tmp_path / "z.zarr"
    with EpisodeStore.create(path) as s:
        s.append({"img": np.zeros((3, 4, 4, 3), np.uint8), "n": np.zeros(3, np.int32)})
    assert EpisodeStore.open(path).episode(0)["n"].tolist() == [0, 0, 0]
    assert (path / "data" / "n" / "0").is_file() and (path / "data" / "img" / "0.0.0.0").is_file()


@pytest.mark.parametrize("shape", [250_000_000, 10**12])
def test_row5_a_declared_size_is_checked_against_the_files(tmp_path, capsys, shape):
    """Issue 42 row 5: episode_ends declared 2.5e8 entries: 21 s and 5.9 GB for a 46 KB store."""
    import json
    import time

    path = _store_of(tmp_path)
    meta = path / "meta" / "episode_ends" / ".zarray"
    z = json.loads(meta.read_text())
    z["shape"] = [shape]
    meta.write_text(json.dumps(z))
    t0 = time.perf_counter()
    assert main(["data", "info", str(path)]) == 1
    assert f"meta/episode_ends declares {shape} entries but its chunk files hold at most 4096" in one_error(capsys)
    assert time.perf_counter() - t0 < 5


@pytest.mark.parametrize("damage", ["truncated", "dtype"])
def test_row10_a_damaged_chunk_is_one_line_everywhere(tmp_path, capsys, damage):
    """Issue 42 row 10: a truncated chunk or an edited dtype gave RuntimeError / ValueError tracebacks."""
    import json

    path = _store_of(tmp_path)
    if damage == "truncated":
        chunk = next(p for p in (path / "data" / "img").iterdir() if not p.name.startswith("."))
        chunk.write_bytes(chunk.read_bytes()[:100])
    else:
        meta = path / "data" / "action" / ".zarray"
        meta.write_text(json.dumps({**json.loads(meta.read_text()), "dtype": "<f8"}))
    other = _store_of(tmp_path, 2, "t.zarr")
    out = tmp_path / "out"
    for argv in (["data", "export", "--format", "lerobot-v3", "--in", str(path), "--out", str(out)],
                 ["data", "export", "--format", "lerobot-v2.1", "--in", str(path), "--out", str(out)],
                 ["data", "export", "--format", "hdf5-aloha", "--in", str(path), "--out", str(out)],
                 ["data", "merge", str(other), str(path), "--out", str(out)],
                 ["train", "policy", "--policy", "dp", "--preset", "tiny-dp", "--data", str(path), "--out", str(out)],
                 ):
        assert main(argv) == 1, argv
        line = one_error(capsys)
        assert "is damaged: a chunk cannot be read" in line, line
        assert not out.exists()


def _policy_args(store: Path, out: Path, *extra: str) -> list[str]:
    return ["train", "policy", "--policy", "dp", "--preset", "tiny-dp", "--data", f"{store}:2", "--out", str(out),
            "--no-progress", "--steps", "2", *extra]


def test_row7_one_training_per_run_directory(play_store, tmp_path, capsys):
    """Issue 42 row 7: two trainings into one --out ran at once and mixed their checkpoints."""
    from iwsim.core.lock import DirLock

    out = tmp_path / "pol"
    out.mkdir()
    with DirLock(out, what="training"):  # the first run, still training
        for extra in ((), ("--seed", "7", "--force")):
            assert main(_policy_args(play_store, out, *extra)) == 1
            line = error_line(capsys)
            assert f"{out} is being written by pid" in line and "train into another --out" in line
    assert sorted(p.name for p in out.iterdir()) == [".iwsim.lock"]
    assert main(_policy_args(play_store, out)) == 0  # once it is done


def test_row8_force_with_another_config_starts_over(play_store, tmp_path):
    """Issue 42 row 8: a finished seed-0 run rerun with --seed 7 --force kept seed 0's weights."""
    from safetensors.torch import load_file

    def weights(out: Path) -> dict:
        return load_file(out / "checkpoints" / "last" / "model.safetensors")

    out, fresh = tmp_path / "pol", tmp_path / "fresh"
    assert main(_policy_args(play_store, out)) == 0
    seed0 = weights(out)
    assert main(_policy_args(play_store, out, "--seed", "7", "--force")) == 0
    assert main(_policy_args(play_store, fresh, "--seed", "7")) == 0
    forced, seed7 = weights(out), weights(fresh)
    assert all(torch_equal(forced[k], seed7[k]) for k in seed7)
    assert not all(torch_equal(forced[k], seed0[k]) for k in seed0)
    lines = (out / "metrics.jsonl").read_text().splitlines()
    assert len(lines) == len((fresh / "metrics.jsonl").read_text().splitlines())


def torch_equal(a, b) -> bool:
    import torch

    return bool(torch.equal(a, b))


def test_row11_a_damaged_latent_cache_is_rebuilt_and_a_wrong_one_refused(play_store, tmp_path, caplog):
    """Issue 42 row 11: a truncated cache gave a SafetensorError; a directory left a 1.3 MB temp."""
    import torch

    from iwsim.core.config import to_dict
    from iwsim.core.errors import InputError
    from iwsim.data.store import EpisodeStore
    from iwsim.world_model.codecs import build_codec
    from iwsim.world_model.dynamics_data import encode_store
    from iwsim.world_model.presets import AE_PRESETS

    codec = build_codec("conv-ae", to_dict(AE_PRESETS["tiny-conv"])).eval()
    store, cpu = EpisodeStore.open(play_store), torch.device("cpu")
    cache = tmp_path / "latents.safetensors"
    good = encode_store(codec, store, cpu, False, cache, chunk=16)
    cache.write_bytes(cache.read_bytes()[: cache.stat().st_size // 2])  # truncated
    assert torch.equal(encode_store(codec, store, cpu, False, cache, chunk=16), good)
    assert "is damaged" in caplog.text
    assert torch.equal(encode_store(codec, store, cpu, False, cache, chunk=16), good)  # rebuilt, whole again
    text = tmp_path / "notes.txt"
    text.write_text("my notes")
    with pytest.raises(InputError, match="is not a latent cache"):
        encode_store(codec, store, cpu, False, text, chunk=16)
    assert text.read_text() == "my notes"
    folder = tmp_path / "dir"
    folder.mkdir()
    with pytest.raises(InputError, match="is a directory"):
        encode_store(codec, store, cpu, False, folder, chunk=16)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["dir", "latents.safetensors", "notes.txt"]


def test_row12_a_full_disk_while_training_is_one_line(play_store, tmp_path, capsys, monkeypatch):
    """Issue 42 row 12: a checkpoint on a full disk gave a SafetensorError traceback."""
    import errno

    import safetensors.torch

    out = tmp_path / "pol"
    real = safetensors.torch.save_file

    def full(*args, **kwargs):
        raise safetensors.SafetensorError("Error while serializing: I/O error: No space left on device "
                                          "(os error 28)")

    monkeypatch.setattr("iwsim.core.checkpoint.save_file", full)
    assert main(_policy_args(play_store, out)) == 1
    line = error_line(capsys)
    assert "cannot write checkpoint 00000002" in line and os_strerror(errno.ENOSPC) in line, line
    assert "resumes from the start" in line
    assert sorted(p.name for p in (out / "checkpoints").iterdir()) == []  # no temporary left
    monkeypatch.setattr("iwsim.core.checkpoint.save_file", real)
    assert main(_policy_args(play_store, out)) == 0


def os_strerror(code: int) -> str:
    import os

    return os.strerror(code)


def test_row13_a_config_of_another_shape_is_one_line(tmp_path, capsys):
    """Issue 42 row 13: provenance.data as a list (a policy's) gave a TypeError in task_from_config."""
    import json

    from iwsim.core.errors import InputError
    from iwsim.envs.registry import task_from_config

    low, high = [-0.2] * 4, [0.2] * 4
    config = {"kind": "world_model", "action_norm": {"low": low, "high": high},
              "provenance": {"data": ["a.zarr", "b.zarr"]}}
    assert task_from_config(config).kind == "pusht"  # the store is gone: T-push by its 4-D actions
    for bad in ({"action_norm": [1, 2]}, {"action_norm": {"low": "x", "high": "y"}}, {"provenance": 3, "data": 7},
                {"action_norm": {"low": [0, "a"], "high": [1, 2]}}):
        with pytest.raises(InputError, match="no action bounds"):
            task_from_config(bad)
    run = tmp_path / "policy_run"
    run.mkdir()
    (run / "config.json").write_text(json.dumps({"kind": "policy", "provenance": {"data": ["x.zarr"]}}))
    (run / "model.safetensors").write_bytes(b"")
    assert main(["experiment", "policy-eval", "--world-model", str(run), "--out", str(tmp_path / "o"),
                 "--work", str(tmp_path / "w")]) == 1
    assert "is a 'policy' checkpoint, not a world model" in error_line(capsys)


@pytest.fixture(scope="module")
def lerobot(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    """LeRobot v3 and v2.1 exports of a small fake store."""
    root = tmp_path_factory.mktemp("lerobot")
    store = _store_of(root, 2)
    out = {}
    for fmt in ("lerobot-v3", "lerobot-v2.1"):
        out[fmt] = root / fmt
        assert main(["data", "export", "--format", fmt, "--in", str(store), "--out", str(out[fmt]), "--no-progress",
                     "--task", "t"]) == 0
    return out


def _copy(src: Path, dst: Path) -> Path:
    import shutil

    shutil.copytree(src, dst)
    return dst


def _edit_json(path: Path, edit) -> None:
    import json

    obj = json.loads(path.read_text())
    edit(obj)
    path.write_text(json.dumps(obj))


def _problems(path: Path) -> list[str]:
    from iwsim.data.formats import validate

    return validate(path)[1]


def test_row17_lerobot_validate_names_what_import_would_choke_on(lerobot, tmp_path, capsys):
    """Issue 42 row 17: fps 0, episodes.jsonl lengths of 10**9, a parquet without episode_index and an
    action dtype "string" were all called valid (and fps 0 imported into a store validate rejects)."""
    import pyarrow.parquet as pq

    assert _problems(lerobot["lerobot-v3"]) == [] and _problems(lerobot["lerobot-v2.1"]) == []
    v3 = _copy(lerobot["lerobot-v3"], tmp_path / "fps0")
    _edit_json(v3 / "meta/info.json", lambda i: i.update(fps=0))
    assert any("fps': 0, expected a positive number" in p or "key 'fps': 0" in p for p in _problems(v3))
    assert main(["data", "import", "--format", "lerobot-v3", "--in", str(v3), "--out", str(tmp_path / "i.zarr")]) == 1
    assert "key 'fps': 0, expected a positive number" in one_error(capsys)
    assert not (tmp_path / "i.zarr").exists()

    v21 = _copy(lerobot["lerobot-v2.1"], tmp_path / "long")
    lines = (v21 / "meta/episodes.jsonl").read_text().splitlines()
    (v21 / "meta/episodes.jsonl").write_text("\n".join(line.replace('"length": 30', '"length": 1000000000')
                                                       for line in lines) + "\n")
    assert any("says length 1000000000, the data file holds 30 rows" in p for p in _problems(v21))

    v3 = _copy(lerobot["lerobot-v3"], tmp_path / "noindex")
    data = next((v3 / "data").rglob("*.parquet"))
    pq.write_table(pq.read_table(data).drop(["episode_index"]), data)
    assert any("key 'episode_index' (episode 0): column missing" in p for p in _problems(v3))

    v3 = _copy(lerobot["lerobot-v3"], tmp_path / "string")
    _edit_json(v3 / "meta/info.json", lambda i: i["features"]["action"].update(dtype="string"))
    assert any("features.action.dtype': 'string', expected one of float32" in p for p in _problems(v3))


@pytest.mark.parametrize("name", ["meta/info.json", "meta/episodes.jsonl"])
def test_row5_lerobot_metadata_is_read_with_a_cap(lerobot, tmp_path, capsys, name):
    """Issue 42 row 5: meta/info.json or episodes.jsonl symlinked to /dev/zero was read until memory ran out."""
    src = _copy(lerobot["lerobot-v2.1"], tmp_path / "zero")
    (src / name).unlink()
    (src / name).symlink_to("/dev/zero")
    assert main(["data", "import", "--format", "lerobot-v2.1", "--in", str(src), "--out",
                 str(tmp_path / "i.zarr")]) == 1
    assert f"{src / name}: not a regular file." in one_error(capsys)
    assert not (tmp_path / "i.zarr").exists()
    assert any("not a regular file" in p for p in _problems(src))


def test_row4_hdf5_export_on_a_full_disk_is_one_line_and_leaves_nothing(tmp_path, capsys, monkeypatch):
    """Issue 42 row 4: hdf5-aloha export on a full disk crashed (rc 139) and left its temp directory."""
    import builtins
    import errno

    from iwsim.data.formats import hdf5

    store = _store_of(tmp_path, 2)
    writes = []

    def full_open(path, mode="r", *args, **kwargs):
        f = builtins.open(path, mode, *args, **kwargs)
        if "w" in mode:
            def write(data):
                writes.append(path)
                raise OSError(errno.ENOSPC, "No space left on device")

            f.write = write
        return f

    monkeypatch.setattr(hdf5, "open", full_open, raising=False)
    out = tmp_path / "aloha"
    assert main(["data", "export", "--format", "hdf5-aloha", "--in", str(store), "--out", str(out)]) == 1
    assert "No space left on device" in one_error(capsys) and writes
    assert sorted(p.name for p in tmp_path.iterdir()) == ["s.zarr"]  # no output, no temporary
    monkeypatch.undo()
    assert main(["data", "export", "--format", "hdf5-aloha", "--in", str(store), "--out", str(out)]) == 0
    assert _problems(out) == []


@pytest.mark.parametrize("env", ["pusht", "world-model"])
def test_row6_episodes_that_cannot_fit_are_refused_before_anything_runs(tmp_path, capsys, env):
    """Issue 42 row 6: eval policy --episodes 100000000 grew from 1.2 to 7.9 GB in 32 s, no output."""
    import time

    t0 = time.perf_counter()
    assert main(["eval", "policy", "--checkpoint", str(tmp_path / "unused"), "--env", env, "--episodes",
                 "100000000", "--out", str(tmp_path / "e")]) == 1
    line = error_line(capsys)
    assert f"--episodes 100000000 of 600 steps in {env}, run together would need about" in line
    assert time.perf_counter() - t0 < 5 and not (tmp_path / "e").exists()


def test_row9_expensive_messages_are_charged_by_their_cost():
    """Issue 42 row 9: toggling side_by_side ~80 times a second (under the drop limit) took another
    session from 10.0 to 3.9 frames/s."""
    import json
    import time

    from websockets.sync.client import connect

    from iwsim.play.server import COST_REASON, MAX_MESSAGES_PER_STEP, MessageBudget, running
    from tests.test_play import engine, receive

    now = [0.0]
    budget = MessageBudget(MAX_MESSAGES_PER_STEP * 10, clock=lambda: now[0])
    assert budget.take(100) and budget.take(100) and not budget.take(100) and budget.take(1) is False
    now[0] += 1.0
    assert budget.take(100) and not budget.take(1)  # a second buys one expensive message back

    eng = engine(max_sessions=2)
    with running(eng) as srv, connect(srv.ws) as toggler, connect(srv.ws) as other:
        receive(toggler, "hello")
        receive(other, "hello")
        t0 = time.monotonic()
        for i in range(80):  # 80 a second: under the 100 messages a second that drop a client
            toggler.send(json.dumps({"type": "side_by_side", "on": i % 2 == 0}))
            time.sleep(max(0.0, t0 + (i + 1) / 80 - time.monotonic()))
        toggler.send(json.dumps({"type": "action", "seq": 1, "action": [0.0, 0.0, 0.0, 0.0]}))
        applied = refused = 0
        while applied + refused < 80:
            data = toggler.recv(timeout=30)
            if isinstance(data, bytes):
                continue
            m = json.loads(data)
            applied += m["type"] == "status" and "side by side" in m["message"]
            refused += m["type"] == "error" and m["message"] == COST_REASON
        assert applied <= 4 and refused >= 76, (applied, refused)
        receive(toggler, "frame", where=lambda h: h["ack"] == 1)  # the session goes on
        receive(other, "frame")


# -- issue 42: the probe's findings -----------------------------------------------------------


@pytest.mark.parametrize("damage, says", [
    ("zattrs_dev_zero", ".zattrs: not a regular file"),
    ("zarray_not_json", "data/img/.zarray is not a JSON object"),
    ("ends_float", "meta/episode_ends holds float64, not integers"),
])
def test_probe_damaged_store_metadata_is_one_line(tmp_path, capsys, damage, says):
    """Zarr read a .zattrs symlinked to /dev/zero until memory ran out, a .zarray that is not
    JSON gave a traceback, and float episode ends were silently cut to integers."""
    import zarr

    path = _store_of(tmp_path, 2)
    if damage == "zattrs_dev_zero":
        (path / ".zattrs").unlink()
        (path / ".zattrs").symlink_to("/dev/zero")
    elif damage == "zarray_not_json":
        (path / "data" / "img" / ".zarray").write_text("{oops")
    else:
        ends = zarr.open_array(path / "meta/episode_ends", mode="r")[:]
        group = zarr.open_group(path, mode="r+")
        del group["meta/episode_ends"]
        group["meta"].create_array("episode_ends", data=ends.astype("f8") + 0.5, chunks=(4096,))
    assert main(["data", "info", str(path)]) == 1
    line = one_error(capsys)
    assert f"{path} is damaged" in line and says in line, line


def test_probe_merging_a_store_with_itself_is_refused(tmp_path, capsys):
    path = _store_of(tmp_path, 2)
    assert main(["data", "merge", str(path), str(tmp_path / "." / path.name), "--out", str(tmp_path / "m.zarr")]) == 1
    assert f"merge names the store {path} twice" in one_error(capsys)
    assert not (tmp_path / "m.zarr").exists()


@pytest.mark.parametrize("what", ["token", "bindings", "checkpoint config"])
def test_probe_small_files_a_user_names_are_read_with_a_cap(tmp_path, capsys, what):
    """A token file, a bindings file or a checkpoint's config.json symlinked to /dev/zero was
    read until memory ran out (MemoryError tracebacks), or called missing."""
    from tests.test_dynamics import tiny_world_model

    zero = tmp_path / "zero"
    zero.symlink_to("/dev/zero")
    if what == "checkpoint config":
        ckpt = tiny_world_model().save(tmp_path / "wm")
        (ckpt / "config.json").unlink()
        (ckpt / "config.json").symlink_to("/dev/zero")
        argv = ["rollout", "--checkpoint", str(ckpt), "--data", str(_store_of(tmp_path, 1)), "--out",
                str(tmp_path / "v.mp4")]
        says = f"{ckpt / 'config.json'}: not a regular file."
    else:
        flag = "--token-file" if what == "token" else "--bindings"
        argv = ["play", "--checkpoint", str(tmp_path / "unused"), flag, str(zero), "--port", "0"]
        says = f"{zero}: not a regular file."
    assert main(argv) == 1
    assert says in one_error(capsys)


def test_probe_a_latent_cache_shorter_than_its_hashes_is_rebuilt(play_store, tmp_path):
    """A cache whose metadata matched but which held fewer latents than its chunks gave an IndexError."""
    import torch
    from safetensors import safe_open
    from safetensors.torch import save_file

    from iwsim.core.config import to_dict
    from iwsim.data.store import EpisodeStore
    from iwsim.world_model.codecs import build_codec
    from iwsim.world_model.dynamics_data import encode_store
    from iwsim.world_model.presets import AE_PRESETS

    codec = build_codec("conv-ae", to_dict(AE_PRESETS["tiny-conv"])).eval()
    store, cpu, cache = EpisodeStore.open(play_store), torch.device("cpu"), tmp_path / "c.safetensors"
    good = encode_store(codec, store, cpu, False, cache, chunk=16)
    with safe_open(cache, "pt") as f:
        meta, latents = f.metadata(), f.get_tensor("latents")
    for short in (latents[:5], latents[:40]):  # in the first chunk; in the last
        save_file({"latents": short.contiguous()}, cache, metadata=meta)
        assert torch.equal(encode_store(codec, store, cpu, False, cache, chunk=16), good)


@pytest.mark.parametrize("flag", ["--out", "--work"])
def test_probe_a_study_directory_that_is_a_file_is_refused_before_any_work(tmp_path, capsys, flag):
    """--out naming a file was found only after the whole study had run (minutes to hours)."""
    from tests.test_dynamics import tiny_world_model

    wm = tiny_world_model().save(tmp_path / "wm")
    (tmp_path / "f").write_text("mine")
    dirs = {"--out": str(tmp_path / "o"), "--work": str(tmp_path / "w"), flag: str(tmp_path / "f")}
    assert main(["experiment", "policy-eval", "--world-model", str(wm), *[x for kv in dirs.items() for x in kv]]) == 1
    assert f"{flag} {tmp_path / 'f'} is a file; expected a directory" in error_line(capsys)
    assert (tmp_path / "f").read_text() == "mine"


def test_the_batch_memory_check_reads_the_frames_a_store_holds(tmp_path, capsys):
    """A store imported at its source's size records no image_size: the check sizes a
    sample by the frames themselves (128 px here: 4x the bytes of 64 px)."""
    import numpy as np

    from iwsim.data.store import EpisodeStore

    path = tmp_path / "big.zarr"
    with EpisodeStore.create(path, {"task": "robot", "fps": 10}) as s:
        s.append({"img": np.zeros((3, 128, 128, 3), np.uint8), "action": np.zeros((3, 2), np.float32)})
    assert main(["train", "ae", "--preset", "tiny", "--batch-size", "100000", "--data", str(path),
                 "--out", str(tmp_path / "out")]) == 1
    assert "--batch-size 100000 (about 80.0 MiB per sample)" in error_line(capsys)


def test_a_model_with_non_finite_weights_is_refused_in_one_line(tmp_path, capsys):
    """Issue 65 row 2: NaN weights used to run as a working model (black frames, NaN
    scores); every command that loads a model now names the broken tensor."""
    from safetensors.torch import load_file, save_file

    from iwsim.core.checkpoint import CheckpointError
    from iwsim.policies.factory import load_policy
    from iwsim.world_model import WorldModel
    from tests.test_dynamics import tiny_world_model

    src = tiny_world_model().save(tmp_path / "wm")
    tensors = load_file(src / "model.safetensors")
    name = next(k for k in tensors if k.startswith("dynamics.") and k.endswith("weight"))
    tensors[name] = torch.full_like(tensors[name], float("nan"))
    save_file(tensors, src / "model.safetensors")
    with pytest.raises(CheckpointError, match=f"tensor '{name}' holds NaN"):
        WorldModel.load(src)
    assert main(["export-model", "--run", str(src), "--out", str(tmp_path / "copy")]) == 1
    assert name in error_line(capsys) and not (tmp_path / "copy").exists()
    policy = tmp_path / "dp"
    shutil.copytree(ROOT / "checkpoints" / "dp-pusht-64", policy)
    tensors = load_file(policy / "model.safetensors")
    name = next(k for k in tensors if tensors[k].is_floating_point())
    tensors[name][0] = float("inf")
    save_file(tensors, policy / "model.safetensors")
    with pytest.raises(CheckpointError, match="infinite"):
        load_policy(policy)


def test_export_model_force_never_replaces_another_kind_nor_deletes_what_it_did_not_write(tmp_path, capsys):
    """Issue 65 row 1: ``--force`` over a policy checkpoint replaced it with a world model
    and deleted its README.md and metrics.json; a self-export deleted them too."""
    from tests.test_dynamics import tiny_world_model

    src = tiny_world_model().save(tmp_path / "wm")
    policy = tmp_path / "dp"
    shutil.copytree(ROOT / "checkpoints" / "dp-pusht-64", policy)
    before = {p.name: p.read_bytes() for p in policy.iterdir()}
    assert main(["export-model", "--run", str(src), "--out", str(policy), "--force"]) == 1
    assert "is a policy, not a world model" in error_line(capsys)
    assert {p.name: p.read_bytes() for p in policy.iterdir()} == before
    # a world model's README.md and metrics.json (a person's, a ship script's) stay when its weights are replaced
    ckpt = tiny_world_model(seed=1).save(tmp_path / "ckpt")
    (ckpt / "README.md").write_text("how it was made")
    (ckpt / "metrics.json").write_text('{"psnr": 30}')
    assert main(["export-model", "--run", str(src), "--out", str(ckpt), "--force"]) == 0
    assert (ckpt / "model.safetensors").read_bytes() == (src / "model.safetensors").read_bytes()
    assert (ckpt / "README.md").read_text() == "how it was made"
    assert (ckpt / "metrics.json").read_text() == '{"psnr": 30}'
    # and a checkpoint exported onto itself keeps them too
    assert main(["export-model", "--run", str(ckpt), "--out", str(ckpt), "--force", "--rest-threshold", "0.05"]) == 0
    assert (ckpt / "README.md").read_text() == "how it was made" and (ckpt / "metrics.json").exists()
    assert load_json(ckpt / "config.json")["stage2"]["rest_threshold"] == 0.05
    assert sorted(p.name for p in tmp_path.iterdir() if p.name.startswith(".")) == []


def test_a_world_model_is_not_its_own_trust_partner(tmp_path, capsys):
    """Issue 65 row 10: --trust-model given the --world-model (or its weights at another
    path) reported "0% of episodes differ", the model checked against itself."""
    wm = ROOT / "checkpoints" / "pusht-64"
    copy = tmp_path / "copy"
    shutil.copytree(wm, copy)
    for partner in (wm, copy):
        assert main(["eval", "policy", "--checkpoint", str(ROOT / "checkpoints" / "dp-pusht-64"), "--env",
                     "world-model", "--world-model", str(wm), "--trust-model", str(partner), "--episodes", "1",
                     "--steps", "2", "--out", str(tmp_path / "eval")]) == 1
        assert "holds the same weights as --world-model" in error_line(capsys)
        assert not (tmp_path / "eval").exists()


def test_export_model_refuses_novelty_data_of_another_task(tmp_path, capsys, store):
    """Issue 65 row 9: a T-push store's statistics were fitted into a pile-sweeping model."""
    assert main(["export-model", "--run", str(ROOT / "checkpoints" / "pilesweep-64"), "--out", str(tmp_path / "wm"),
                 "--novelty-data", str(store), "--no-progress"]) == 1
    assert "holds episodes of task 'pusht' but the world model is of 'pilesweep'" in error_line(capsys)
    assert not (tmp_path / "wm").exists()


def test_a_demonstration_store_resumes_with_its_model_reached_by_another_path(tmp_path, capsys, monkeypatch):
    """Issue 65 row 12: ``iwsim demos --world-model ckpts/wm`` rerun with ``ckpts/wm/``, an
    absolute path or a copy was refused though the weights' hashes matched; another model
    still is."""
    from iwsim.data.store import EpisodeStore
    from tests.test_dynamics import tiny_world_model

    monkeypatch.chdir(tmp_path)
    tiny_world_model().save(tmp_path / "ckpts" / "wm")
    copy = shutil.copytree(tmp_path / "ckpts" / "wm", tmp_path / "copy")
    base = ["demos", "--steps", "4", "--accept-iou", "0", "--tail", "0", "--batch", "1", "--out", "d.zarr",
            "--no-progress"]
    for n, model in enumerate(("ckpts/wm", "ckpts/wm/", str(tmp_path / "ckpts" / "wm"), str(copy)), 1):
        assert main([*base, "--episodes", str(n), "--world-model", model]) == 0, model
        assert EpisodeStore.open("d.zarr").n_episodes == n
    capsys.readouterr()
    tiny_world_model(seed=1).save(tmp_path / "other")
    assert main([*base, "--episodes", "5", "--world-model", "other"]) == 1
    assert "world_model_sha256=" in error_line(capsys)
    assert EpisodeStore.open("d.zarr").n_episodes == 4


def test_row14_a_collect_killed_in_its_first_episode_leaves_a_store_any_collect_fills(tmp_path, capsys):
    """Issue 65 row 14: kill -9 of ``iwsim collect`` in its first episode left an empty
    store that ``data validate`` called 4 problems and a collect with other flags refused
    ("holds episodes with steps=200", though it held none)."""
    import os
    import signal
    import subprocess
    import sys
    import time

    from iwsim.data.store import EpisodeStore

    out = tmp_path / "s.zarr"
    iwsim = str(Path(sys.executable).parent / "iwsim")
    proc = subprocess.Popen([iwsim, "collect", "--task", "pusht", "--policy", "play", "--episodes", "1", "--steps",
                             "5000", "--workers", "1", "--no-progress", "--out", str(out)],
                            env={**os.environ, "MUJOCO_GL": "egl"})
    deadline = time.monotonic() + 120
    while not (out / ".zattrs").is_file() and proc.poll() is None and time.monotonic() < deadline:
        time.sleep(0.05)
    time.sleep(0.5)  # into the first episode
    proc.send_signal(signal.SIGKILL)
    proc.wait()
    assert EpisodeStore.open(out).n_episodes == 0
    assert main(["data", "validate", str(out)]) == 1
    printed = capsys.readouterr()
    assert "1 problem(s)" in printed.out + printed.err and "an empty store" in printed.out + printed.err
    assert main(["collect", *TINY_COLLECT, "--episodes", "1", "--out", str(out)]) == 0  # 3 steps, not 5000
    store = EpisodeStore.open(out)
    assert store.n_episodes == 1 and store.attrs["steps"] == 3 and store.episode_ends.tolist() == [3]
    assert main(["data", "validate", str(out)]) == 0
    # a store that holds episodes still takes only its own command's
    capsys.readouterr()
    assert main(["collect", *TINY_COLLECT[:4], "--steps", "4", "--workers", "1", "--no-progress", "--episodes", "2",
                 "--out", str(out)]) == 1
    assert "holds episodes with steps=3, not steps=4" in error_line(capsys)


def test_row14_an_empty_demonstration_store_is_refilled_unless_it_records_tried_candidates(tmp_path, capsys):
    """The same for ``iwsim demos``: a store holding no takes and no tried candidates takes
    another recipe; one whose candidates all failed keeps its record and refuses it."""
    from iwsim.data.store import EpisodeStore
    from iwsim.experiments.demos import demo_attrs

    out = tmp_path / "d.zarr"
    EpisodeStore.create(out, demo_attrs("pusht", 300, 64, None, 300000, 0.9, 10)).close()
    base = ["demos", "--task", "pusht", "--steps", "4", "--accept-iou", "0", "--tail", "0", "--batch", "1",
            "--no-progress", "--out", str(out)]
    assert main([*base, "--episodes", "1"]) == 0
    assert EpisodeStore.open(out).attrs["steps"] == 4 and EpisodeStore.open(out).n_episodes == 1
    failed = tmp_path / "failed.zarr"
    store = EpisodeStore.create(failed, demo_attrs("pusht", 300, 64, None, 300000, 0.9, 10))
    store.update_attrs({"candidates_tried": 32, "candidate_max_iou": [0.1] * 32})
    store.close()
    capsys.readouterr()
    assert main([*base[:-1], str(failed), "--episodes", "1"]) == 1
    assert "steps=300" in error_line(capsys) and EpisodeStore.open(failed).attrs["candidates_tried"] == 32


def test_row2_a_model_whose_finite_weights_overflow_is_refused_at_its_first_step(tmp_path, capsys):
    """Issue 65 row 2, its other half: finite weights that overflow (here a dynamics layer
    scaled by 1e30) gave NaN frames and scores through every command; the first step whose
    output is not finite is now one line naming the model and the output, and nothing is
    written."""
    from safetensors.torch import load_file, save_file

    from iwsim.core.checkpoint import CheckpointError
    from iwsim.eval.policy import rollout
    from iwsim.world_model import WorldModel
    from tests.test_dynamics import tiny_world_model

    wm = tiny_world_model().save(tmp_path / "wm")
    tensors = load_file(wm / "model.safetensors")
    for name in [k for k in tensors if k.startswith("dynamics.") and k.endswith("weight")]:
        tensors[name] = tensors[name] * 1e30
    save_file(tensors, wm / "model.safetensors")
    model = WorldModel.load(wm)  # finite weights load
    frames = np.zeros((1, 1, 64, 64, 3), np.uint8)
    says = f"world model {wm} gave NaN or infinite values in its dynamics' next latent"
    with pytest.raises(CheckpointError, match=says):
        model.rollout(frames, np.zeros((1, 2, 4), np.float32))
    assert main(["eval", "policy", "--checkpoint", str(ROOT / "checkpoints" / "dp-pusht-64"), "--env",
                 "world-model", "--world-model", str(wm), "--episodes", "1", "--steps", "3", "--videos", "0",
                 "--out", str(tmp_path / "eval"), "--no-progress"]) == 1
    assert "NaN or infinite values in its dynamics' next latent" in error_line(capsys)
    assert not (tmp_path / "eval" / "results.json").exists()

    class Broken:  # a policy whose actions are not numbers
        obs_horizon, name = 1, "policy broken"

        def reset(self) -> None:
            pass

        def predict_action(self, obs: dict) -> np.ndarray:
            return np.full((len(obs["image"]), 1, 4), np.nan, np.float32)

    with pytest.raises(CheckpointError, match="policy broken gave NaN or infinite values in its actions"):
        rollout(Broken(), "pusht", [0], 2, progress=False)


def test_weights_get_the_mode_of_every_other_file(tmp_path, play_store):
    """Issue 65's smaller list: every model.safetensors was written 0600 (safetensors' own
    mode) beside a config.json of 0644: weights others could not read."""
    import stat

    from tests.test_dynamics import tiny_world_model

    def mode(p: Path) -> int:
        return stat.S_IMODE(p.stat().st_mode)

    wm = tiny_world_model().save(tmp_path / "wm")
    assert mode(wm / "model.safetensors") == mode(wm / "config.json")
    run = tmp_path / "dp"
    assert main(["train", "policy", "--policy", "dp", "--preset", "tiny-dp", "--data", f"{play_store}:1", "--steps",
                 "1", "--out", str(run), "--no-progress"]) == 0
    files = [p for p in run.rglob("*") if p.is_file() and p.name != ".iwsim.lock"]
    assert {p.suffix for p in files} >= {".safetensors", ".json"}
    assert {mode(p) for p in files} == {mode(run / "config.json")}, {str(p): oct(mode(p)) for p in files}


def test_collect_runs_a_learned_policy_on_its_own_task(tmp_path, capsys):
    """Issue 65's smaller list: a pile-sweeping policy given to ``collect`` without --task
    was refused in eval's words ("evaluate it on 'pilesweep'"); it now collects on its own
    task, and a --task naming another is refused in collect's words."""
    from iwsim.data.store import EpisodeStore
    from iwsim.envs.registry import task_from_store

    pile = tmp_path / "pile.zarr"
    assert main(["collect", "--task", "pilesweep", "--policy", "play", "--episodes", "1", "--steps", "4",
                 "--workers", "1", "--no-progress", "--out", str(pile)]) == 0
    run = tmp_path / "dp"
    assert main(["train", "policy", "--policy", "dp", "--preset", "tiny-dp", "--data", str(pile), "--steps", "1",
                 "--out", str(run), "--no-progress"]) == 0
    out = tmp_path / "learned.zarr"
    assert main(["collect", "--policy", str(run), "--episodes", "1", "--steps", "3", "--workers", "1",
                 "--no-progress", "--out", str(out)]) == 0
    assert task_from_store(out).name == "pilesweep" and EpisodeStore.open(out).n_episodes == 1
    capsys.readouterr()
    assert main(["collect", "--task", "pusht", "--policy", str(run), "--episodes", "1", "--steps", "3",
                 "--no-progress", "--out", str(tmp_path / "other.zarr")]) == 1
    assert "not --task pusht; collect its episodes with --task pilesweep" in error_line(capsys)


@pytest.mark.parametrize("kind", ["store", "checkpoint"])
def test_reports_are_not_written_into_a_store_or_a_checkpoint(kind, store, tmp_path, capsys):
    """Issue 65's own probe: ``eval policy --out STORE`` wrote results.json, iou.json and
    videos into an episode store (likewise into a checkpoint); a report now needs a
    directory of its own, checked before the work."""
    target = tmp_path / "target"
    shutil.copytree(store if kind == "store" else ROOT / "checkpoints" / "dp-pusht-64", target)
    before = sorted(p.name for p in target.rglob("*"))
    assert main(["eval", "policy", "--checkpoint", str(ROOT / "checkpoints" / "dp-pusht-64"), "--episodes", "1",
                 "--steps", "2", "--out", str(target), "--no-progress"]) == 1
    assert "give the report a directory of its own" in error_line(capsys)
    assert main(["experiment", "policy-eval", "--preset", "tiny", "--out", str(target), "--work",
                 str(tmp_path / "work"), "--no-progress"]) == 1
    assert "give the report a directory of its own" in error_line(capsys)
    assert sorted(p.name for p in target.rglob("*")) == before


def test_lerobot_v3_export_of_short_episodes(store, tmp_path, capsys):
    """Issue 65's own probe: exporting episodes of a few frames to LeRobot v3 said
    "file-000.mp4: No such file or directory" (the encoder had not yet written the file
    whose size the exporter read); now they export and import back."""
    from iwsim.data.store import EpisodeStore

    out = tmp_path / "lerobot"
    assert main(["data", "export", "--format", "lerobot-v3", "--in", str(store), "--out", str(out),
                 "--no-progress"]) == 0
    assert main(["data", "validate", str(out)]) == 0
    back = tmp_path / "back.zarr"
    assert main(["data", "import", "--format", "lerobot-v3", "--in", str(out), "--out", str(back),
                 "--no-progress"]) == 0
    a, b = EpisodeStore.open(store), EpisodeStore.open(back)
    assert a.episode_ends.tolist() == b.episode_ends.tolist()
    np.testing.assert_allclose(a.array("action")[:], b.array("action")[:])


def test_a_world_model_is_not_rolled_out_on_another_tasks_episodes(store, tmp_path, capsys):
    """Issue 65's own probe: ``iwsim rollout`` (and ``iwsim bench``) of the pile-sweeping
    model on T-push episodes ran and scored, the frames of one task fed to a model of another."""
    assert main(["rollout", "--checkpoint", str(ROOT / "checkpoints" / "pilesweep-64"), "--data", str(store),
                 "--episode", "0", "--steps", "2", "--out", str(tmp_path / "r.mp4")]) == 1
    assert "holds episodes of task 'pusht' but the world model is of 'pilesweep'" in error_line(capsys)
    assert not (tmp_path / "r.mp4").exists()
