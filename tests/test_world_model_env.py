"""iwsim/WorldModel-v0 and its vector form on a tiny world model, and the stage-2 CLI."""

import json
from pathlib import Path

import gymnasium as gym
import numpy as np
import pytest
import torch
from gymnasium.utils.env_checker import check_env

from iwsim.cli import main
from iwsim.world_model import WorldModel
from iwsim.world_model.env import WorldModelEnv, WorldModelVectorEnv
from tests.test_dynamics import tiny_world_model


@pytest.fixture(scope="module")
def wm() -> WorldModel:
    return tiny_world_model()


def test_check_env(wm):
    env = WorldModelEnv(model=wm)
    check_env(env, skip_render_check=False)
    mujoco = gym.make("iwsim/BimanualPushT-v0")
    assert env.observation_space == mujoco.observation_space and env.action_space == mujoco.action_space


def test_reset_sources(wm, play_store):
    env = WorldModelEnv(model=wm)
    obs, info = env.reset(seed=100000)
    ref, _ = gym.make("iwsim/BimanualPushT-v0").reset(seed=100000)
    np.testing.assert_array_equal(obs["pixels"], ref["pixels"])  # the same seed's MuJoCo frame
    np.testing.assert_array_equal(obs["agent_pos"], ref["agent_pos"])
    assert 0 <= info["iou"] <= 1
    obs, _ = env.reset(options={"frame": ref["pixels"]})
    assert np.abs(obs["agent_pos"] - ref["agent_pos"]).max() < 0.005  # read from the pushers' pixels
    store_env = WorldModelEnv(model=wm, reset_source="store", store=play_store)
    a, _ = store_env.reset(seed=1)
    b, _ = store_env.reset(seed=1)
    np.testing.assert_array_equal(a["pixels"], b["pixels"])
    obs, reward, terminated, truncated, info = store_env.step(store_env.action_space.sample())
    assert obs["pixels"].shape == (64, 64, 3) and reward == info["iou"]
    with pytest.raises(ValueError, match="unknown reset options"):
        env.reset(options={"frmae": 1})
    with pytest.raises(ValueError, match="store"):
        WorldModelEnv(model=wm, reset_source="store")
    with pytest.raises(ValueError, match="shape"):
        env.reset(options={"frame": np.zeros((32, 32, 3), np.uint8)})


def test_gym_make_from_checkpoint(wm, tmp_path):
    wm.save(tmp_path / "wm")
    env = gym.make("iwsim/WorldModel-v0", checkpoint=str(tmp_path / "wm"))
    env.reset(seed=0)
    assert env.spec.max_episode_steps == 600
    with pytest.raises(ValueError, match="finite"):
        env.step(np.array([0, np.nan, 0, 0], np.float32))


def test_vector_env_equals_single_envs(wm):
    n, steps = 3, 4
    venv = WorldModelVectorEnv(n, model=wm, max_episode_steps=steps)
    rng = np.random.default_rng(0)
    actions = rng.uniform(-0.2, 0.2, (steps, n, 4)).astype(np.float32)
    obs, _ = venv.reset(seed=100)
    frames, ious = [obs["pixels"]], []
    for t in range(steps):
        obs, reward, term, trunc, info = venv.step(actions[t])
        frames.append(obs["pixels"])
        ious.append(info["iou"])
        assert trunc.all() == (t == steps - 1) and not term.any()
    single = WorldModelEnv(model=tiny_world_model())
    for i in range(n):
        o, _ = single.reset(seed=100 + i)
        assert np.abs(o["pixels"].astype(int) - frames[0][i]).max() == 0
        for t in range(steps):
            o, r, *_ = single.step(actions[t, i])
            assert np.abs(o["pixels"].astype(int) - frames[t + 1][i]).max() <= 1
    obs, reward, term, trunc, _ = venv.step(actions[0])  # next-step autoreset
    assert not trunc.any() and (reward == 0).all()
    np.testing.assert_array_equal(obs["pixels"][0], WorldModelEnv(model=wm).reset(seed=103)[0]["pixels"])


