"""The pushers' own state (issue 64, item 2): the dynamics takes the robot's state, predicts
it each step and feeds the prediction back; the world-model environment and play report it
as ``agent_pos``. Tiny models: trained a few steps, the head lowers its error."""

import dataclasses
import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import gymnasium as gym
import numpy as np
import pytest
import torch
from test_dynamics import batch_for, randomise, tiny_cfg

from iwsim.cli import main
from iwsim.core.errors import InputError
from iwsim.world_model import StreamState, WorldModel
from iwsim.world_model.dynamics import Dynamics, add_state
from iwsim.world_model.env import WorldModelVectorEnv, predicts_agent_pos
from iwsim.world_model.train_dynamics import DynamicsTrainModule


def test_the_state_head_learns_where_the_pushers_go(one_thread):
    """Pushers held back halfway to their setpoints (the state the action sets, times
    0.5): a few dozen steps on one batch take the state's error well below where it starts
    (the head starts at the setpoint), and every state parameter gets a gradient (once
    the zero-initialised output layers have moved)."""
    cfg = tiny_cfg("state")
    torch.manual_seed(0)
    module = DynamicsTrainModule(Dynamics(cfg.dynamics), cfg)
    g = torch.Generator().manual_seed(0)
    b, n, k = 8, 3, cfg.dynamics.context
    actions = torch.rand(b, n + 1, 4, generator=g) * 2 - 1
    batch = batch_for(cfg, torch.randn(b, k + n, 4, 16, 16, generator=g), actions, g)
    held_back = 0.5 * actions[:, 1:] * 0.22 / 0.2  # half the state the action sets (tiny_cfg's state_action_scale)
    batch.states = torch.cat([torch.rand(b, 1, 4, generator=g) * 2 - 1, held_back], 1)
    opt = torch.optim.Adam(module.parameters(), lr=3e-3)
    errors = []
    for i in range(40):
        loss, parts = module(batch)
        opt.zero_grad()
        loss.backward()
        if i == 39:
            assert all(p.grad is not None and p.grad.abs().sum() > 0 for name, p in module.named_parameters()
                       if name.startswith(("dynamics.state_head", "dynamics.state_grid")))
        opt.step()
        errors.append(parts["state_mse"])
    assert errors[-1] < 0.3 * errors[0], errors


def test_contact_weighs_the_steps_where_the_robot_stands_apart_from_its_setpoint(one_thread):
    """``state_contact_weight``: a step whose recorded state stands more than the gap from
    the state its setpoint sets adds its state error 1 + weight times; the others once."""
    cfg = tiny_cfg("state")
    dynamics = Dynamics(cfg.dynamics)
    randomise(dynamics)
    g = torch.Generator().manual_seed(0)
    b, n, k = 6, 3, cfg.dynamics.context
    actions = torch.rand(b, n + 1, 4, generator=g) * 2 - 1
    batch = batch_for(cfg, torch.randn(b, k + n, 4, 16, 16, generator=g), actions, g)
    reached = dynamics.setpoint_state(torch.stack([actions[:, :-1], actions[:, 1:]], 2).flatten(0, 1)).view(b, n, 4)
    reached[::2] += 0.1  # every other sequence held 0.1 (normalised) back at each step
    batch.states = torch.cat([torch.zeros(b, 1, 4), reached], 1)
    plain, err = DynamicsTrainModule(dynamics, cfg).unroll(batch)
    contact = dataclasses.replace(cfg, state_contact_weight=4.0, state_contact_gap=0.05)
    weighted, err_again = DynamicsTrainModule(dynamics, contact).unroll(batch)
    torch.testing.assert_close(err, err_again)
    held = torch.zeros(b, 1)
    held[::2] = 1
    torch.testing.assert_close(weighted - plain, 4.0 * held * err)
    with pytest.raises(InputError, match="state_contact_weight needs a robot state"):
        no_points = dataclasses.replace(contact, dynamics=dataclasses.replace(
            cfg.dynamics, state_action_scale=(), state_action_offset=()))
        DynamicsTrainModule(Dynamics(no_points.dynamics), no_points)


