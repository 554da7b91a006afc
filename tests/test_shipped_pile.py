"""The shipped pile-sweeping checkpoint loads, is small, is the task's default, still predicts
MuJoCo as well as its metrics.json says, and its recipe rebuilds it (a file apart from the
T-push model's, so that `make test`'s two workers run the two recipes side by side)."""

import json
from pathlib import Path

import pytest

from iwsim.eval.rollout import against_mujoco
from iwsim.world_model import WorldModel
from tests.conftest import run_recipe

PILE = Path(__file__).resolve().parents[1] / "checkpoints" / "pilesweep-64"


def test_the_shipped_pile_model_is_complete_small_and_the_tasks_default():
    from iwsim.envs.registry import get_task

    files = {p.name for p in PILE.iterdir()}
    assert {"model.safetensors", "config.json", "metrics.json", "README.md", "recipe.sh"} <= files
    assert sum(p.stat().st_size for p in PILE.iterdir()) <= 50 * 2**20
    assert get_task("pilesweep").checkpoint == "checkpoints/pilesweep-64"
    wm = WorldModel.load(PILE)
    assert wm.image_size == 64 and wm.task.name == "pilesweep"


@pytest.mark.parametrize("i", range(2))
def test_the_shipped_pile_model_reaches_its_recorded_psnr_against_mujoco(i):
    recorded = json.loads((PILE / "metrics.json").read_text())["mujoco_rollout"]
    seed = recorded["seeds"][i]
    result = against_mujoco(WorldModel.load(PILE), seed, recorded["steps"], recorded["policy"],
                            noise_seed=recorded["noise_seed"])
    assert abs(float(result.psnr.mean()) - recorded["psnr_per_seed"][i]) <= recorded["tolerance_db"], seed


@pytest.mark.slow
def test_the_pile_recipe_rebuilds_a_model_and_resumes(tmp_path):
    """checkpoints/pilesweep-64/recipe.sh, shrunk to seconds: every step runs, and a second
    run resumes everything (no episode collected twice, no training restarted)."""
    from iwsim.data.store import EpisodeStore

    first = run_recipe(PILE / "recipe.sh", tmp_path)
    assert first.returncode == 0, first.stderr[-2000:]
    model = WorldModel.load(tmp_path / "out" / "pilesweep-64")
    assert model.image_size == 64 and model.task.name == "pilesweep" and model.cfg.dynamics.context == 10
    assert (model.cfg.rest_threshold, model.cfg.delta_deadband) == (0.05, 0.06)
    episodes = EpisodeStore.open(tmp_path / "data" / "pile_contact.zarr").n_episodes
    again = run_recipe(PILE / "recipe.sh", tmp_path)
    assert again.returncode == 0, again.stderr[-2000:]
    assert again.stderr.count("resuming from") == 4  # the codec, the dynamics, the decoder, the wider window
    assert EpisodeStore.open(tmp_path / "data" / "pile_contact.zarr").n_episodes == episodes
