"""Imitation policies: Diffusion Policy, the data mixture, training through the generic loop, closed-loop
evaluation (MuJoCo and a tiny world model) and its statistics."""

import dataclasses
import json
import shutil
from pathlib import Path

import numpy as np
import pytest
import torch
from scipy import stats

from iwsim.cli import main
from iwsim.core.checkpoint import CheckpointError
from iwsim.data.store import EpisodeStore
from iwsim.envs.collect import collect
from iwsim.envs.pilesweep.task import PileSweepTask
from iwsim.eval.policy import evaluate, rollout
from iwsim.eval.stats import beta_posterior, clopper_pearson
from iwsim.policies import PRESETS
from iwsim.policies.common import Normalizer, random_shift
from iwsim.policies.data import PolicyData, Source, parse_mixture
from iwsim.policies.factory import load_policy, make_policy
from tests.test_dynamics import tiny_world_model

pytestmark = pytest.mark.usefixtures("one_thread")

TINY_DP = PRESETS["tiny-dp"].model


def norms(a: int = 4, s: int = 4) -> tuple[Normalizer, Normalizer]:
    return (Normalizer(-0.22 * torch.ones(a), 0.22 * torch.ones(a)),
            Normalizer(-0.22 * torch.ones(s), 0.22 * torch.ones(s)))


def test_mixture_takes_exactly_the_requested_episodes(play_store, tmp_path):
    assert parse_mixture("a.zarr:30, b.zarr:70") == [Source(Path("a.zarr"), 30), Source(Path("b.zarr"), 70)]
    assert parse_mixture("c:/x.zarr")[0].episodes is None
    with pytest.raises(ValueError, match="names no episode store"):
        parse_mixture(" , ")
    data = PolicyData([Source(play_store, 3), Source(play_store, 1)], obs_horizon=2, horizon=8)
    store = EpisodeStore.open(play_store)
    ends = store.episode_ends
    assert data.n_episodes == 4 and data.n_frames == int(ends[2]) + int(ends[0])
    assert data.counts == {str(play_store): 1}  # the same store twice: the last count is listed
    with pytest.raises(ValueError, match="holds 4 episodes; 5 were asked"):
        PolicyData([Source(play_store, 5)], 2, 8)
    with pytest.raises(ValueError, match="mixture is empty"):
        PolicyData([], 2, 8)
    big = tmp_path / "big.zarr"  # 96 px frames do not fit a 64 px mixture
    collect("pusht", "play", 1, out=big, steps=4, image_size=96, workers=1, seed=0, progress=False)
    with pytest.raises(ValueError, match=r"frames of shape \(96, 96, 3\).*a mixture must agree"):
        PolicyData([Source(play_store, 1), Source(big, 1)], 2, 8)


def test_a_checkpoint_of_another_kind_is_refused(tmp_path):
    (tmp_path / "config.json").write_text(json.dumps({"kind": "world_model"}))
    (tmp_path / "model.safetensors").write_bytes(b"")
    with pytest.raises(CheckpointError, match="is a 'world_model' checkpoint, not a policy"):
        load_policy(tmp_path)


def test_windows_pad_like_diffusion_policy(play_store):
    data = PolicyData([Source(play_store, 2)], obs_horizon=2, horizon=8)
    n0 = int(data.ends[0])  # episode 0 is steps 0 .. n0 - 1
    obs, act, pad = data.windows(torch.tensor([0, n0 - 1, n0]))
    assert obs[0].tolist() == [0, 0] and act[0].tolist() == [0, 0, 1, 2, 3, 4, 5, 6]  # before the start: repeats
    assert obs[1].tolist() == [n0 - 2, n0 - 1] and act[1, :2].tolist() == [n0 - 2, n0 - 1]
    assert act[1, 2:].tolist() == [n0 - 1] * 6 and pad[1].tolist() == [False, False] + [True] * 6
    assert obs[2].tolist() == [n0, n0] and not pad[2].any()  # episode 1 starts fresh


def test_a_policy_learns_the_commands_or_the_executed_setpoints(play_store):
    store = EpisodeStore.open(play_store)
    end = int(store.episode_ends[1])
    for key in ("action", "target"):
        data = PolicyData([Source(play_store, 2)], 2, 8, actions=key)
        np.testing.assert_array_equal(data.action.numpy(), np.asarray(store.array(key)[:end], np.float32))
    assert PRESETS["dp"].actions == "action"
    with pytest.raises(ValueError, match="actions must be one of action, target"):
        dataclasses.replace(PRESETS["dp"], actions="state")


