"""The Task seam: T-push behind it as before, and a second task (a 2-D point robot the
tests render themselves, ``conftest.point_model``) end to end: import -> tiny training ->
``iwsim/WorldModel-v0`` -> play sessions and a recording -> LeRobot export -> ``iwsim eval
policy`` in the model, with "no scorer" where the task has none. The same model driven in
Chromium: ``test_play_browser.py``."""

import json
from pathlib import Path

import gymnasium as gym
import numpy as np
import pytest

from iwsim.cli import main
from iwsim.core.errors import InputError
from iwsim.data.store import EpisodeStore
from iwsim.envs.pusht.sim import limit_targets
from iwsim.envs.pusht.task import PushTTask
from iwsim.envs.registry import DatasetTask, get_task, task_from_config, task_from_dict, task_from_store, task_of
from iwsim.envs.task import Bindings, Task
from iwsim.play import protocol as proto
from iwsim.play.engine import Engine, PlayConfig
from iwsim.world_model import WorldModel
from iwsim.world_model.env import WorldModelEnv, WorldModelVectorEnv
from tests.conftest import render_point
from tests.test_dynamics import tiny_world_model

ROOT = Path(__file__).resolve().parents[1]

# -- the Task object --------------------------------------------------------------------------


def test_pusht_keeps_its_keys_motion_and_scorer():
    task = get_task("pusht")
    assert isinstance(task, PushTTask) and task.action_dim == 4 and task.start_source == "mujoco"
    b = task.bindings.to_dict()
    # the page's keys before the Task seam: WASD the left pusher, IJKL the right one, 0.2 m/s
    assert b["keys"] == {"w": [1, 1.0], "s": [1, -1.0], "a": [0, -1.0], "d": [0, 1.0],
                         "i": [3, 1.0], "k": [3, -1.0], "j": [2, -1.0], "l": [2, 1.0]}
    assert b["axes"] == [[0, 0, 1.0], [1, 1, -1.0], [2, 2, 1.0], [3, 3, -1.0]]
    assert b["speed"] == [0.2] * 4 and b["drag"] == [[0, 1], [2, 3]] and b["drag_speed"] == 0.3
    setpoint, command = np.zeros(4), np.array([0.3, 0.0, -0.01, 0.01])
    np.testing.assert_array_equal(task.executed(setpoint, command), limit_targets(setpoint, command))
    assert task.out_of_bounds(np.array([1.0, 0, 0, 0])) is None  # clipped, as MuJoCo clips
    blank = np.full((1, 64, 64, 3), 255, np.uint8)
    assert task.score(blank).shape == (1,) and task.is_success(np.array([0.95, 0.5])).tolist() == [True, False]


def test_pusht_agent_pos_is_the_setpoint_unless_the_frame_shows_the_pusher_held_back():
    obs, _ = gym.make("iwsim/BimanualPushT-v0").reset(seed=3)
    frame, true = obs["pixels"][None], obs["agent_pos"].astype(np.float64)[None]
    task, previous = get_task("pusht"), np.full((1, 4), 0.1, np.float32)
    near = true + np.array([[0.003, -0.002, -0.002, 0.003]])  # a pixel reading's error, not contact
    np.testing.assert_allclose(task.observe(frame, near, previous)[1], near, atol=1e-6)
    far = true + np.array([[0.02, 0.0, 0.0, -0.02]])  # commanded 2 cm further than the pushers are
    seen = task.observe(frame, far, previous)[1]
    apart = np.linalg.norm((seen - far).reshape(2, 2), axis=1)
    assert np.abs(seen - true).max() < 0.004 and apart.min() > 0.015
    blank = np.full_like(frame, 255)  # no pusher seen: the previous positions
    np.testing.assert_array_equal(task.observe(blank, near, previous)[1], previous)


