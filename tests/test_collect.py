"""``iwsim collect`` and ``iwsim data info``: tiny end-to-end runs and bad input."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from iwsim.cli import main
from iwsim.core.lock import LOCK_NAME, DirLock, is_locked
from iwsim.data.store import EpisodeStore, StoreLockedError
from iwsim.envs.collect import collect, store_attrs
from iwsim.envs.pusht.scripted import record_episode
from iwsim.eval.policy import recorder
from iwsim.policies.factory import load_policy

IWSIM = Path(sys.executable).parent / "iwsim"  # the console script of this environment
TINY = ["--task", "pusht", "--policy", "play", "--steps", "5", "--image-size", "64", "--seed", "3", "--no-progress"]


def collect_args(out: Path, episodes: int, workers: int = 1, *extra: str) -> list[str]:
    return ["collect", *TINY, "--episodes", str(episodes), "--workers", str(workers), "--out", str(out), *extra]


def assert_same_stores(a: Path, b: Path) -> None:
    sa, sb = EpisodeStore.open(a), EpisodeStore.open(b)
    assert sa.attrs == sb.attrs
    np.testing.assert_array_equal(sa.episode_ends, sb.episode_ends)
    for i in range(sa.n_episodes):
        ea, eb = sa.episode(i), sb.episode(i)
        assert ea.keys() == eb.keys()
        for k in ea:
            assert ea[k].dtype == eb[k].dtype
            np.testing.assert_array_equal(ea[k], eb[k], err_msg=f"episode {i} {k}")


def snapshot(path: Path) -> dict[str, tuple[bytes, int]]:
    """Every file under ``path`` with its bytes and mtime, except the writers' lock file
    (each writer notes itself there; it is not data)."""
    return {str(p.relative_to(path)): (p.read_bytes(), p.stat().st_mtime_ns) for p in path.rglob("*")
            if p.is_file() and p.name != LOCK_NAME}


def one_error_line(err: str) -> str:
    lines = err.strip().splitlines()
    assert len(lines) == 1, err
    assert lines[0].startswith("iwsim: error: "), err
    return lines[0]


@pytest.fixture(scope="module")
def two_episodes(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """2 episodes x 5 steps, recorded in this process (1 worker)."""
    out = tmp_path_factory.mktemp("one_worker") / "pusht.zarr"
    assert main(collect_args(out, 2, 1)) == 0
    return out


def test_collect_writes_the_requested_episodes(two_episodes: Path) -> None:
    store = EpisodeStore.open(two_episodes)
    assert (store.n_episodes, store.n_frames) == (2, 10)
    assert store.seeds == [3, 4]
    attrs = store.attrs
    assert (attrs["task"], attrs["policy"], attrs["image_size"], attrs["steps"], attrs["fps"]) == (
        "pusht",
        "play",
        64,
        5,
        10,
    )
    assert len(attrs["action_low"]) == len(attrs["action_names"]) == 4 and "iwsim_version" in attrs
    ep = store.episode(1)
    assert ep["img"].shape == (5, 64, 64, 3) and ep["img"].dtype == np.uint8
    assert ep["action"].shape == ep["state"].shape == (5, 4) and ep["block_pose"].shape == (5, 3)


@pytest.mark.slow
def test_console_script_with_two_workers_gives_identical_data(two_episodes: Path, tmp_path: Path) -> None:
    out = tmp_path / "pusht.zarr"
    env = {**os.environ, "MUJOCO_GL": os.environ.get("MUJOCO_GL", "egl")}
    proc = subprocess.run([str(IWSIM), *collect_args(out, 2, 2)], capture_output=True, text=True, env=env)
    assert proc.returncode == 0, proc.stderr
    assert "frames/s" in proc.stderr
    assert_same_stores(out, two_episodes)


def test_rerun_with_more_episodes_appends_only_the_missing(two_episodes: Path, tmp_path: Path) -> None:
    out = tmp_path / "pusht.zarr"
    assert main(collect_args(out, 1)) == 0
    assert EpisodeStore.open(out).n_episodes == 1
    assert main(collect_args(out, 2)) == 0
    assert_same_stores(out, two_episodes)
    before = snapshot(out)
    assert main(collect_args(out, 2)) == 0  # nothing missing: nothing written
    assert snapshot(out) == before


def test_data_info(two_episodes: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["data", "info", str(two_episodes)]) == 0
    out = capsys.readouterr().out
    expected_rows = (
        "episodes      2",
        "frames        10",
        "fps           10",
        "image size    64",
        "pusht (policy play)",
    )
    for expected in expected_rows:
        assert expected in out, out
    assert "(10, 64, 64, 3)" in out and "uint8" in out and "(10, 4)" in out and "float32" in out
    assert "size on disk" in out and "KiB" in out


@pytest.mark.parametrize(
    ("flags", "message"),
    [
        (["--task", "pushq"], "unknown task 'pushq'"),
        (["--policy", "random"], "unknown policy 'random'"),
        (["--image-size", "50"], "image size must be one of [64, 96, 128], got 50"),
        (["--episodes", "0"], "episodes must be a positive integer"),
        (["--steps", "-1"], "steps must be a positive integer"),
        (["--workers", "0"], "workers must be a positive integer"),
    ],
)
def test_bad_flags_fail_with_one_line(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], flags: list[str], message: str
) -> None:
    out = tmp_path / "data" / "x.zarr"
    assert main(collect_args(out, 2, 1, *flags)) == 1
    assert message in one_error_line(capsys.readouterr().err)
    assert not (tmp_path / "data").exists()


def _existing_store(path: Path, **changes: object) -> Path:
    """A store as `iwsim collect` would make it (seed 3), with ``changes`` to its attrs."""
    attrs = {**store_attrs("pusht", "play", 5, 64), **changes}
    store = EpisodeStore.create(path, attrs)
    rng = np.random.default_rng(0)
    size = attrs["image_size"]
    store.append(
        {
            "img": rng.integers(0, 256, (5, size, size, 3), dtype=np.uint8),
            "state": np.zeros((5, 4), np.float32),
            "action": np.zeros((5, 4), np.float32),
            "block_pose": np.zeros((5, 3), np.float32),
            "iou": np.zeros(5, np.float32),
            "n_contacts": np.zeros(5, np.int32),
        },
        seed=3,
    )
    store.close()
    return path


@pytest.mark.parametrize(
    ("changes", "extra", "message"),
    [
        ({"image_size": 96}, [], "image_size=96, not image_size=64"),
        ({"task": "other"}, [], "task='other', not task='pusht'"),
        ({"policy": "expert"}, [], "policy='expert', not policy='play'"),
        ({"steps": 200}, [], "steps=200, not steps=5"),
        ({}, ["--seed", "7"], "seed 3, which --seed 7 would not give"),
    ],
)
def test_incompatible_existing_store_is_refused_untouched(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], changes: dict, extra: list[str], message: str
) -> None:
    out = _existing_store(tmp_path / "old.zarr", **changes)
    before = snapshot(out)
    assert main(collect_args(out, 3, 1, *extra)) == 1
    line = one_error_line(capsys.readouterr().err)
    assert message in line and str(out) in line
    assert snapshot(out) == before


@pytest.mark.parametrize("kind", ["under a regular file", "a regular file", "a directory that is not a store"])
def test_unusable_out_path_is_refused(tmp_path: Path, capsys: pytest.CaptureFixture[str], kind: str) -> None:
    blocker = tmp_path / "blocker"
    if kind == "under a regular file":
        blocker.write_text("x")
        out = blocker / "sub" / "x.zarr"
    elif kind == "a regular file":
        blocker.write_text("x")
        out = blocker
    else:
        blocker.mkdir()
        (blocker / "notes.txt").write_text("x")
        out = blocker
    before = snapshot(tmp_path)
    assert main(collect_args(out, 1, 1)) == 1
    line = one_error_line(capsys.readouterr().err)
    assert str(blocker) in line
    assert snapshot(tmp_path) == before


@pytest.mark.parametrize("kind", ["missing", "file"])
def test_data_info_on_a_non_store(tmp_path: Path, capsys: pytest.CaptureFixture[str], kind: str) -> None:
    path = tmp_path / "thing"
    if kind == "file":
        path.write_text("x")
    assert main(["data", "info", str(path)]) == 1
    captured = capsys.readouterr()
    assert str(path) in one_error_line(captured.err) and captured.out == ""


def test_argparse_errors_exit_2(capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as e:
        main(["collect", "--episodes", "two"])
    assert e.value.code == 2


@pytest.mark.slow
def test_two_collect_processes_on_one_store_take_turns(tmp_path: Path) -> None:
    """Two real `iwsim collect` processes appending to one store: while the first holds the
    store, a second is refused with one line naming it, or waits with --wait-for-lock and
    then finds nothing missing; the store equals a single writer's."""
    out, alone = tmp_path / "shared.zarr", tmp_path / "alone.zarr"
    env = {**os.environ, "MUJOCO_GL": os.environ.get("MUJOCO_GL", "egl")}
    assert main(collect_args(out, 1)) == 0
    assert main(collect_args(alone, 4)) == 0
    first = subprocess.Popen([str(IWSIM), *collect_args(out, 4)], stderr=subprocess.PIPE, text=True, env=env)
    try:
        deadline = time.monotonic() + 60
        # the first writer holds the store and has written its name (a moment after the lock) ...
        while not (is_locked(out) and f"pid {first.pid} " in (out / LOCK_NAME).read_text()):
            assert first.poll() is None and time.monotonic() < deadline, "the first writer never took the lock"
            time.sleep(0.01)
        os.kill(first.pid, signal.SIGSTOP)  # ... and keeps it while the second one tries
        refused = subprocess.run([str(IWSIM), *collect_args(out, 4)], capture_output=True, text=True, env=env)
        waiting = subprocess.Popen([str(IWSIM), *collect_args(out, 4, 1, "--wait-for-lock")],
                                   stderr=subprocess.PIPE, text=True, env=env)
        time.sleep(1.0)
        assert waiting.poll() is None  # still waiting
    finally:
        os.kill(first.pid, signal.SIGCONT)
    assert first.wait(60) == 0, first.stderr.read()
    assert waiting.wait(60) == 0
    assert refused.returncode == 1
    line = one_error_line(refused.stderr)
    assert f"{out} is being written by pid {first.pid} (iwsim collect)" in line and "--wait-for-lock" in line
    assert "nothing to do" in waiting.stderr.read()
    first.stderr.close()
    waiting.stderr.close()
    assert_same_stores(out, alone)