def test_random_shift_moves_whole_windows_with_the_border_repeated():
    image = torch.arange(2 * 2 * 3 * 6 * 6, dtype=torch.float32).view(2, 2, 3, 6, 6)
    out = random_shift(image, 2, torch.tensor([[2, 0], [2, 4]]))  # window 0 stays in place
    assert torch.equal(out[0], image[0])
    # window 1: offset (dy, dx) = (0, 4) of the padded image: row i shows row max(i - 2, 0), column min(j + 2, 5)
    rows, cols = (torch.arange(6) - 2).clamp(0, 5), (torch.arange(6) + 2).clamp(0, 5)
    assert torch.equal(out[1], image[1][:, :, rows][:, :, :, cols])
    assert torch.equal(random_shift(image, 0), image)
    drawn = random_shift(image, 1)
    assert drawn.shape == image.shape and all(torch.equal(drawn[b, 0] - image[b, 0], drawn[b, 1] - image[b, 1])
                                              for b in range(2))  # both frames of a window move together


@pytest.mark.parametrize("policy", ["dp", "act"])
def test_relative_actions_train_on_offsets_and_act_in_absolute_units(play_store, policy, monkeypatch):
    data = PolicyData([Source(play_store, 2)], obs_horizon=2 if policy == "dp" else 1, horizon=8)
    action_norm, state_norm = data.normalizers(relative=True)
    t = torch.arange(0, data.n_frames, 3)
    obs, act, _ = data.windows(t)
    offsets = data.action[act] - data.state[obs[:, -1]][:, None]
    batch = data.batch(t, action_norm, state_norm, relative=True)
    assert torch.allclose(action_norm.unnormalize(batch.action), offsets, atol=1e-6)
    every = data.actions(*data.windows(torch.arange(data.n_frames))[:2], relative=True).flatten(0, 1)
    assert torch.allclose(action_norm.low, every.min(0).values)
    assert torch.allclose(action_norm.high, every.max(0).values)
    model = {**PRESETS[f"tiny-{policy}"].model, "relative_actions": True}
    if policy == "act":
        model["temporal_ensemble"] = None
    net = make_policy(policy, model, action_norm, state_norm).eval()
    # A network whose normalised output is 0 predicts the middle of the offsets' range: the
    # policy must return that offset from each episode's current agent_pos.
    if policy == "dp":
        monkeypatch.setattr(net, "sample", lambda cond, generator=None: torch.zeros(len(cond), 8, 4))
    else:
        monkeypatch.setattr(net, "decode", lambda image, pos, z: torch.zeros(len(image), 8, 4))
    pos = data.state[obs].numpy()
    out = net.predict_action({"image": data.img[obs].numpy(), "agent_pos": pos})
    middle = ((action_norm.low + action_norm.high) / 2).numpy()
    assert np.allclose(out, pos[:, -1:, :] + middle, atol=1e-6)
    small = PolicyData([Source(play_store, 1)], 2, 8)
    small.state = small.state[:, :3]  # agent_pos of another size than the action
    with pytest.raises(ValueError, match="relative actions need actions and agent_pos of one size"):
        small.normalizers(relative=True)


@pytest.mark.slow
def test_diffusion_policy_overfits_and_acts(play_store):
    """The noise-prediction loss on 4 fixed windows falls by 2.5x in 300 steps."""
    torch.manual_seed(0)
    data = PolicyData([Source(play_store, 2)], obs_horizon=2, horizon=8)
    policy = make_policy("dp", TINY_DP, *data.normalizers())
    t = torch.arange(0, 8, 2)
    batch = data.batch(t, *data.normalizers())
    opt = torch.optim.Adam(policy.parameters(), lr=3e-3)
    losses = []
    for step in range(300):
        torch.manual_seed(step)
        loss, _ = policy(batch)
        opt.zero_grad()
        loss.backward()
        opt.step()
        losses.append(loss.item())
    assert np.mean(losses[-30:]) < 0.4 * np.mean(losses[:5]), (losses[:5], losses[-30:])
    policy.eval()
    obs = {"image": data.img[data.windows(torch.arange(3))[0]].numpy(),
           "agent_pos": data.state[data.windows(torch.arange(3))[0]].numpy()}
    act = policy.predict_action(obs)
    assert act.shape == (3, 4, 4)  # (B, Ta, A) of the tiny preset
    low, high = policy.action_norm.low.numpy(), policy.action_norm.high.numpy()
    assert (act >= low - 1e-5).all() and (act <= high + 1e-5).all()
    with pytest.raises(ValueError, match="observes 2 steps"):
        policy.predict_action({"image": obs["image"][:, :1], "agent_pos": obs["agent_pos"][:, :1]})
    with pytest.raises(ValueError, match="4-D agent_pos"):
        policy.predict_action({"image": obs["image"], "agent_pos": obs["agent_pos"][..., :3]})


