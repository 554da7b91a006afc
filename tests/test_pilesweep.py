"""Pile sweeping (issue 45): the task's physics, its pixel scorer on rendered frames, its
scripted policies, its Task behind the seam and ``iwsim collect --task pilesweep``. The
expert's score, the scorer's error over held-out episodes and collection throughput are
measured in ``bench/bench_pilesweep.py``."""

from __future__ import annotations

from pathlib import Path

import gymnasium as gym
import numpy as np
import pytest

from iwsim.cli import main
from iwsim.core.errors import InputError
from iwsim.data.store import EpisodeStore
from iwsim.envs import make_env
from iwsim.envs.pilesweep.pixels import count_pieces, pieces_kept, tray_share
from iwsim.envs.pilesweep.scripted import SweepExpert, degraded_expert, make_policy, record_episode, run_scripted
from iwsim.envs.pilesweep.sim import MAX_PIECES, PIECE_RADIUS, STATE_SIZE, TRAY, PileSweepEnv, in_tray
from iwsim.envs.pilesweep.task import PileSweepTask
from iwsim.envs.registry import get_task, task_from_store
from iwsim.envs.tabletop.scene import WALL_INNER


@pytest.fixture(scope="module")
def env():
    e = PileSweepEnv(64)
    yield e
    e.close()


def state(pushers: list[float], pieces: list[tuple[float, float]]) -> np.ndarray:
    s = np.full(STATE_SIZE, np.nan)
    s[:4] = pushers
    s[4: 4 + 2 * len(pieces)] = np.ravel(pieces)
    return s


# -- physics --------------------------------------------------------------------------------------


def test_registered_and_checked():
    e = gym.make("iwsim/PileSweep-v0")
    assert e.spec.max_episode_steps == 200
    from gymnasium.utils.env_checker import check_env

    check_env(e.unwrapped, skip_render_check=True)
    e.close()


def test_same_seed_same_frame_and_state(env):
    a, info_a = env.reset(seed=7)
    state_a = env.get_state()
    b, info_b = make_env("pilesweep").reset(seed=7)
    assert np.array_equal(a["pixels"], b["pixels"]) and np.array_equal(a["agent_pos"], b["agent_pos"])
    assert 15 <= info_a["n_pieces"] <= 30 and info_a["n_in_tray"] == 0
    again, _ = env.reset(options={"reset_to_state": state_a})
    np.testing.assert_array_equal(again["pixels"], a["pixels"])
    np.testing.assert_array_equal(env.get_state(), state_a)
    c, _ = env.reset(seed=8)
    assert not np.array_equal(a["pixels"], c["pixels"])


def test_the_tray_count_is_exact(env):
    x0, x1, y0, _ = TRAY
    inside = [(0.0, 0.2), (x0 + 0.01, y0 + 0.01), (x1 - 0.01, 0.15)]
    outside = [(0.0, y0 - 0.01), (x1 + 0.01, 0.2), (-0.1, -0.1), (0.15, -0.2)]
    _, info = env.reset(options={"reset_to_state": state([-0.2, -0.2, 0.2, -0.2], inside + outside)})
    assert (info["n_in_tray"], info["n_pieces"]) == (3, 7) and info["score"] == pytest.approx(3 / 7)
    assert not info["is_success"]
    np.testing.assert_allclose(info["pieces"], inside + outside, atol=1e-6)
    assert in_tray(np.array(inside)).all() and not in_tray(np.array(outside)).any()


def test_pieces_stay_on_the_table_when_pushed_hard(env):
    """Both pushers driven through the pile into a corner and along the walls at full speed."""
    _, info = env.reset(seed=3)
    z = np.array([env.model.joint(f"piece_{i}_z").qposadr[0] for i in range(info["n_pieces"])])
    start = env.pieces.copy()
    corners = [[-1, -1, -1, -0.8], [1, -1, 0.8, -1], [1, 1, 1, 0.8], [-0.8, 1, -1, 1]]
    for target in ([start.mean(0)[0], -0.3, start.mean(0)[0], -0.3], *corners):
        for _ in range(12):
            _, _, _, _, info = env.step(np.array(target, np.float64) * 0.3)
            p = env.pieces
            assert np.abs(p).max() < WALL_INNER - PIECE_RADIUS + 0.004  # not through a wall
            assert np.abs(env.data.qpos[z]).max() < 0.002  # on the table plane
    assert info["n_contacts"] >= 0 and np.abs(env.pieces - start).max() > 0.02  # the pieces moved


def test_bad_states_and_actions_are_one_line(env):
    with pytest.raises(InputError, match="reset_to_state"):
        env.reset(options={"reset_to_state": np.zeros(7)})
    with pytest.raises(InputError, match="at least one piece"):
        env.reset(options={"reset_to_state": state([0, 0, 0.1, 0], [])})
    env.reset(seed=0)
    with pytest.raises(InputError, match="actions of shape"):
        env.step(np.zeros(3))