def test_a_released_lock_names_nobody(tmp_path: Path) -> None:
    """CI stop 90: a writer that had just taken a store's lock, and not yet written its name,
    was reported as the store's last holder, a process long gone."""
    with DirLock(tmp_path) as lock:
        assert f"pid {os.getpid()} " in lock.holder()
        with pytest.raises(OSError, match=f"pid {os.getpid()} "):
            DirLock(tmp_path)  # refused: a second open lock, even in this process; it names us
        assert f"pid {os.getpid()} " in lock.holder()  # and the refusal did not clear our name
    assert not is_locked(tmp_path) and (tmp_path / LOCK_NAME).read_text() == ""


@pytest.mark.parametrize("writes_its_name", [True, False])
def test_a_refusal_never_names_a_killed_writer(tmp_path: Path, writes_its_name: bool) -> None:
    """A killed writer leaves its name in the lock file; a new holder overwrites it a moment
    after taking the lock. A writer refused in that moment names the new holder once it has
    written its name, or nobody, never the dead process."""
    gone = subprocess.Popen([sys.executable, "-c", "pass"])
    gone.wait()
    (tmp_path / LOCK_NAME).write_text(f"pid {gone.pid} (iwsim collect), writing since 2026-01-01 00:00:00\n")
    write = "os.pwrite(fd, f'pid {os.getpid()} (new), writing\\n'.encode(), 0); " if writes_its_name else ""
    holder = subprocess.Popen([sys.executable, "-c", "import fcntl, os, sys, time; "
                               "fd = os.open(sys.argv[1], os.O_RDWR); fcntl.flock(fd, fcntl.LOCK_EX); "
                               f"print('locked', flush=True); time.sleep(0.3); {write}time.sleep(60)",
                               str(tmp_path / LOCK_NAME)], stdout=subprocess.PIPE, text=True)
    try:
        assert holder.stdout.readline() == "locked\n"
        with pytest.raises(OSError) as refused:
            DirLock(tmp_path)
    finally:
        holder.kill()
        holder.wait()
        holder.stdout.close()
    assert f"pid {gone.pid} " not in str(refused.value)
    assert (f"pid {holder.pid} (new)" if writes_its_name else "being written by another process") in str(refused.value)