def test_the_shipped_checkpoint_and_models_built_in_code_are_pusht():
    config = json.loads((ROOT / "checkpoints" / "pusht-64" / "config.json").read_text())
    assert isinstance(task_from_config(config), PushTTask)
    before_the_task_seam = {k: v for k, v in config.items() if k != "task"}  # as checkpoints written before it
    assert isinstance(task_from_config(before_the_task_seam), PushTTask)
    assert isinstance(task_of(tiny_world_model()), PushTTask)
    generic = task_from_config({"action_norm": {"low": [-1.0, 0.0], "high": [1.0, 2.0]}})
    assert type(generic) is DatasetTask and generic.action_dim == 2 and generic.score(None) is None


def test_generic_task_defaults_and_round_trip():
    task = DatasetTask(name="arm", action_low=(-1, 0, -2), action_high=(1, 1, 2), action_names=("a", "b", "c"),
                       fps=15, action_step=(0.1, 0.05, 0.2), store="data/arm.zarr")
    b = task.bindings
    assert [k for k, _, _ in b.keys] == ["d", "a", "w", "s", "l", "j"]  # the first three dimensions
    assert b.speed == pytest.approx((1.5, 0.75, 3.0))  # a held key moves a step per control step
    assert task.score_name is None and task.is_success(None) is None
    np.testing.assert_array_equal(task.executed(np.zeros(3), np.array([5.0, 0.5, -5.0])), [1.0, 0.5, -2.0])
    assert "action b = 1.5 is outside the task's bounds [0, 1]" in task.out_of_bounds(np.array([0, 1.5, 0]))
    assert task.out_of_bounds(np.array([1.0, 0.0, 2.0])) is None
    back = task_from_dict(json.loads(json.dumps(task.describe())))
    assert back == task
    assert task_from_dict(get_task("pusht").describe()) == get_task("pusht")


BAD_BINDINGS = {
    "reserved key": ({"keys": {"c": [0, 1]}, "speed": [1, 1]}, "'c' is taken by the page"),
    "long key": ({"keys": {"up": [0, 1]}, "speed": [1, 1]}, "one lower-case character"),
    "dimension": ({"keys": {"w": [2, 1]}, "speed": [1, 1]}, "dimension 2 is not one of the task's 0..1"),
    "sign": ({"keys": {"w": [0, 2]}, "speed": [1, 1]}, "sign must be 1 or -1"),
    "axis": ({"axes": [[40, 0, 1]], "speed": [1, 1]}, "gamepad axis 0..15"),
    "speed": ({"speed": [1]}, "speed must be 2 positive numbers"),
    "drag without a view": ({"drag": [[0, 1]], "drag_speed": 1, "speed": [1, 1]}, "declares view_half"),
    "unknown field": ({"speed": [1, 1], "mouse": 1}, "unknown binding fields"),
    "not an object": ([1, 2], "JSON object"),
}


@pytest.mark.parametrize("name", BAD_BINDINGS)
def test_bad_bindings_are_one_line(name):
    d, match = BAD_BINDINGS[name]
    with pytest.raises(InputError, match=match) as e:
        Bindings.from_dict(d, 2)
    assert "\n" not in str(e.value)


def test_bad_task_descriptions_are_one_line():
    with pytest.raises(InputError, match="high > low"):
        DatasetTask(name="x", action_low=(0, 0), action_high=(1, 0))
    with pytest.raises(InputError, match="2 action dimensions but 3 names"):
        DatasetTask(name="x", action_low=(0, 0), action_high=(1, 1), action_names=("a", "b", "c"))
    with pytest.raises(InputError, match="unknown task kind 'robot'"):
        task_from_dict({"kind": "robot"})
    with pytest.raises(InputError, match="unknown task 'aloha'"):
        get_task("aloha")
    with pytest.raises(InputError, match="no initial frames"):
        Task(name="x", action_low=(0,), action_high=(1,)).initial_frames(64)


