"""The shipped T-push checkpoint loads, is small, and still predicts MuJoCo as well as its
metrics.json says (so the file can never silently rot); the pile model's: test_shipped_pile.py."""

import json
from pathlib import Path

import gymnasium as gym
import numpy as np
import pytest

from iwsim.eval.rollout import against_mujoco
from iwsim.world_model import WorldModel
from tests.conftest import run_recipe

SHIPPED = Path(__file__).resolve().parents[1] / "checkpoints" / "pusht-64"


def test_shipped_checkpoint_is_complete_and_small():
    files = {p.name for p in SHIPPED.iterdir()}
    assert {"model.safetensors", "config.json", "metrics.json", "README.md"} <= files
    assert sum(p.stat().st_size for p in SHIPPED.iterdir()) <= 50 * 2**20
    readme = (SHIPPED / "README.md").read_text()
    assert "iwsim collect" in readme and "iwsim train ae" in readme and "iwsim train dynamics" in readme


def test_the_shipped_checkpoint_is_found_from_any_working_directory(tmp_path, monkeypatch):
    from iwsim.core.checkpoint import CheckpointError, resolve_checkpoint

    monkeypatch.chdir(tmp_path)
    assert resolve_checkpoint("checkpoints/pusht-64") == SHIPPED
    assert WorldModel.load("checkpoints/pusht-64").image_size == 64
    (tmp_path / "checkpoints" / "pusht-64").mkdir(parents=True)  # one here comes first
    with pytest.raises(CheckpointError, match="neither a checkpoint directory"):
        resolve_checkpoint("checkpoints/pusht-64")
    with pytest.raises(CheckpointError, match=f"a relative path: looked for in {tmp_path}"):
        resolve_checkpoint("checkpoints/missing")


@pytest.mark.parametrize("i", range(4))
def test_shipped_checkpoint_reaches_its_recorded_psnr_against_mujoco(i):
    recorded = json.loads((SHIPPED / "metrics.json").read_text())["mujoco_rollout"]
    wm = WorldModel.load(SHIPPED)
    seed = recorded["seeds"][i]
    result = against_mujoco(wm, seed, recorded["steps"], recorded["policy"], noise_seed=recorded["noise_seed"])
    psnr = float(result.psnr.mean())
    assert abs(psnr - recorded["psnr_per_seed"][i]) <= recorded["tolerance_db"], (seed, psnr)


def test_shipped_rollout_holds_its_recorded_values():
    """A short rollout of the shipped checkpoint gives the values recorded when it was
    shipped (per-frame mean intensity of 6 steps from seed 100000's MuJoCo frame; the
    encoder's latent L1 norm), so a refactor that changes what it computes fails here."""
    wm = WorldModel.load(SHIPPED)
    obs, _ = gym.make("iwsim/BimanualPushT-v0").reset(seed=100000)
    ramp = np.linspace(0, 0.04, 6, dtype=np.float32)[None, :, None] * np.array([1, 1, -1, 1], np.float32)
    frames = wm.rollout(obs["pixels"][None], obs["agent_pos"][None, None] + ramp, seed=0)
    recorded = [205.9185, 205.958, 205.9888, 206.0144, 206.0174, 206.0181]
    np.testing.assert_allclose(frames.reshape(6, -1).mean(1), recorded, atol=0.02)
    assert abs(float(wm.encode(obs["pixels"][None]).abs().sum()) - 424.4131) < 0.01


@pytest.mark.slow
def test_the_recipe_rebuilds_a_model_and_resumes(tmp_path):
    """checkpoints/pusht-64/recipe.sh, shrunk to seconds: every step of the chain runs, and
    a second run resumes everything (no episode collected twice, no training restarted)."""
    from iwsim.data.store import EpisodeStore

    first = run_recipe(SHIPPED / "recipe.sh", tmp_path)
    assert first.returncode == 0, first.stderr[-2000:]
    model = WorldModel.load(tmp_path / "out" / "pusht-64")
    assert model.cfg.rest_threshold == 0.05 and model.image_size == 64 and model.cfg.dynamics.context == 10
    episodes = EpisodeStore.open(tmp_path / "data" / "contact.zarr").n_episodes
    again = run_recipe(SHIPPED / "recipe.sh", tmp_path)
    assert again.returncode == 0, again.stderr[-2000:]
    assert again.stderr.count("resuming from") == 7  # the codec, the dynamics, the decoder, four fine-tunes
    assert EpisodeStore.open(tmp_path / "data" / "contact.zarr").n_episodes == episodes