def test_a_model_gains_the_state_without_changing_its_latents():
    """``add_state``: a network without the state, given one with zero input weights, predicts
    the same latents whatever the state, and its head starts at the state the setpoint sets."""
    cfg = tiny_cfg("state").dynamics
    without = dataclasses.replace(cfg, state_dim=0, state_point_scale=(), state_point_offset=(), state_action_scale=(),
                                  state_action_offset=())
    old = randomise(Dynamics(without), 1)
    new = Dynamics(cfg)
    new.load_state_dict(add_state(old.state_dict(), without, new))
    g = torch.Generator().manual_seed(0)
    x, ctx = torch.randn(2, 4, 16, 16, generator=g), torch.randn(2, cfg.context, 4, 16, 16, generator=g)
    t, a, state = torch.full((2,), 999.0), torch.rand(2, 2, 4, generator=g) * 2 - 1, torch.rand(2, 4, generator=g)
    with torch.no_grad():
        torch.testing.assert_close(new(x, ctx, t, t * 0, t * 0, a, state), old(x, ctx, t, t * 0, t * 0, a))
        torch.testing.assert_close(new.predict_state(x, ctx[:, -1], a, state), a[:, 1] * 0.22 / 0.2)
    with pytest.raises(InputError, match="takes the robot's state"):
        new(x, ctx, t, t * 0, t * 0, a)


@pytest.fixture(scope="module")
def state_model(play_store, tmp_path_factory):
    """A tiny T-push world model trained with the state, as a user would."""
    root = tmp_path_factory.mktemp("state")
    n = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        for argv in (["train", "ae", "--data", str(play_store), "--preset", "tiny", "--out", str(root / "ae"),
                      "--no-progress"],
                     ["train", "dynamics", "--data", str(play_store), "--ae", str(root / "ae"), "--preset", "tiny",
                      "--variant", "state", "--out", str(root / "dyn"), "--no-progress"],
                     ["export-model", "--run", str(root / "dyn"), "--out", str(root / "wm")]):
            assert main(argv) == 0, argv
    finally:
        torch.set_num_threads(n)
    return root


def test_the_frame_shows_the_pushers_and_the_prediction_fills_in_those_it_does_not(monkeypatch):
    """A pusher the frame shows is where the frame shows it (at its setpoint when seen near
    it); one it does not show is where the model predicted it, or without a prediction
    where it was; a task without a pixel reading reports the prediction, else the setpoint."""
    from iwsim.envs.registry import get_task

    task = get_task("pusht")
    seen = np.array([[0.10, 0.10, -0.05, 0.02]])  # the left pusher seen 5 mm from its setpoint, the right 50 mm
    monkeypatch.setattr(type(task), "read", lambda self, frames: (np.zeros(1), seen, np.array([[True, False]])))
    setpoint = np.array([[0.105, 0.10, 0.0, 0.0]])
    previous, predicted = np.full((1, 4), 0.2, np.float32), np.full((1, 4), -0.1, np.float32)
    frames = np.zeros((1, 64, 64, 3), np.uint8)
    np.testing.assert_allclose(task.observe(frames, setpoint, previous, predicted)[1], [[0.105, 0.10, -0.1, -0.1]])
    np.testing.assert_allclose(task.observe(frames, setpoint, previous)[1], [[0.105, 0.10, 0.2, 0.2]])
    monkeypatch.setattr(type(task), "read", lambda self, frames: (np.zeros(1), seen, np.array([[True, True]])))
    np.testing.assert_allclose(task.observe(frames, setpoint, previous, predicted)[1], [[0.105, 0.10, -0.05, 0.02]])
    from iwsim.envs.task import Task

    np.testing.assert_array_equal(Task.observe(task, frames, setpoint, previous, predicted)[1], predicted)
    np.testing.assert_allclose(Task.observe(task, frames, setpoint, previous)[1], setpoint)


