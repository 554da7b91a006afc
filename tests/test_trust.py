"""Per-episode trust signals (``iwsim.eval.trust``): the frames' plausibility, the spread of
the model's samples, the error predictor and the calibration, and every evaluation inside
a world model reporting them."""

import json

import numpy as np
import pytest

from iwsim.cli import main
from iwsim.core.errors import InputError
from iwsim.envs.pusht.pixels import block_fraction
from iwsim.envs.pusht.sim import BimanualPushTEnv
from iwsim.envs.registry import get_task
from iwsim.envs.task import Task
from iwsim.eval import trust
from iwsim.eval.policy import rollout, sampled_rollout
from iwsim.eval.trust import SAMPLE_OFFSET, ErrorPredictor, calibration, episode_signals
from iwsim.policies.scripted import ScriptedBatch
from tests.test_dynamics import tiny_world_model


def test_pusht_frames_of_mujoco_are_plausible_and_a_bent_block_is_not():
    env = BimanualPushTEnv(image_size=64)
    obs, _ = env.reset(seed=3)
    frame = obs["pixels"]
    env.close()
    task = get_task("pusht")
    blank = np.full_like(frame, frame[0, 0])  # the table alone: no block to fit
    bent = frame.copy()
    block = np.argwhere(block_fraction(frame) > 0.5)
    half = block[block[:, 1] < np.median(block[:, 1])]
    bent[half[:, 0], half[:, 1]] = frame[0, 0]  # the block's left half gone: no T fits what is left
    fit = task.plausibility(np.stack([frame, bent, blank]))
    assert fit.shape == (3,) and fit[0] > 0.9 and fit[1] < fit[0] - 0.1 and fit[2] == 0
    assert Task("generic", (0.0,), (1.0,)).plausibility(frame[None]) is None  # a task that cannot tell


def test_signals_summaries_and_the_error_ranking():
    plaus = np.array([[0.95, 0.9, 0.95], [0.5, 0.9, 0.7], [0.9, 0.9, 0.9]])
    s = episode_signals(plaus, [np.array([0.9, 0.2, 0.5]), np.array([0.8, 0.6, 0.5]), np.array([0.85, 0.3, 0.45])])
    np.testing.assert_allclose(s["implausibility"], [1 - 2.8 / 3, 1 - 2.1 / 3, 0.1])
    np.testing.assert_allclose(s["implausibility_worst"], [0.1, 0.5, 0.1])
    np.testing.assert_allclose(s["sample_spread"], [0.1, 0.4, 0.05])
    assert episode_signals(None, [np.array([0.5])]) == {}  # one sample: no spread
    out = trust.summary(s)
    assert out["sample_spread"]["above_warn"] == pytest.approx(1 / 3) and out["implausibility"]["per_episode"][1] == 0.3
    rho = trust.error_ranking(s, np.array([0.05, 0.5, 0.01]))
    assert rho["implausibility"] == pytest.approx(0.5) and rho["sample_spread"] == pytest.approx(1.0)
    assert trust.spearman(np.ones(5), np.arange(5)) is None  # a constant signal ranks nothing


def test_the_command_lead_is_the_larger_pushers_distance_in_half_views():
    task = get_task("pusht")  # its points: (lx, ly) and (rx, ry)
    pos = np.zeros((2, 3, 4))
    cmd = pos.copy()
    cmd[0, 1, :2] = (0.03, 0.04)  # the left pusher's setpoint 50 mm ahead
    cmd[1, 2, 2:] = (0.0, -0.1)  # the right one's 100 mm
    lead = task.command_lead(cmd, pos)
    np.testing.assert_allclose(lead, np.array([[0, 0.05, 0], [0, 0, 0.1]]) / task.view_half)
    assert Task("generic", (0.0,) * 4, (1.0,) * 4).command_lead(cmd, pos) is None  # no positions declared
    assert task.command_lead(cmd, pos[..., :2]) is None  # a state in another space
    s = episode_signals(None, None, np.linspace(0, 1, 101)[None].repeat(2, 0))
    np.testing.assert_allclose(s["command_lead"], [0.9, 0.9])  # the episode's 90th percentile