def test_train_resume_save_load_and_checkpoints_kept(play_store, tmp_path, capsys):
    out = tmp_path / "pol"
    args = ["train", "policy", "--policy", "dp", "--preset", "tiny-dp", "--data", f"{play_store}:2",
            "--out", str(out), "--no-progress"]
    assert main([*args, "--steps", "10"]) == 0
    assert main([*args, "--steps", "20"]) == 0  # resumes
    assert sorted(p.name for p in (out / "checkpoints").iterdir()) == ["00000010", "00000020", "last"]
    config = json.loads((out / "config.json").read_text())
    assert config["policy"] == "dp" and config["episodes_used"] == {str(play_store): 2}
    a, b = load_policy(out), load_policy(out / "checkpoints" / "00000020")
    obs = {"image": np.zeros((2, 2, 64, 64, 3), np.uint8), "agent_pos": np.zeros((2, 2, 4), np.float32)}
    first = a.predict_action(obs, torch.Generator().manual_seed(0))
    np.testing.assert_array_equal(first, b.predict_action(obs, torch.Generator().manual_seed(0)))
    # executing fewer actions per query changes execution only: the same chunk, cut shorter
    short = load_policy(out, n_action_steps=2)
    assert short.cfg.n_action_steps == 2 and first.shape[1] == a.cfg.n_action_steps > 2
    np.testing.assert_array_equal(short.predict_action(obs, torch.Generator().manual_seed(0)), first[:, :2])
    with pytest.raises(ValueError, match="n_action_steps must be in"):
        load_policy(out, n_action_steps=99)
    capsys.readouterr()
    act = ["train", "policy", "--policy", "act", "--preset", "tiny-act", *args[6:]]
    assert main([*act, "--steps", "10"]) == 1  # another policy into the dp run
    assert "holds a run with a different config" in capsys.readouterr().err
    with pytest.raises(CheckpointError, match="not a policy checkpoint"):
        load_policy(tmp_path)
    assert main(["eval", "policy", "--checkpoint", str(out), "--episodes", "2", "--steps", "4", "--videos", "1",
                 "--action-steps", "1", "--out", str(tmp_path / "eval"), "--no-progress"]) == 0
    result = json.loads((tmp_path / "eval" / "results.json").read_text())
    assert len(result["episodes"]) == 2 and result["env"] == "pusht" and (tmp_path / "eval/episode_100000.mp4").exists()
    assert result["n_action_steps"] == 1
    assert "mean max IoU" in capsys.readouterr().out
    # the sampling noise is seeded: the same command, the same episodes (its video, frame for frame)
    assert main(["eval", "policy", "--checkpoint", str(out), "--episodes", "2", "--steps", "4", "--videos", "1",
                 "--action-steps", "1", "--out", str(tmp_path / "again"), "--no-progress"]) == 0
    assert (tmp_path / "again/episode_100000.mp4").read_bytes() == (tmp_path / "eval/episode_100000.mp4").read_bytes()

    assert main([*act, "--out", str(tmp_path / "act"), "--steps", "10"]) == 0
    policy = load_policy(tmp_path / "act")
    now = {"image": obs["image"][:, -1:], "agent_pos": obs["agent_pos"][:, -1:]}
    assert policy.kind == "act" and policy.predict_action(now).shape == (2, 1, 4)
    # execution-only fields: ACT without temporal ensembling executes 4 actions of each chunk
    chunked = load_policy(tmp_path / "act", n_action_steps=4, temporal_ensemble=None)
    np.testing.assert_array_equal(chunked.predict_action(now), policy.predict_chunk(now)[:, :4].numpy())
    assert load_policy(out, inference_steps=2).cfg.inference_steps == 2
    with pytest.raises(ValueError, match="temporal_ensemble cannot be changed when running a 'dp' policy"):
        load_policy(out, temporal_ensemble=None)
    with pytest.raises(ValueError, match="temporal ensembling queries every step"):
        load_policy(tmp_path / "act", n_action_steps=4)