def test_the_environment_reports_the_predicted_agent_pos(state_model, one_thread):
    """The checkpoint records the state's normalisation; ``WorldModel-v0`` starts the state
    at the start's agent_pos and after each step reports the pushers the frame shows, and
    the model's prediction (within the workspace) for those it does not, in one
    environment and in the vector env (whose batched rollout equals the single ones)."""
    wm = WorldModel.load(state_model / "wm")
    assert wm.state_dim == 4 and predicts_agent_pos(wm, wm.task)
    env = gym.make("iwsim/WorldModel-v0", model=wm)
    obs, _ = env.reset(seed=100000)
    start = obs["agent_pos"].copy()
    np.testing.assert_allclose(wm.robot_state()[0], start, atol=1e-6)
    rng = np.random.default_rng(0)
    actions = rng.uniform(-0.2, 0.2, (5, 4)).astype(np.float32)
    singles = []
    previous = start
    for a in actions:
        obs, _, _, _, info = env.step(a)
        # the prediction, within the workspace (the task's agent_pos bounds), where the frame shows no pusher
        own = np.clip(wm.robot_state()[0], wm.task.action_low, wm.task.action_high).astype(np.float32)
        _, want = wm.task.observe(obs["pixels"][None], info["target"][None], previous[None], own[None])
        np.testing.assert_array_equal(obs["agent_pos"], want[0])
        assert env.observation_space["agent_pos"].contains(obs["agent_pos"])
        singles.append(previous := obs["agent_pos"])
    assert not np.allclose(singles[-1], start)  # the state moves with the commands
    venv = WorldModelVectorEnv(2, model=WorldModel.load(state_model / "wm"), max_episode_steps=10)
    venv.reset(seed=100000)
    for a in actions:
        vobs, *_ = venv.step(np.stack([a, a]))
    np.testing.assert_allclose(vobs["agent_pos"][0], singles[-1], atol=1e-5)


def test_a_state_model_refuses_mixed_batches_and_fine_tunes_add_it(state_model, play_store, tmp_path, one_thread,
                                                                   capsys):
    """StreamState.cat refuses states of a model with and without the state; ``--init`` of a
    model trained without it with ``--variant state`` trains the state in, ``state-contact``
    also weighs contact in its loss; any other variant with --init is still refused."""
    wm = WorldModel.load(state_model / "wm")
    frame = np.zeros((1, 64, 64, 3), np.uint8)
    with_state = wm.reset_state(frame, state=np.zeros((1, 4), np.float32))
    without = dataclasses.replace(with_state, robot=None)
    with pytest.raises(InputError, match="with and without"):
        StreamState.cat([with_state, without])
    assert StreamState.cat([with_state, with_state]).split()[1].robot.shape == (1, 4)
    ae = state_model / "ae"
    plain = tmp_path / "plain"
    assert main(["train", "dynamics", "--data", str(play_store), "--ae", str(ae), "--preset", "tiny", "--out",
                 str(plain), "--no-progress"]) == 0
    assert WorldModel.load(plain / "checkpoints" / "00000006").state_dim == 0
    assert main(["train", "dynamics", "--data", str(play_store), "--init", str(plain), "--variant", "state",
                 "--preset", "tiny", "--steps", "3", "--out", str(tmp_path / "ft"), "--no-progress"]) == 0
    assert WorldModel.load(tmp_path / "ft" / "checkpoints" / "00000003").state_dim == 4
    assert main(["train", "dynamics", "--data", str(play_store), "--init", str(plain), "--variant", "no-delta",
                 "--preset", "tiny", "--out", str(tmp_path / "bad"), "--no-progress"]) != 0
    capsys.readouterr()
    assert main(["train", "dynamics", "--data", str(play_store), "--init", str(state_model / "wm"), "--variant",
                 "state-contact", "--preset", "tiny", "--out", str(tmp_path / "contact"), "--dry-run"]) == 0
    printed = json.loads(capsys.readouterr().out)
    assert printed["predict_state"] and printed["state_contact_weight"] == 4.0 and printed["state_contact_gap"] == 0.04