def test_the_error_predictor_recovers_a_linear_error_and_the_calibration_flags_it():
    rng = np.random.default_rng(0)
    x = {"a": rng.normal(size=400), "b": rng.normal(size=400), "noise": rng.normal(size=400)}
    err = 0.3 + 0.1 * x["a"] - 0.05 * x["b"]
    p = ErrorPredictor.fit(x, err, ridge=1e-6)
    w = p.weights()
    assert w["a"] == pytest.approx(0.1 * x["a"].std(), rel=1e-3) and abs(w["noise"]) < 1e-4
    np.testing.assert_allclose(p.predict(x), err, atol=1e-6)
    rows = calibration(p.predict(x), err, (0.1, 0.5, 1.0))
    assert rows[0]["flagged_error"] == pytest.approx(np.sort(err)[-40:].mean())
    assert rows[0]["flagged_error"] > rows[1]["flagged_error"] > rows[0]["rest_error"]
    assert rows[2]["flagged_error"] == pytest.approx(err.mean()) and np.isnan(rows[2]["rest_error"])


def test_a_world_model_rollout_measures_plausibility_and_other_samples(one_thread):
    wm = tiny_world_model()
    run = rollout(ScriptedBatch("still"), "world-model", [0, 1], 5, world_model=wm, progress=False,
                  plausibility_every=2)
    assert run["plausibility"].shape == (2, 3) and np.all((run["plausibility"] >= 0) & (run["plausibility"] <= 1))
    lead = run["command_lead"]  # the still pushers' commands are where they are
    assert lead.shape == (2, 5) and np.all(lead < 1e-3)
    assert rollout(ScriptedBatch("still"), "pusht", [0], 2, progress=False)["command_lead"] is None  # MuJoCo's: none
    assert rollout(ScriptedBatch("still"), "world-model", [0], 2, world_model=wm, progress=False)[
        "plausibility"] is None  # not asked
    def frames(offset: int) -> np.ndarray:
        return rollout(ScriptedBatch("play"), "world-model", [0, 1], 4, world_model=wm, progress=False, record=2,
                       noise_offset=offset)["frames"]

    first = frames(0)
    np.testing.assert_array_equal(first, frames(0))  # the same noise: the same episodes
    assert not np.array_equal(first[:, 1:], frames(SAMPLE_OFFSET)[:, 1:])  # another sample of them
    run, maxes = sampled_rollout(ScriptedBatch("play"), "world-model", [0, 1], 4, samples=3, world_model=wm,
                                 progress=False)
    assert maxes is not None and len(maxes) == 3 and run["plausibility"] is not None
    np.testing.assert_array_equal(maxes[0], run["iou"].max(1))
    with pytest.raises(InputError, match="--samples applies to --env world-model"):
        sampled_rollout(ScriptedBatch("play"), "pusht", [0], 2, samples=2)
    with pytest.raises(InputError, match="--samples must be >= 1"):
        sampled_rollout(ScriptedBatch("play"), "world-model", [0], 2, samples=0, world_model=wm)


def test_eval_policy_reports_the_trust_signals(play_store, tmp_path, capsys, one_thread):
    src = tiny_world_model().save(tmp_path / "wm", {})
    pol = tmp_path / "dp"
    assert main(["train", "policy", "--policy", "dp", "--preset", "tiny-dp", "--data", f"{play_store}:2",
                 "--steps", "1", "--out", str(pol), "--no-progress"]) == 0
    capsys.readouterr()
    assert main(["eval", "policy", "--checkpoint", str(pol), "--env", "world-model", "--world-model", str(src),
                 "--samples", "2", "--episodes", "2", "--steps", "10", "--videos", "0",
                 "--out", str(tmp_path / "ev"), "--no-progress"]) == 0
    printed = capsys.readouterr().out
    assert "plausibility:" in printed and "samples:" in printed and "command lead:" in printed
    result = json.loads((tmp_path / "ev" / "results.json").read_text())
    assert len(result["implausibility"]["per_episode"]) == 2 and len(result["sample_spread"]["per_episode"]) == 2
    assert len(result["command_lead"]["per_episode"]) == 2
    assert main(["eval", "policy", "--checkpoint", str(pol), "--env", "pusht", "--samples", "2",
                 "--episodes", "1", "--steps", "2", "--videos", "0", "--out", str(tmp_path / "ev2")]) == 1
    assert "--samples applies to --env world-model" in capsys.readouterr().err