def test_a_run_started_before_a_new_model_field_resumes(play_store, tmp_path, capsys):
    out = tmp_path / "act"
    args = ["train", "policy", "--policy", "act", "--preset", "tiny-act", "--data", f"{play_store}:2",
            "--out", str(out), "--no-progress"]
    assert main([*args, "--steps", "4"]) == 0
    config = json.loads((out / "config.json").read_text())
    del config["model"]["image_tokens"], config["model"]["keypoints"]  # as a run started before they existed
    del config["train"]["lr_decay"]  # (a training field too)
    (out / "config.json").write_text(json.dumps(config))
    assert main([*args, "--steps", "8"]) == 0  # resumes: their defaults are what the old run trained with
    assert sorted(p.name for p in (out / "checkpoints").iterdir())[-2:] == ["00000008", "last"]
    config["model"]["dim"] = 64  # a field that did change is still refused
    (out / "config.json").write_text(json.dumps(config))
    capsys.readouterr()
    assert main([*args, "--steps", "12"]) == 1
    assert "differs in model.dim" in capsys.readouterr().err


@pytest.mark.parametrize("preset", ["tiny-dp", "tiny-act"])
def test_the_same_command_trains_bit_identical_weights_resumed_or_not(play_store, tmp_path, preset):
    """Issue 25: two runs of one command give the same weights, and a run stopped and
    resumed gives the weights of one that was not (model, EMA and optimizer state)."""
    from safetensors.torch import load_file

    def run(out: Path, killed_after: int | None = None) -> dict[str, torch.Tensor]:
        args = ["train", "policy", "--policy", preset[5:], "--preset", preset, "--data", f"{play_store}:2",
                "--out", str(out), "--steps", "20", "--no-progress"]
        assert main(args) == 0
        if killed_after is not None:  # as if killed after that checkpoint: later ones never written
            for ckpt in (out / "checkpoints").iterdir():
                if ckpt.name.isdigit() and int(ckpt.name) > killed_after:
                    shutil.rmtree(ckpt)
            assert main(args) == 0
            assert f"resuming from {out / 'checkpoints' / f'{killed_after:08d}'}" in (out / "log.txt").read_text()
        state = out / "checkpoints" / "last" / "training_state"
        return {f"{f.stem}.{k}": v for f in sorted(state.glob("*.safetensors")) for k, v in load_file(f).items()}

    a, b, c = run(tmp_path / "a"), run(tmp_path / "b"), run(tmp_path / "c", killed_after=10)
    assert a.keys() == b.keys() == c.keys() and any(k.startswith("ema.") for k in a)
    for k in a:
        assert torch.equal(a[k], b[k]) and torch.equal(a[k], c[k]), k


class Scripted(torch.nn.Module):
    """A deterministic policy for runner tests: push both targets towards the centre."""

    obs_horizon = 2

    def reset(self) -> None:
        self.calls = 0

    def predict_action(self, obs: dict) -> np.ndarray:
        self.calls += 1
        pos = np.asarray(obs["agent_pos"])[:, -1]
        return np.stack([pos * 0.8, pos * 0.6], 1).astype(np.float32)  # (B, 2, A)


def test_batched_evaluation_equals_sequential_in_a_world_model():
    wm = tiny_world_model()
    batched = rollout(Scripted(), "world-model", [100000, 100001, 100002], steps=6, world_model=wm, progress=False)
    for i, seed in enumerate([100000, 100001, 100002]):
        alone = rollout(Scripted(), "world-model", [seed], steps=6, world_model=wm, progress=False)
        np.testing.assert_allclose(alone["iou"][0], batched["iou"][i], atol=1e-6)
    assert batched["iou"].shape == (3, 7)