@pytest.mark.slow
def test_stage2_cli_end_to_end(play_store, tmp_path, capsys):
    ae, dyn, wm_dir = tmp_path / "ae", tmp_path / "dyn", tmp_path / "wm"
    assert main(["train", "ae", "--data", str(play_store), "--preset", "tiny", "--out", str(ae), "--no-progress"]) == 0
    assert main(["train", "dynamics", "--data", str(play_store), "--ae", str(ae), "--preset", "tiny",
                 "--out", str(dyn), "--no-progress"]) == 0
    rows = [json.loads(line) for line in (dyn / "metrics.jsonl").read_text().splitlines()]
    assert rows[-1]["step"] == 6 and "eval/psnr" in rows[-1]
    WorldModel.load(dyn / "checkpoints" / "last")  # every run checkpoint is a world model
    assert main(["export-model", "--dynamics", str(dyn), "--out", str(wm_dir)]) == 0
    assert main(["export-model", "--dynamics", str(dyn), "--out", str(wm_dir)]) == 1  # exists
    # stage 3: the decoder changes, the encoder and the dynamics do not
    ft = tmp_path / "ft"
    assert main(["train", "decoder-finetune", "--world-model", str(wm_dir), "--data", str(play_store),
                 "--out", str(ft), "--steps", "2", "--no-progress"]) == 0
    assert main(["export-model", "--run", str(ft), "--out", str(tmp_path / "wm_ft")]) == 0
    before, after = WorldModel.load(wm_dir).state_dict(), WorldModel.load(tmp_path / "wm_ft").state_dict()
    assert before.keys() == after.keys()
    changed = {k.split(".")[0] + "." + k.split(".")[1] for k in before if not torch.equal(before[k], after[k])}
    assert changed == {"codec.decoder"}
    # the fine-tuned decoder on another dynamics run of the same encoder; a codec of other
    # encoder weights is refused in one line and writes nothing
    dyn2 = tmp_path / "dyn2"
    assert main(["train", "dynamics", "--init", str(wm_dir), "--data", str(play_store), "--preset", "tiny",
                 "--steps", "2", "--out", str(dyn2), "--no-progress"]) == 0
    assert main(["export-model", "--run", str(dyn2), "--decoder", str(ft), "--out", str(tmp_path / "wm2")]) == 0
    joined, dec, dyn2_wm = (WorldModel.load(p).state_dict() for p in (tmp_path / "wm2", tmp_path / "wm_ft",
                                                                       dyn2 / "checkpoints" / "last"))
    assert all(torch.equal(v, dec[k] if k.startswith("codec.") else dyn2_wm[k]) for k, v in joined.items())
    assert json.loads((tmp_path / "wm2" / "config.json").read_text())["provenance"]["decoder"].startswith(str(ft))
    ae2 = tmp_path / "ae2"
    assert main(["train", "ae", "--data", str(play_store), "--preset", "tiny", "--seed", "1", "--out", str(ae2),
                 "--no-progress"]) == 0
    dyn3 = tmp_path / "dyn3"
    assert main(["train", "dynamics", "--data", str(play_store), "--ae", str(ae2), "--preset", "tiny",
                 "--steps", "2", "--out", str(dyn3), "--no-progress"]) == 0
    capsys.readouterr()
    assert main(["export-model", "--run", str(dyn3), "--decoder", str(ft), "--out", str(tmp_path / "wm3")]) == 1
    assert "encodes differently" in capsys.readouterr().err and not (tmp_path / "wm3").exists()
    video = tmp_path / "r.mp4"
    capsys.readouterr()
    assert main(["rollout", "--checkpoint", str(wm_dir), "--data", str(play_store), "--episode", "3",
                 "--steps", "8", "--out", str(video)]) == 0
    assert "mean PSNR" in capsys.readouterr().out
    scores = json.loads(video.with_suffix(".json").read_text())
    assert len(scores["psnr_per_step"]) == 8 and video.stat().st_size > 0
    assert (tmp_path / "r_psnr.png").exists()
    assert main(["rollout", "--checkpoint", str(wm_dir), "--data", str(play_store), "--episode", "3",
                 "--steps", "50", "--out", str(video)]) == 1  # the episode is shorter
    assert main(["rollout", "--checkpoint", str(ae / "checkpoints" / "last"), "--data", str(play_store),
                 "--out", str(video)]) == 1  # not a world model


def test_the_model_is_conditioned_on_the_motion_mujoco_executes(wm):
    """From the same seed and under the same far commands, WorldModel-v0 conditions its
    model on exactly the setpoints MuJoCo executes (the task's speed limit), in the single
    and the vector env."""
    mujoco = gym.make("iwsim/BimanualPushT-v0")
    env = WorldModelEnv(model=wm)
    venv = WorldModelVectorEnv(2, model=tiny_world_model())  # a model holds one rollout's state
    mujoco.reset(seed=100000)
    env.reset(seed=100000)
    venv.reset(seed=100000)
    rng = np.random.default_rng(0)
    for _ in range(6):
        command = rng.uniform(-0.3, 0.3, 4).astype(np.float32)  # far, some outside the workspace
        _, _, _, _, truth = mujoco.step(command)
        _, _, _, _, info = env.step(command)
        _, _, _, _, vinfo = venv.step(np.stack([command, command]))
        np.testing.assert_allclose(info["target"], truth["target"], atol=1e-6)
        np.testing.assert_allclose(vinfo["target"][0], truth["target"], atol=1e-6)
    with pytest.raises(ValueError, match="finite actions"):
        env.step(np.array([0.0, np.nan, 0.0, 0.0], np.float32))


def test_a_store_of_another_task_is_refused_as_starts(play_store):
    """Issue 65 row 11: T-push frames from --store were fed to (and scored by) a pile model."""
    pile = WorldModel.load(Path(__file__).resolve().parents[1] / "checkpoints" / "pilesweep-64")
    with pytest.raises(ValueError, match="holds episodes of task 'pusht'; the world model is of 'pilesweep'"):
        WorldModelEnv(model=pile, reset_source="store", store=play_store)
