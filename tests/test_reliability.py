"""Bad flags get one line, not a traceback, and are refused before anything is loaded or
allocated (issue 17): out-of-range episodes, devices this build lacks, negative seeds,
a store named twice, sizes the machine cannot hold; and thread counts are chosen."""

from __future__ import annotations

from pathlib import Path

import pytest

from iwsim.cli import main
from iwsim.resources import choose_threads

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
    from iwsim import cli
    from iwsim.play.engine import PlayConfig

    assert cli.RECORD_STEPS == PlayConfig().max_record_steps
    assert main(["play", "--checkpoint", str(tmp_path / "none"), "--port", "0", "--max-sessions", "1000000"]) == 1
    line = error_line(capsys)
    assert "--max-sessions 1000000 (about" in line and "of memory" in line
    assert main(["play", "--checkpoint", str(tmp_path / "none"), "--port", "0", "--max-sessions", "0"]) == 1
    assert "--max-sessions must be a positive integer" in error_line(capsys)