def test_a_store_named_after_a_builtin_task_with_other_actions_is_generic(tmp_path):
    """Another simulator's Push-T (one pusher, 2-D actions) is not our bimanual T-push."""
    store = EpisodeStore.create(tmp_path / "pusht.zarr", {"task": "pusht", "fps": 10, "image_size": 64})
    pos = np.random.default_rng(0).uniform(-1, 1, (8, 2)).astype(np.float32)
    store.append({"img": render_point(pos), "state": pos, "action": pos})
    task = task_from_store(tmp_path / "pusht.zarr")
    assert type(task) is DatasetTask and task.name == "pusht" and task.action_dim == 2
    assert task.action_names == ("a0", "a1") and task.store == str(tmp_path / "pusht.zarr")
    np.testing.assert_allclose(task.action_step, 0.1 * pos.std(0), rtol=1e-5)
    np.testing.assert_allclose(task.action_high, pos.max(0), rtol=1e-6)


# -- a second task end to end ------------------------------------------------------------------


def test_the_checkpoint_records_its_task(point_model):
    config = json.loads((point_model["checkpoint"] / "config.json").read_text())
    task = config["task"]
    assert task["kind"] == "generic" and task["name"] == "point" and task["action_names"] == ["x", "y"]
    assert task["store"] == str(point_model["store"]) and task["fps"] == 10
    wm = WorldModel.load(point_model["checkpoint"])
    assert wm.task == task_from_dict(task) and wm.action_dim == 2
    np.testing.assert_allclose(wm.task.action_low, wm.action_low.numpy(), rtol=1e-6)
    # the training run's own checkpoints record it too (they load without the store)
    run_config = json.loads((point_model["run"] / "checkpoints" / "last" / "config.json").read_text())
    assert run_config["task"] == task


def test_world_model_env_on_the_point_task(point_model, one_thread):
    env = gym.make("iwsim/WorldModel-v0", checkpoint=str(point_model["checkpoint"]))
    assert env.action_space.shape == (2,) and env.observation_space["agent_pos"].shape == (2,)
    store = EpisodeStore.open(point_model["store"])
    obs, info = env.reset(seed=7)  # the first frame of episode 7 % 6
    np.testing.assert_array_equal(obs["pixels"], store.episode(1)["img"][0])
    np.testing.assert_allclose(obs["agent_pos"], store.episode(1)["action"][0])
    assert info == {"score": None}
    command = np.array([0.3, -0.2], np.float32)
    obs, reward, terminated, truncated, info = env.step(command)
    assert obs["pixels"].shape == (64, 64, 3) and info["score"] is None and "is_success" not in info
    assert reward == 0.0 and not terminated
    np.testing.assert_allclose(info["target"], command)  # the identity map: executed as commanded
    np.testing.assert_allclose(obs["agent_pos"], command)
    obs, *_, info = env.step(np.array([9.0, 0.0]))  # beyond the bounds: clipped to them
    assert info["target"][0] == pytest.approx(env.unwrapped.task.action_high[0])
    with pytest.raises(InputError, match=r"shape \(2,\) \[x, y\]"):
        env.step(np.zeros(4))
    with pytest.raises(InputError, match="reset_source must be one of \\('dataset', 'store'\\)"):
        WorldModelEnv(point_model["checkpoint"], reset_source="mujoco")
    with pytest.raises(InputError, match="takes 2-D actions; task 'pusht' needs 4"):
        WorldModelEnv(point_model["checkpoint"], task="pusht")
    env.close()

    venv = WorldModelVectorEnv(3, point_model["checkpoint"], max_episode_steps=2)
    obs, info = venv.reset(seed=0)
    for e in range(3):
        np.testing.assert_array_equal(obs["pixels"][e], store.episode(e)["img"][0])
    obs, reward, _, truncated, info = venv.step(np.zeros((3, 2)))
    assert info["score"] is None and reward.tolist() == [0, 0, 0] and obs["agent_pos"].shape == (3, 2)