def test_a_killed_writers_lock_is_free(tmp_path: Path) -> None:
    out = tmp_path / "s.zarr"
    assert main(collect_args(out, 1)) == 0
    holder = subprocess.Popen([sys.executable, "-c", "import sys, time; from iwsim.data.store import EpisodeStore; "
                               "s = EpisodeStore.open(sys.argv[1], 'a'); print('locked', flush=True); time.sleep(60)",
                               str(out)], stdout=subprocess.PIPE, text=True)
    assert holder.stdout.readline() == "locked\n"
    with pytest.raises(StoreLockedError, match=f"pid {holder.pid}"):
        EpisodeStore.open(out, "a")
    holder.kill()
    holder.wait()
    holder.stdout.close()
    assert main(collect_args(out, 2)) == 0  # the lock died with its holder
    assert EpisodeStore.open(out).n_episodes == 2


@pytest.mark.parametrize("what", ["empty directory", "user directory"])
def test_collect_into_a_directory_that_is_not_a_store_leaves_nothing_in_it(tmp_path: Path, capsys, what) -> None:
    """Issue 26: refusing a non-store --out left an .iwsim.lock file behind."""
    out = tmp_path / "dir"
    out.mkdir()
    if what == "user directory":
        (out / "notes.txt").write_text("mine")
    before = sorted(p.name for p in out.iterdir())
    assert main(["collect", "--task", "pusht", "--policy", "play", "--episodes", "1", "--steps", "3",
                 "--workers", "1", "--no-progress", "--out", str(out)]) == 1
    assert "not" in capsys.readouterr().err
    assert sorted(p.name for p in out.iterdir()) == before