# -- the pixel scorer ---------------------------------------------------------------------------


def test_the_scorer_counts_rendered_pieces(env):
    """Scattered pieces, a pile at a reset, and pieces a sweep packed into the tray."""
    rng = np.random.default_rng(0)
    scattered = [tuple(p) for p in rng.uniform([-0.2, -0.2], [0.2, 0.0], (12, 2))]
    obs, info = env.reset(options={"reset_to_state": state([-0.2, -0.21, 0.2, -0.21], scattered)})
    frames, truth = [obs["pixels"]], [(info["n_in_tray"], info["n_pieces"])]
    for seed in (1, 2):
        obs, info = env.reset(seed=seed)
        frames.append(obs["pixels"])
        truth.append((info["n_in_tray"], info["n_pieces"]))
    inside, seen = count_pieces(np.stack(frames))
    assert inside.shape == seen.shape == (3,)
    np.testing.assert_array_equal(np.stack([inside, seen], axis=1), truth)
    np.testing.assert_allclose(tray_share(np.stack(frames)), [t / n for t, n in truth])
    ep = record_episode("expert", 100002, 60)  # a packed tray, as sweeping makes it
    inside, seen = count_pieces(ep["img"][::10])
    assert ep["n_in_tray"][-1] >= 5
    assert np.abs(inside - ep["n_in_tray"][::10]).max() <= 1 and np.abs(seen - ep["n_pieces"][::10]).max() <= 1


