"""The shipped checkpoint loads, is small, and still predicts MuJoCo as well as its
metrics.json says (so the file can never silently rot)."""

import json
from pathlib import Path

import pytest

from iwsim.eval.rollout import against_mujoco
from iwsim.world_model import WorldModel

SHIPPED = Path(__file__).resolve().parents[1] / "checkpoints" / "pusht-64"


def test_shipped_checkpoint_is_complete_and_small():
    files = {p.name for p in SHIPPED.iterdir()}
    assert {"model.safetensors", "config.json", "metrics.json", "README.md"} <= files
    assert sum(p.stat().st_size for p in SHIPPED.iterdir()) <= 50 * 2**20
    readme = (SHIPPED / "README.md").read_text()
    assert "iwsim collect" in readme and "iwsim train ae" in readme and "iwsim train dynamics" in readme


@pytest.mark.parametrize("i", range(4))
def test_shipped_checkpoint_reaches_its_recorded_psnr_against_mujoco(i):
    recorded = json.loads((SHIPPED / "metrics.json").read_text())["mujoco_rollout"]
    wm = WorldModel.load(SHIPPED)
    seed = recorded["seeds"][i]
    result = against_mujoco(wm, seed, recorded["steps"], recorded["policy"], noise_seed=recorded["noise_seed"])
    psnr = float(result.psnr.mean())
    assert abs(psnr - recorded["psnr_per_seed"][i]) <= recorded["tolerance_db"], (seed, psnr)