def test_play_records_and_exports_and_eval_reports_no_scorer(point_model, tmp_path, capsys, one_thread):
    wm = WorldModel.load(point_model["checkpoint"])
    demos = tmp_path / "demos.zarr"
    eng = Engine(wm, PlayConfig(record_to=demos, checkpoint=str(point_model["checkpoint"])))
    s = eng.open()
    hello = json.loads(eng.hello(s))
    assert hello["action_names"] == ["x", "y"] and hello["score_name"] is None and not hello["side_by_side"]
    assert hello["reset_sources"] == ["dataset"] and hello["start_source"] == "dataset"
    assert set(hello["bindings"]["keys"]) == {"d", "a", "w", "s"} and hello["bindings"]["drag"] == []
    store = EpisodeStore.open(point_model["store"])
    start = store.episode(s.seed % store.n_episodes)
    np.testing.assert_allclose(s.target, start["action"][0])  # the episode's first command
    # a command outside the bounds: one line, the command and the session unchanged
    before = s.target.copy()
    (event,) = eng.handle(s, proto.Action(1, (5.0, 0.0)))
    assert json.loads(event)["type"] == "error" and "action x = 5 is outside the task's bounds" in event
    np.testing.assert_array_equal(s.target, before)
    assert "starts from 'dataset' or 'store', not 'mujoco'" in eng.handle(s, proto.Reset("mujoco", 1))[0]
    assert "no simulator" in eng.handle(s, proto.SideBySide(True))[0]
    eng.handle(s, proto.Reset("dataset", 2))
    eng.handle(s, proto.Command("record"))
    commands = np.array([[0.1, 0.2], [0.2, 0.2], [0.3, 0.1], [0.3, 0.0]], np.float32)
    for t, c in enumerate(commands):
        assert eng.handle(s, proto.Action(t + 2, tuple(c))) == []
        eng.tick()
        header, views = proto.unpack_frame(eng.frame_message(s))
        assert header["iou"] is None and header["action"] == pytest.approx(c.tolist())
    eng.handle(s, proto.Command("save"))
    eng.recorder.close()
    assert json.loads(eng.finished_saves()[0][1])["type"] == "saved"
    eng.shutdown()
    ep = EpisodeStore.open(demos).episode(0)
    assert sorted(ep) == ["action", "img", "state", "target"]  # no score: no "iou" array
    np.testing.assert_allclose(ep["action"], commands)
    np.testing.assert_allclose(ep["target"], commands)  # executed as commanded
    np.testing.assert_array_equal(ep["img"][0], store.episode(2)["img"][0])
    recorded = task_from_store(demos)
    assert (recorded.name, recorded.action_names, recorded.fps) == ("point", ("x", "y"), 10.0)
    assert recorded.action_low == wm.task.action_low and recorded.action_high == wm.task.action_high

    # the take exports to LeRobot like any other store and validates
    lerobot = tmp_path / "lerobot"
    assert main(["data", "export", "--format", "lerobot-v3", "--in", str(demos), "--out", str(lerobot)]) == 0
    assert main(["data", "validate", str(lerobot)]) == 0
    info = json.loads((lerobot / "meta" / "info.json").read_text())
    assert info["features"]["action"]["shape"] == [2] and info["features"]["action"]["names"] == ["x", "y"]
    back = tmp_path / "back.zarr"  # and a LeRobot v3 dataset imports as the same task
    assert main(["data", "import", "--format", "lerobot-v3", "--in", str(lerobot), "--out", str(back),
                 "--image-size", "64"]) == 0
    assert task_from_store(back).action_names == ("x", "y") and task_from_store(back).name == "point"

    # a (barely) trained policy evaluated inside the model: no scorer, so no score
    policy, out = tmp_path / "policy", tmp_path / "eval"
    assert main(["train", "policy", "--policy", "dp", "--preset", "tiny-dp", "--data", str(point_model["store"]),
                 "--steps", "2", "--out", str(policy), "--no-progress"]) == 0
    capsys.readouterr()
    assert main(["eval", "policy", "--checkpoint", str(policy), "--env", "world-model", "--world-model",
                 str(point_model["checkpoint"]), "--episodes", "2", "--steps", "3", "--videos", "1",
                 "--out", str(out), "--no-progress"]) == 0
    assert "no scorer (task 'point' has no pixel scorer)" in capsys.readouterr().out
    result = json.loads((out / "results.json").read_text())
    assert result["scorer"] is None and result["mean_max_score"] is None and result["success_rate"] is None
    assert result["task"] == "point" and [e["seed"] for e in result["episodes"]] == [100000, 100001]
    assert (out / "episode_100000.mp4").stat().st_size > 0 and not (out / "iou.json").exists()
    assert next(iter(result)) == "command" and result["command"].startswith("iwsim eval policy --checkpoint")


