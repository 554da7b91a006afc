"""The reference policies load, are small, say what they score, and run closed loop in
MuJoCo and inside the shipped world model through ``iwsim eval policy`` (one command)."""

import json
from pathlib import Path

import pytest

from iwsim.cli import main
from iwsim.policies.factory import load_policy
from tests.conftest import imports_dynamo

CHECKPOINTS = Path(__file__).resolve().parents[1] / "checkpoints"
SHIPPED = ("dp-pusht-64", "act-pusht-64")


@pytest.mark.parametrize("name", SHIPPED)
def test_a_reference_policy_is_complete_small_and_says_what_it_scores(name):
    path = CHECKPOINTS / name
    assert {"model.safetensors", "config.json", "metrics.json", "README.md"} <= {p.name for p in path.iterdir()}
    assert sum(p.stat().st_size for p in path.iterdir()) <= 12 * 2**20
    test = json.loads((path / "metrics.json").read_text())["mujoco_test"]
    assert (test["episodes"], test["steps"], test["first_seed"]) == (50, 600, 100000)
    assert 0 <= test["mean_max_iou"] <= 1 and 0 <= test["success_rate"] <= 1
    readme = (path / "README.md").read_text()
    assert f"{test['mean_max_iou']:.3f}" in readme and f"iwsim eval policy --checkpoint checkpoints/{name}" in readme
    policy = load_policy(path)
    assert policy.image_size == 64


@pytest.mark.parametrize("name", SHIPPED)
@pytest.mark.parametrize("env", ["pusht", "world-model"])
def test_a_reference_policy_runs_closed_loop_in_one_command(name, env, tmp_path, monkeypatch, one_thread):
    monkeypatch.chdir(tmp_path)  # the shipped checkpoints are found from any working directory
    out = tmp_path / "eval"
    assert main(["eval", "policy", "--checkpoint", f"checkpoints/{name}", "--env", env, "--episodes", "2",
                 "--steps", "12", "--videos", "1", "--out", str(out), "--no-progress"]) == 0
    result = json.loads((out / "results.json").read_text())
    assert len(result["episodes"]) == 2 and 0 <= result["mean_max_iou"] <= 1
    assert (out / "episode_100000.mp4").stat().st_size > 0


def test_loading_diffusion_policy_leaves_torch_dynamo_unimported():
    """Loading first builds a policy on the meta device to count its weights; arithmetic
    there (its normalisers, its noise schedule) ran through torch's reference ops, whose
    first use imports torch._dynamo: 2 s more for every process that loaded a policy.
    (ACT's initialisation still computes on the meta device, and still pays it.)"""
    assert not imports_dynamo("from iwsim.policies.factory import load_policy; load_policy(sys.argv[1])",
                              CHECKPOINTS / "dp-pusht-64")