def test_a_learned_policys_episodes_are_collected_like_scripted_ones(play_store: Path, tmp_path: Path,
                                                                     capsys: pytest.CaptureFixture[str]) -> None:
    """``iwsim collect --policy RUN``: a trained policy's MuJoCo episodes in the store's
    layout (step t: the frame before action t); the same command records the same store,
    one extended in whole batches holds the same episodes; only the same policy appends."""
    pol = tmp_path / "pol"
    assert main(["train", "policy", "--policy", "dp", "--preset", "tiny-dp", "--data", f"{play_store}:2",
                 "--steps", "2", "--out", str(pol), "--no-progress"]) == 0
    args = ["collect", "--policy", str(pol), "--steps", "5", "--seed", "50", "--no-progress"]
    whole = tmp_path / "whole.zarr"
    assert main([*args, "--episodes", "3", "--out", str(whole)]) == 0
    store = EpisodeStore.open(whole, "r")
    assert store.n_episodes == 3 and store.seeds == [50, 51, 52] and store.attrs["policy"] == f"learned:{pol}"
    ep = store.episode(1)
    assert ep["img"].shape == (5, 64, 64, 3) and ep["block_pose"].shape == (5, 3) and ep["n_contacts"].shape == (5,)
    first = record_episode("pusht", "play", 51, 1)  # the same MuJoCo reset: the same first frame and state
    np.testing.assert_array_equal(ep["img"][0], first["img"][0])
    np.testing.assert_array_equal(ep["state"][0], first["state"][0])
    assert np.abs(ep["target"] - ep["state"]).max() < 0.5 and np.isfinite(ep["action"]).all()
    again = tmp_path / "again.zarr"  # the same command, the same store (each batch's noise seeded)
    assert main([*args, "--episodes", "3", "--out", str(again)]) == 0
    for i in range(3):
        for k in ("img", "action", "target"):
            np.testing.assert_array_equal(EpisodeStore.open(again, "r").episode(i)[k], store.episode(i)[k])
    # extended in whole batches, a store holds what one recorded at once holds
    net, rec = load_policy(pol), {}
    for name, counts in (("once", (3,)), ("extended", (2, 3))):
        for n in counts:
            collect("pusht", "learned", n, out=tmp_path / f"{name}.zarr", steps=4, seed=50, progress=False,
                    recorder=recorder(net, "pusht", 4, batch=2))
        rec[name] = EpisodeStore.open(tmp_path / f"{name}.zarr", "r")
    for i in range(3):
        np.testing.assert_array_equal(rec["once"].episode(i)["action"], rec["extended"].episode(i)["action"])
    capsys.readouterr()
    assert main(["collect", "--policy", "play", "--steps", "5", "--seed", "50", "--episodes", "4", "--out", str(whole),
                 "--no-progress"]) == 1
    assert "policy" in capsys.readouterr().err and EpisodeStore.open(whole, "r").n_episodes == 3
    assert main([*args, "--episodes", "3"]) == 1
    assert "needs --out" in capsys.readouterr().err