def test_pieces_kept_counts_what_a_frame_lost(env):
    pieces = [(-0.15 + 0.04 * (k % 5), -0.15 + 0.05 * (k // 5)) for k in range(10)]
    obs, _ = env.reset(options={"reset_to_state": state([-0.2, 0.2, 0.2, 0.2], pieces)})
    frame = obs["pixels"]
    table = frame[32, 2].copy()
    lost = frame.copy()
    for x, y in pieces[:3]:  # paint three pieces over with the table
        col, row = int((x + 0.26) / 0.52 * 64), int((0.26 - y) / 0.52 * 64)
        lost[row - 2: row + 3, col - 2: col + 3] = table
    np.testing.assert_allclose(pieces_kept(np.stack([frame, frame, lost])), [1.0, 1.0, 0.7])
    blank = np.broadcast_to(table, frame.shape)
    assert count_pieces(blank) == (0, 0) and tray_share(blank) == 0.0
    with pytest.raises(InputError, match="RGB"):
        count_pieces(np.zeros((64, 64), np.uint8))


# -- scripted policies ----------------------------------------------------------------------------


def test_the_expert_reads_pixels_only_and_sweeps_pieces_in():
    """The expert never reads info (it gets an empty one) and fills the tray in a short episode."""

    class Blind(SweepExpert):
        def __call__(self, obs, info):
            return super().__call__(obs, {})

    first = last = None
    for tr in run_scripted(Blind(), 100001, 60):
        first = tr.info if first is None else first
        last = tr.next_info
    assert first["n_in_tray"] == 0 and last["n_in_tray"] >= 3


def test_policies_are_seeded_and_touch_the_pieces():
    a = record_episode("play", 3, 30)
    b = record_episode("play", 3, 30)
    assert all(np.array_equal(a[k], b[k], equal_nan=True) for k in a)
    assert a["img"].shape == (30, 64, 64, 3) and a["pieces"].shape == (30, MAX_PIECES, 2)
    assert a["action"].shape == a["target"].shape == a["state"].shape == (30, 4)
    assert (a["n_contacts"] > 0).any() and not np.array_equal(a["action"], record_episode("play", 4, 30)["action"])
    noisy = [record_episode("expert-noisy", s, 8)["action"] for s in (5, 5, 6)]
    assert np.array_equal(noisy[0], noisy[1]) and not np.array_equal(noisy[0], noisy[2])
    with pytest.raises(InputError, match="unknown policy"):
        make_policy("dance", 0)


def test_degraded_experts_lag_and_add_noise():
    env = PileSweepEnv(64)
    obs, info = env.reset(seed=5)
    clean = SweepExpert()
    clean.reset(obs, info)
    late = degraded_expert(0, latency=2)
    late.reset(obs, info)
    held = [late(obs, info) for _ in range(3)]
    np.testing.assert_array_equal(held[0], obs["agent_pos"])
    np.testing.assert_array_equal(held[1], obs["agent_pos"])
    np.testing.assert_array_equal(held[2], clean(obs, info))
    noisy = degraded_expert(1, noise=0.01)
    noisy.reset(obs, info)
    fresh = SweepExpert()
    fresh.reset(obs, info)
    assert 0.002 < np.abs(noisy(obs, info) - fresh(obs, info)).mean() < 0.03
    env.close()


# -- the Task and collection ------------------------------------------------------------------


def test_the_task_behind_the_seam(env):
    task = get_task("pilesweep")
    assert isinstance(task, PileSweepTask) and task.action_dim == 4 and task.start_source == "mujoco"
    assert task.bindings == get_task("pusht").bindings and task.score_name and task.horizon == 200
    assert set(task.scripted_policies) >= {"play", "expert", "expert-noisy", "expert-lagged"}
    starts = task.initial_frames(64)
    start = starts.draw(21)
    again = starts.draw(0, state=start.state)
    starts.close()
    np.testing.assert_array_equal(again.frame, start.frame)
    scores, pos = task.observe(start.frame[None], start.command[None], np.zeros((1, 4), np.float32))
    assert scores.shape == (1,) and scores[0] == 0.0
    np.testing.assert_allclose(pos[0], start.agent_pos, atol=1e-6)
    np.testing.assert_allclose(task.read_agent_pos(start.frame[None], np.zeros((1, 4)))[0], start.agent_pos,
                               atol=0.004)


def test_iwsim_collect_records_a_pilesweep_store(tmp_path: Path, capsys: pytest.CaptureFixture[str]):
    out = tmp_path / "pile.zarr"
    args = ["collect", "--task", "pilesweep", "--policy", "play", "--episodes", "2", "--steps", "5",
            "--seed", "3", "--workers", "1", "--no-progress", "--out", str(out)]
    assert main(args) == 0
    store = EpisodeStore.open(out)
    assert (store.n_episodes, store.n_frames, store.seeds) == (2, 10, [3, 4])
    attrs = store.attrs
    assert (attrs["task"], attrs["policy"], attrs["image_size"], attrs["fps"]) == ("pilesweep", "play", 64, 10)
    assert attrs["tray"] == list(TRAY) and len(attrs["action_names"]) == 4
    ep = store.episode(1)
    np.testing.assert_array_equal(ep["img"], record_episode("play", 4, 5)["img"])
    assert ep["pieces"].shape == (5, MAX_PIECES, 2) and ep["score"].shape == (5,)
    assert isinstance(task_from_store(out), PileSweepTask)
    start = get_task("pilesweep").start_from_record(ep["img"][0], {"state": ep["state"][0], "pieces": ep["pieces"][0]})
    assert start.state is not None and start.state.shape == (STATE_SIZE,)
    assert main(["collect", *args[1:4], "expert-lagged", *args[5:]]) == 1  # another policy into the same store
    assert "policy" in capsys.readouterr().err
    assert main(["collect", "--task", "pilesweep", "--policy", "play-broad", "--episodes", "1",
                 "--out", str(tmp_path / "x.zarr")]) == 1
    assert "unknown policy 'play-broad' for task 'pilesweep'" in capsys.readouterr().err


def test_the_simulator_behind_the_seam_runs_batched_with_its_pixel_policies():
    """Issue 45: evaluation steps the task's simulator in a vector env (the piles differ in
    size, so the pieces come padded, as a store holds them), driven by its scripted policies
    that read only the frame (the expert acts on the pieces it sees)."""
    from iwsim.eval.policy import rollout
    from iwsim.policies.scripted import ScriptedBatch

    task = get_task("pilesweep")
    env = task.ground_truth_env(64)
    _, info = env.reset(seed=7)
    env.close()
    assert info["pieces"].shape == (MAX_PIECES, 2) and np.isnan(info["pieces"][info["n_pieces"]:]).all()
    with pytest.raises(InputError, match="start must be one of random for task 'pilesweep', got 'goal-turned'"):
        task.ground_truth_env(64, start="goal-turned")
    assert isinstance(task.pixel_policy("expert", 0, np.random.default_rng(0)), SweepExpert)
    with pytest.raises(InputError, match="unknown policy 'expert-wide'"):
        task.pixel_policy("expert-wide", 0, np.random.default_rng(0))
    run = rollout(ScriptedBatch("expert", task), "pilesweep", [3, 4], 20, record=1, progress=False,
                  keep=("pieces", "n_pieces"))
    assert run["task"] == "pilesweep" and run["score_key"] == "score" and run["scorer"] == task.score_name
    assert run["iou"].shape == (2, 21) and run["info"]["pieces"].shape == (2, 21, MAX_PIECES, 2)
    # the expert's commands are those it gives the same frames alone (pixels and agent_pos only)
    alone = SweepExpert()
    first = {"pixels": run["frames"][0, 0], "agent_pos": run["agent_pos"][0, 0]}
    alone.reset(first, {})
    np.testing.assert_array_equal(alone(first, {}), run["action"][0, 0])
    with pytest.raises(InputError, match="start must be one of random"):
        rollout(ScriptedBatch("expert", task), "pilesweep", [3], 2, start="goal-turned", progress=False)
