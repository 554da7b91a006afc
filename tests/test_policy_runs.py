"""A policy run's checkpoint scores (``iwsim.eval.policy_runs``, shared by the policy
campaign's scripts and probes): where an evaluation is cached, the training minutes of a
run's steps, and a run's checkpoints scored one by one with their weights loaded into one
policy module."""

import json
from pathlib import Path

import pytest

from iwsim.cli import main
from iwsim.eval.policy_runs import TEST_SEED, VAL_SEED, eval_path, score_checkpoints, training_minutes
from iwsim.policies.factory import load_policy


def test_eval_path_is_one_file_per_checkpoint_seeds_and_execution(tmp_path):
    run = tmp_path / "runs" / "dp-x"
    assert eval_path(run, "val", 20, 600, 4000) == run / "eval" / "val20x600" / "00004000.json"
    assert eval_path(run, "test", 50, 600, 4000, "-n_action_steps4").parent.name == "test50x600-n_action_steps4"
    assert VAL_SEED != TEST_SEED


def test_training_minutes_are_read_per_logged_step(tmp_path):
    rows = [{"step": 1, "loss": 0.5}, {"step": 2, "elapsed_s": 30.0}, {"step": 4, "elapsed_s": 90.0}]
    (tmp_path / "metrics.jsonl").write_text("\n".join(json.dumps(r) for r in rows) + "\n\n")
    assert training_minutes(tmp_path) == {2: 0.5, 4: 1.5}


def test_a_runs_checkpoints_are_scored_one_by_one(play_store: Path, tmp_path: Path, one_thread) -> None:
    run = tmp_path / "pol"
    assert main(["train", "policy", "--policy", "dp", "--preset", "tiny-dp", "--data", f"{play_store}:2",
                 "--steps", "2", "--out", str(run), "--no-progress"]) == 0
    assert 2 in training_minutes(run)
    policy = load_policy(run / "checkpoints" / "00000002")
    scores = score_checkpoints(policy, run, [2, 2], seeds=[VAL_SEED + 3], eval_steps=3, out="s.jsonl")
    step, first = next(scores)  # each checkpoint is scored as it is asked for, its line written first
    assert step == 2 and 0 <= first["mean_max_iou"] <= 1 and first["success_rate"] in (0.0, 1.0)
    assert first["seconds"] > 0 and len((run / "s.jsonl").read_text().splitlines()) == 1
    step, again = next(scores)
    assert {k: again[k] for k in ("mean_max_iou", "success_rate")} == {
        k: first[k] for k in ("mean_max_iou", "success_rate")}  # the sampling noise is seeded: the same score
    lines = [json.loads(line) for line in (run / "s.jsonl").read_text().splitlines()]
    assert lines == [{"step": 2, "mean_max_iou": first["mean_max_iou"], "success": first["success_rate"]}] * 2
    with pytest.raises(StopIteration):
        next(scores)