def test_play_cli_refuses_bad_bindings_in_one_line(point_model, tmp_path, capsys):
    bad = tmp_path / "bindings.json"
    bad.write_text(json.dumps({"keys": {"w": [5, 1]}, "speed": [1, 1]}))
    assert main(["play", "--checkpoint", str(point_model["checkpoint"]), "--port", "0", "--bindings", str(bad)]) == 1
    err = capsys.readouterr().err.strip()
    assert err == "iwsim: error: binding key 'w': dimension 5 is not one of the task's 0..1."
    bad.write_text("{not json")
    assert main(["play", "--checkpoint", str(point_model["checkpoint"]), "--port", "0", "--bindings", str(bad)]) == 1
    assert "is not valid JSON" in capsys.readouterr().err


def test_rollout_of_the_point_model_reports_no_score(point_model, tmp_path, capsys, one_thread):
    """Open loop on another robot's episodes: PSNR and SSIM, never T-push's IoU of its frames."""
    video = tmp_path / "r.mp4"
    capsys.readouterr()
    assert main(["rollout", "--checkpoint", str(point_model["checkpoint"]), "--data", str(point_model["store"]),
                 "--episode", "1", "--steps", "4", "--out", str(video)]) == 0
    assert "no scorer (the task has no pixel scorer)" in capsys.readouterr().out
    scores = json.loads(video.with_suffix(".json").read_text())
    assert scores["iou_true"] is None and scores["iou_abs_err"] is None and len(scores["psnr_per_step"]) == 4
    assert main(["bench", "--checkpoint", str(point_model["checkpoint"]), "--data", str(point_model["store"]),
                 "--out", str(tmp_path / "bench"), "--episodes", "1", "--steps", "2"]) == 1
    assert "task 'point' has no pixel scorer" in capsys.readouterr().err


def test_a_policy_of_another_size_is_refused_in_one_line(point_model, one_thread):
    from iwsim.eval.policy import evaluate

    class Still:
        obs_horizon, action_dim, state_dim = 1, 2, 5

    with pytest.raises(InputError, match="the policy takes 5-D states; task 'point' in world-model has 2-D ones"):
        evaluate(Still(), "world-model", episodes=1, seed=0, steps=1,
                 world_model=WorldModel.load(point_model["checkpoint"]))


def test_play_takes_bindings_instead_of_the_tasks(point_model):
    own = {"keys": {"h": [1, 1], "n": [1, -1]}, "axes": [[3, 0, 1]], "speed": [0.5, 0.25], "legend": ["y: H / N"]}
    eng = Engine(WorldModel.load(point_model["checkpoint"]), PlayConfig(bindings=own))
    hello = json.loads(eng.hello(eng.open()))
    assert hello["bindings"] == {**own, "keys": {"h": [1, 1.0], "n": [1, -1.0]}, "axes": [[3, 0, 1.0]],
                                 "drag": [], "drag_speed": 0.0}
    with pytest.raises(InputError, match="binding key 'q' is taken by the page"):
        Engine(WorldModel.load(point_model["checkpoint"]), PlayConfig(bindings={**own, "keys": {"q": [0, 1]}}))


@pytest.mark.parametrize("study", ["datagen", "policy-eval"])
def test_the_studies_refuse_a_world_model_of_another_task(point_model, tmp_path, capsys, study):
    """The studies compare with MuJoCo's T-push: a point-robot model gets one line, and no work is started."""
    work = tmp_path / "work"
    assert main(["experiment", study, "--preset", "tiny", "--world-model", str(point_model["checkpoint"]),
                 "--work", str(work), "--out", str(tmp_path / "out")]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "task 'point'" in err[0] and "'pusht'" in err[0]
    assert not work.exists()
