import gymnasium as gym
import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env

import iwsim  # noqa: F401  (registers the ids)
from iwsim.envs.pusht import geometry as geo
from iwsim.envs.pusht import pixels
from iwsim.envs.pusht.sim import GOAL_POSE, MAX_STEP, PUSHER_RADIUS, WORKSPACE, BimanualPushTEnv, limit_targets


@pytest.fixture(scope="module")
def env():
    e = BimanualPushTEnv(64)
    yield e
    e.close()


def test_check_env():
    e = gym.make("iwsim/BimanualPushT-v0")
    check_env(e.unwrapped, skip_render_check=False)
    e.close()


def test_spaces_and_info(env):
    obs, info = env.reset(seed=1)
    assert obs["pixels"].shape == (64, 64, 3) and obs["pixels"].dtype == np.uint8
    assert obs["agent_pos"].shape == (4,) and obs["agent_pos"].dtype == np.float32
    assert env.action_space.shape == (4,)
    assert set(info) >= {"iou", "block_pose", "goal_pose", "is_success"}
    np.testing.assert_allclose(info["goal_pose"], GOAL_POSE)
    assert info["is_success"] == (info["iou"] >= 0.9)


@pytest.mark.parametrize("size", [96, 128])
def test_other_image_sizes(size):
    e = BimanualPushTEnv(size)
    obs, _ = e.reset(seed=0)
    assert obs["pixels"].shape == (size, size, 3)
    e.close()


def test_bad_image_size():
    with pytest.raises(ValueError, match="image_size"):
        BimanualPushTEnv(50)


def test_same_seed_same_first_frame_bit_for_bit():
    a, b = BimanualPushTEnv(64), BimanualPushTEnv(64)
    fa, _ = a.reset(seed=123)
    a.step(a.action_space.sample())
    fa2, _ = a.reset(seed=123)
    fb, _ = b.reset(seed=123)
    fc, _ = b.reset(seed=124)
    assert np.array_equal(fa["pixels"], fb["pixels"]) and np.array_equal(fa["pixels"], fa2["pixels"])
    assert not np.array_equal(fa["pixels"], fc["pixels"])
    a.close(), b.close()


def test_same_actions_same_trajectory(env):
    actions = np.random.default_rng(0).uniform(-0.2, 0.2, (10, 4)).astype(np.float32)
    runs = []
    for _ in range(2):
        env.reset(seed=5)
        runs.append([env.step(a)[0]["pixels"] for a in actions])
    assert all(np.array_equal(x, y) for x, y in zip(*runs))


def test_reset_to_state(env):
    state = np.array([-0.15, 0.1, 0.15, 0.1, 0.02, -0.03, 0.5])
    obs, info = env.reset(options={"reset_to_state": state})
    np.testing.assert_allclose(env.get_state(), state, atol=1e-9)
    np.testing.assert_allclose(obs["agent_pos"], state[:4], atol=1e-6)
    np.testing.assert_allclose(info["block_pose"], state[4:], atol=1e-9)
    with pytest.raises(ValueError, match="reset_to_state"):
        env.reset(options={"reset_to_state": [0.0, 1.0]})


def test_goal_turned_starts_put_the_block_on_the_goal_turned_away_from_it():
    """Issue 25's recovery demonstrations start where policies that do not turn end up."""
    e = BimanualPushTEnv(64, start="goal-turned")
    for seed in range(20):
        _, info = e.reset(seed=seed)
        pose = info["block_pose"]
        assert np.abs(pose[:2] - GOAL_POSE[:2]).max() <= 0.015 + 1e-6  # settled where it was put
        assert np.pi / 4 - 1e-3 <= abs(geo.wrap_angle(pose[2] - GOAL_POSE[2])) <= 3 * np.pi / 4 + 1e-3
        assert info["iou"] < 0.9 and info["n_contacts"] == 0
        assert all(geo.distance_to_t(p, pose) > PUSHER_RADIUS for p in e.agent_pos.reshape(2, 2))
    e.close()
    with pytest.raises(ValueError, match="start must be one of random, goal-turned"):
        BimanualPushTEnv(64, start="goal")