def test_evaluation_in_mujoco_writes_results_and_videos(tmp_path):
    policy = Scripted()
    result = evaluate(policy, "pusht", episodes=3, seed=100000, steps=6, out=tmp_path, videos=2, progress=False)
    assert policy.calls == 3  # 2 actions per query, 6 steps
    written = json.loads((tmp_path / "results.json").read_text())
    assert [e["seed"] for e in written["episodes"]] == [100000, 100001, 100002]
    assert written["mean_max_iou"] == pytest.approx(np.mean([e["max_iou"] for e in written["episodes"]]))
    assert result["mean_max_iou"] == written["mean_max_iou"] and result["env_steps_per_s"] > 0
    assert set(written["success_beta_posterior"]) == {"mean", "low", "high"}
    assert sorted(p.name for p in tmp_path.glob("*.mp4")) == ["episode_100000.mp4", "episode_100001.mp4"]
    evaluate(policy, "pusht", episodes=1, seed=7, steps=2, out=tmp_path / "quiet", videos=0, progress=False)
    assert [p.name for p in (tmp_path / "quiet").iterdir()] and not list((tmp_path / "quiet").glob("*.mp4"))
    with pytest.raises(ValueError, match="--videos"):
        evaluate(policy, "pusht", episodes=1, seed=7, steps=2, videos=-1, progress=False)
    with pytest.raises(ValueError, match="--world-model"):
        evaluate(policy, "world-model", episodes=1, seed=0, steps=1, progress=False)
    with pytest.raises(ValueError, match="trained on 96x96"):
        evaluate(policy, "world-model", episodes=1, seed=0, steps=1, world_model=tiny_world_model(), image_size=96,
                 progress=False)


@pytest.mark.parametrize("k,n", [(0, 10), (3, 10), (10, 10), (17, 50), (1, 1)])
def test_statistics_match_scipy(k, n):
    ci = stats.binomtest(k, n).proportion_ci(confidence_level=0.95, method="exact")
    np.testing.assert_allclose(clopper_pearson(k, n), (ci.low, ci.high), atol=1e-9)
    post = stats.beta(1 + k, 1 + n - k)
    got = beta_posterior(k, n)
    assert got["mean"] == pytest.approx(post.mean())
    np.testing.assert_allclose((got["low"], got["high"]), post.interval(0.95), atol=1e-9)
    with pytest.raises(ValueError):
        clopper_pearson(n + 1, n)


@pytest.mark.parametrize("policy", ["tiny-dp", "tiny-act"])
def test_a_policys_initial_weights_come_from_its_seed_not_the_global_rng(play_store, policy):
    """Issue 26: the initial weights came from the global RNG, so two runs of one study
    trained different policies."""
    from iwsim.policies.train import PolicyTask

    cfg = PRESETS[policy]
    sources = [Source(play_store, None)]
    torch.manual_seed(1)
    a = PolicyTask(cfg, sources).module.state_dict()
    torch.manual_seed(2)
    state = torch.random.get_rng_state()
    b = PolicyTask(cfg, sources).module.state_dict()
    assert torch.equal(torch.random.get_rng_state(), state)  # the global RNG is left as it was
    for k in a:
        assert torch.equal(a[k], b[k]), k