def test_training_with_the_state_needs_a_store_that_records_it(state_model, play_store, tmp_path, capsys):
    """A store without data/state: one line that says so, and no checkpoint written."""
    store = tmp_path / "no_state.zarr"
    shutil.copytree(play_store, store)
    shutil.rmtree(store / "data" / "state")
    capsys.readouterr()
    assert main(["train", "dynamics", "--data", str(store), "--ae", str(state_model / "ae"), "--preset", "tiny",
                 "--variant", "state", "--out", str(tmp_path / "dyn"), "--no-progress"]) != 0
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "no data/state" in err[0], err
    assert not (tmp_path / "dyn" / "checkpoints").exists()


def test_play_shows_the_predicted_agent_pos_of_each_session(state_model, one_thread):
    """``iwsim play``'s engine: two sessions stepped in one pass each get their own
    agent_pos (the pushers their frame shows, their predicted ones where it does not), the
    one they would get alone."""
    from iwsim.play import protocol as proto
    from iwsim.play.engine import Engine, PlayConfig

    targets = np.random.default_rng(1).uniform(-0.2, 0.2, (6, 4)).astype(np.float32)

    def run(together: bool) -> np.ndarray:
        eng = Engine(WorldModel.load(state_model / "wm"), PlayConfig())
        sessions = [eng.open() for _ in range(2 if together else 1)]
        for i, s in enumerate(sessions):
            eng.handle(s, proto.Reset("mujoco", 3 + i))
        s = sessions[0]
        start = s.agent_pos.copy()
        for t, target in enumerate(targets):
            for other in sessions:
                eng.handle(other, proto.Action(t, tuple(float(v) for v in target)))
            previous = s.agent_pos.copy()
            eng.tick()
        own = np.clip(eng.model.robot_state(s.state)[0], -0.22, 0.22)
        _, want = eng.task.observe(s.frame[None], s.setpoint[None], previous[None], own[None])
        np.testing.assert_allclose(s.agent_pos, want[0], atol=1e-6)
        assert not np.allclose(s.agent_pos, start)
        return s.agent_pos

    np.testing.assert_allclose(run(True), run(False), atol=1e-5)


@pytest.mark.slow
def test_pusher_state_bench_compares_the_prediction_and_the_pixel_reading(state_model, play_store, tmp_path):
    """``bench/pusher_state.py`` on a state model and one without: each row says where its
    agent_pos comes from, and the errors are finite millimetres (no quality asserted)."""
    root = Path(__file__).resolve().parents[1]
    plain = tmp_path / "plain"
    assert main(["train", "dynamics", "--data", str(play_store), "--ae", str(state_model / "ae"), "--preset", "tiny",
                 "--steps", "2", "--out", str(plain), "--no-progress"]) == 0
    out = tmp_path / "out"
    subprocess.run([sys.executable, str(root / "bench" / "pusher_state.py"), "--models",
                    f"state={state_model / 'wm'}", f"plain={plain}", "--stores", str(play_store), "--steps", "10",
                    "--out", str(out)], check=True, capture_output=True, env={**os.environ, "OMP_NUM_THREADS": "1"})
    report = json.loads((out / "results.json").read_text())
    rows = report["models"]
    assert rows["state"]["agent_pos"].endswith("prediction where unseen") and "pixel" in rows["plain"]["agent_pos"]
    for row in rows.values():
        r = row["stores"][str(play_store)]
        assert r["episodes"] == 4 and 0 <= r["median_mm"] <= r["p90_mm"] < 1000
        assert 0 <= r["pressing_share"] <= 1
    assert (out / "error_per_step.png").stat().st_size > 0 and "pusher_state.py" in (out / "results.md").read_text()