def test_actions_are_clipped_to_the_workspace(env):
    env.reset(options={"reset_to_state": np.array([-0.15, -0.15, 0.15, -0.15, 0.0, 0.1, 0.0])})
    for _ in range(40):  # the speed limit: 0.016 m per step
        obs, *_ = env.step(np.array([5.0, -5.0, 5.0, 5.0], np.float32))
    assert np.all(np.abs(obs["agent_pos"]) <= WORKSPACE + 1e-3)
    np.testing.assert_allclose(obs["agent_pos"], [WORKSPACE, -WORKSPACE, WORKSPACE, WORKSPACE], atol=2e-3)
    # An out-of-bounds action does exactly what its clipped version does.
    outs = []
    for a in ([9.0, 0.0, -9.0, 0.1], [WORKSPACE, 0.0, -WORKSPACE, 0.1]):
        env.reset(seed=3)
        outs.append(env.step(np.array(a, np.float32))[0]["pixels"])
    assert np.array_equal(*outs)


@pytest.mark.parametrize("bad", [[0.0, 0.0, 0.0], [0.0, np.nan, 0.0, 0.0], [np.inf, 0, 0, 0]])
def test_bad_actions(env, bad):
    env.reset(seed=0)
    with pytest.raises(ValueError, match="action"):
        env.step(np.array(bad, np.float32))


def test_rendering_matches_the_geometry(env):
    """The camera maps the world exactly as the pixel scorer assumes."""
    pose = np.array([0.05, -0.04, 1.1])
    obs, _ = env.reset(options={"reset_to_state": np.array([-0.2, -0.2, 0.2, -0.2, *pose])})
    seen = pixels.block_fraction(obs["pixels"])
    truth = pixels.coverage_mask(tuple(pose), 64)
    assert np.abs(seen - truth).sum() < 0.05 * truth.sum()
    # The goal T is drawn where GOAL_POSE says (the block is elsewhere here).
    goal_rgb = np.round(np.array([0.62, 0.86, 0.62]) * 255)
    goal_seen = np.all(np.abs(obs["pixels"].astype(float) - goal_rgb) < 2, axis=-1)
    goal_truth = pixels.goal_mask(64) > 0.5
    free = pixels.coverage_mask(tuple(pose), 64) == 0
    assert (goal_seen[free] == goal_truth[free]).mean() > 0.97


def test_pushers_move_the_block(env):
    # Left pusher below the stem's tip, pushing up through the block.
    state = np.array([0.0, -0.17, 0.2, 0.2, 0.0, 0.0, 0.0])
    env.reset(options={"reset_to_state": state})
    contacts = 0
    for _ in range(25):  # 0.22 m at the speed limit of 0.016 m per step, then settling
        obs, r, term, trunc, info = env.step(np.array([0.0, 0.05, 0.2, 0.2], np.float32))
        contacts += info["n_contacts"] > 0
    # Pushed (at least) until the pusher stops at y = 0.05, touching the stem's tip.
    tip = 0.05 + 0.015 + 0.12 - 0.0143
    assert info["block_pose"][1] >= tip - 0.005 and contacts >= 1


def test_far_targets_are_approached_at_the_speed_limit(env):
    """A far command moves each pusher's setpoint by exactly MAX_STEP per step towards the
    workspace-clipped target, and the executed setpoints are limit_targets' (the one
    function the world model's callers use too)."""
    start = np.array([-0.15, -0.15, 0.15, -0.15, 0.0, 0.1, 0.0])
    env.reset(options={"reset_to_state": start})
    command = np.array([5.0, -0.15, 0.15, 0.2], np.float32)  # left far right (clipped), right up
    setpoint = start[:4].copy()
    for t in range(30):
        _, _, _, _, info = env.step(command)
        expected = limit_targets(setpoint, command)
        np.testing.assert_allclose(info["target"], expected, atol=1e-6)
        moved = np.linalg.norm((expected - setpoint).reshape(2, 2), axis=1)
        if t < 5:
            np.testing.assert_allclose(moved, MAX_STEP, rtol=1e-9)
        setpoint = expected
    np.testing.assert_allclose(setpoint, [WORKSPACE, -0.15, 0.15, 0.2], atol=1e-9)
    assert np.abs(info["target"] - env.unwrapped.agent_pos).max() < 0.01  # the pushers followed


def test_limit_targets_passes_near_targets_unchanged():
    s = np.array([0.0, 0.0, 0.1, 0.1])
    near = s + np.array([0.01, -0.01, 0.0, 0.015])
    np.testing.assert_allclose(limit_targets(s, near), near)
    batch = limit_targets(np.stack([s, s]), np.stack([near, s + 1.0]))
    assert batch.shape == (2, 4) and np.allclose(batch[0], near)