def test_a_pile_sweeping_policy_records_its_task_and_is_evaluated_on_it(pile_model, tmp_path, capsys, monkeypatch):
    """Issue 45: a policy trained on ``collect --task pilesweep --policy expert`` episodes
    records its task, and ``eval policy`` evaluates it in that task's MuJoCo (its horizon,
    its score: the share of the pieces in the tray) or in a world model of it, and refuses
    another task's in one line."""
    out = tmp_path / "dp"
    assert main(["train", "policy", "--policy", "dp", "--preset", "tiny-dp", "--data", str(pile_model["store"]),
                 "--out", str(out), "--steps", "2", "--no-progress"]) == 0
    config = json.loads((out / "config.json").read_text())
    assert config["task"]["kind"] == "pilesweep" and config["task"]["name"] == "pilesweep"
    assert load_policy(out).task.name == "pilesweep"
    capsys.readouterr()
    assert main(["eval", "policy", "--checkpoint", str(out), "--episodes", "1", "--videos", "0",
                 "--out", str(tmp_path / "horizon"), "--no-progress"]) == 0
    result = json.loads((tmp_path / "horizon" / "results.json").read_text())
    assert (result["env"], result["task"], result["scorer"], result["steps"]) == (
        "pilesweep", "pilesweep", "share in tray", 200)  # the task's MuJoCo, its score and horizon
    assert "pilesweep: mean max share in tray" in capsys.readouterr().out
    # the per-episode score is the maximum of the per-step pixel score, under the task's names
    assert main(["eval", "policy", "--checkpoint", str(out), "--episodes", "2", "--steps", "4", "--videos", "1",
                 "--out", str(tmp_path / "sim"), "--no-progress"]) == 0
    result = json.loads((tmp_path / "sim" / "results.json").read_text())
    per_step = json.loads((tmp_path / "sim" / "score.json").read_text())["score_per_step"]
    assert [e["max_score"] for e in result["episodes"]] == pytest.approx(np.max(per_step, 1), abs=1e-4)
    assert result["mean_max_score"] == pytest.approx(np.mean(np.max(per_step, 1)), abs=1e-4)
    assert "mean_max_iou" not in result and not (tmp_path / "sim" / "iou.json").exists()
    assert (tmp_path / "sim" / "episode_100000.mp4").stat().st_size > 0
    # inside a world model of the task, from the same first frames
    assert main(["eval", "policy", "--checkpoint", str(out), "--env", "world-model", "--world-model",
                 str(pile_model["checkpoint"]), "--episodes", "2", "--steps", "3", "--videos", "0",
                 "--out", str(tmp_path / "wm"), "--no-progress"]) == 0
    in_model = json.loads((tmp_path / "wm" / "results.json").read_text())
    assert (in_model["env"], in_model["task"], in_model["world_model"]) == (
        "world-model", "pilesweep", str(pile_model["checkpoint"]))
    first = json.loads((tmp_path / "wm" / "score.json").read_text())["score_per_step"]
    assert np.array(first)[:, 0] == pytest.approx(np.array(per_step)[:, 0], abs=1e-4)
    # another task's MuJoCo or world model, or no world model to evaluate in: one line each
    monkeypatch.setattr(PileSweepTask, "checkpoint", None)  # a task without a shipped model
    tiny_world_model().save(tmp_path / "pusht-wm")
    capsys.readouterr()
    for extra, message in (
            (["--task", "pusht"], "trained on episodes of task 'pilesweep' (its checkpoint records it), not 'pusht'"),
            (["--env", "pusht"], "trained on episodes of task 'pilesweep'"),
            (["--env", "world-model"], "task 'pilesweep' has no shipped world model; pass --world-model"),
            (["--env", "world-model", "--world-model", str(tmp_path / "pusht-wm")],
             "is a world model of task 'pusht', not 'pilesweep'"),
            (["--task", "nowhere"], "unknown task 'nowhere'")):
        assert main(["eval", "policy", "--checkpoint", str(out), "--episodes", "1", "--steps", "2",
                     "--out", str(tmp_path / "bad"), *extra]) == 1
        err = capsys.readouterr().err.strip()
        assert err.startswith("iwsim: error:") and message in err and "\n" not in err, (extra, err)
    assert main(["collect", "--task", "pusht", "--policy", str(out), "--episodes", "1", "--steps", "2",
                 "--workers", "1", "--out", str(tmp_path / "bad" / "s.zarr")]) == 1
    assert "trained on episodes of task 'pilesweep'" in capsys.readouterr().err
    assert not (tmp_path / "bad").exists()
    # its learned episodes in its own task's MuJoCo: the store's layout is the scripted policies'
    assert main(["collect", "--task", "pilesweep", "--policy", str(out), "--episodes", "2", "--steps", "3",
                 "--workers", "1", "--out", str(tmp_path / "rollouts.zarr"), "--no-progress"]) == 0
    rollouts = EpisodeStore.open(tmp_path / "rollouts.zarr")
    assert rollouts.attrs["task"] == "pilesweep" and rollouts.episode(1)["pieces"].shape == (3, 30, 2)


def test_a_policy_learns_one_task(play_store, pile_model, tmp_path, capsys):
    assert main(["train", "policy", "--policy", "dp", "--preset", "tiny-dp", "--data",
                 f"{play_store}:1,{pile_model['store']}:1", "--out", str(tmp_path / "mixed"), "--steps", "1"]) == 1
    err = capsys.readouterr().err
    assert "mixes episodes of task 'pusht'" in err and "task 'pilesweep'" in err
    assert not (tmp_path / "mixed").exists()
