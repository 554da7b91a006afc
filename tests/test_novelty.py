"""The trust signal (``iwsim.world_model.novelty``): a Gaussian of the training data's step
inputs, saved with the model and reported by every evaluation inside it."""

import json

import numpy as np
import pytest
import torch

from iwsim.cli import main
from iwsim.data.store import EpisodeStore, conditioning_key
from iwsim.eval.policy import disagreement, rollout
from iwsim.policies.scripted import ScriptedBatch
from iwsim.world_model import WorldModel
from iwsim.world_model.dynamics_data import fit_store_novelty
from iwsim.world_model.novelty import fit_novelty
from tests.test_dynamics import tiny_world_model


def test_a_gaussian_fit_scores_its_own_data_near_one_and_far_points_high():
    scale = torch.tensor([1.0, 2.0, 0.1, 5.0, 1.0, 1.0])
    x = torch.randn(5000, 6, generator=torch.Generator().manual_seed(0)) * scale + 3.0
    nov = fit_novelty(x)
    inside = nov(x[:, :4].view(-1, 1, 2, 2), x[:, 4:5], x[:, 5:6])
    assert inside.mean().item() == pytest.approx(1.0, abs=0.05)
    far = x[:10].clone()
    far[:, 2] += 2.0  # twenty standard deviations along the narrowest direction
    assert nov(far[:, :4].view(-1, 1, 2, 2), far[:, 4:5], far[:, 5:6]).min() > 10


def test_novelty_is_higher_for_actions_far_from_the_training_data(play_store, tmp_path, one_thread):
    wm = tiny_world_model()
    wm.novelty = fit_store_novelty(wm, play_store, progress=False)
    store = EpisodeStore.open(play_store)
    actions = np.asarray(store.array(conditioning_key(store.keys))[:], np.float32)
    frames = store.array("img")[:4]
    state = wm.reset_state(frames)
    seen = wm.novelty_of(state, actions[:4])
    far = np.tile([[0.21, -0.21, -0.21, 0.21]], (4, 1)).astype(np.float32)  # both pushers in far corners
    unseen = wm.novelty_of(state, far)
    assert seen.shape == unseen.shape == (4,)
    assert np.all(unseen > seen) and unseen.mean() > 3 * seen.mean()
    # the statistics travel with the checkpoint and every evaluation inside the model reports them
    loaded = WorldModel.load(wm.save(tmp_path / "wm", {}))
    np.testing.assert_allclose(loaded.novelty_of(loaded.reset_state(frames), far), unseen, rtol=1e-5)
    run = rollout(ScriptedBatch("still"), "world-model", [0, 1], 3, world_model=loaded, progress=False)
    assert run["novelty"].shape == (2, 3) and np.all(run["novelty"] > 0)
    assert rollout(ScriptedBatch("still"), "world-model", [0], 2, world_model=tiny_world_model(),
                   progress=False)["novelty"] is None  # no statistics, no signal


def test_export_model_fits_the_trust_signal_and_eval_prints_it(play_store, tmp_path, capsys, one_thread):
    src = tiny_world_model().save(tmp_path / "wm", {})
    out = tmp_path / "trusted"
    assert main(["export-model", "--run", str(src), "--out", str(out), "--novelty-data", str(play_store),
                 "--no-progress"]) == 0
    assert WorldModel.load(out).novelty is not None and WorldModel.load(src).novelty is None
    pol = tmp_path / "dp"
    assert main(["train", "policy", "--policy", "dp", "--preset", "tiny-dp", "--data", f"{play_store}:2",
                 "--steps", "1", "--out", str(pol), "--no-progress"]) == 0
    capsys.readouterr()
    partner = tiny_world_model(seed=1).save(tmp_path / "partner", {})
    assert main(["eval", "policy", "--checkpoint", str(pol), "--env", "world-model", "--world-model", str(out),
                 "--trust-model", str(partner), "--episodes", "2", "--steps", "3", "--videos", "0",
                 "--out", str(tmp_path / "ev"), "--no-progress"]) == 0
    printed = capsys.readouterr().out
    assert "novelty:" in printed and "trust: the two world models' scores differ" in printed
    result = json.loads((tmp_path / "ev" / "results.json").read_text())
    assert len(result["disagreement"]["per_episode"]) == 2 and len(result["novelty"]["per_episode"]) == 2
    assert main(["eval", "policy", "--checkpoint", str(pol), "--env", "pusht", "--trust-model", str(partner),
                 "--episodes", "1", "--steps", "2", "--videos", "0", "--out", str(tmp_path / "ev2")]) == 1
    assert "--trust-model applies to --env world-model" in capsys.readouterr().err


def test_disagreement_is_the_score_gap_per_episode():
    d = disagreement(np.array([0.9, 0.5, 0.2]), np.array([0.4, 0.55, 0.2]))
    assert d["per_episode"] == [0.5, 0.05, 0.0] and d["mean"] == pytest.approx(0.55 / 3)
    assert d["above_warn"] == pytest.approx(1 / 3)
