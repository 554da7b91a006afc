"""A policy run's checkpoints and their closed-loop scores in MuJoCo, as the policy
campaign's scripts keep them (``bench/policy_runs.py``, ``bench/policy_scaling.py``,
``bench/bench_policies.py`` and the probes of ``bench/probes/``): the validation and test
seeds, where a checkpoint's evaluation is cached, a run's training minutes at each logged
step (checkpoints are chosen among those saved within a training budget), and scoring a
run's checkpoints with weights loaded into one policy module."""

from __future__ import annotations

import json
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import torch

from iwsim.core.checkpoint import load_tensors
from iwsim.eval.policy import rollout, summarize

VAL_SEED, TEST_SEED = 200_000, 100_000  # validation seeds choose a checkpoint; test seeds score the chosen one


def eval_path(run: Path, split: str, episodes: int, eval_steps: int, step: int, tag: str = "") -> Path:
    """Where a checkpoint's evaluation is cached: one file per checkpoint, seeds and execution."""
    return run / "eval" / f"{split}{episodes}x{eval_steps}{tag}" / f"{step:08d}.json"


def training_minutes(run: Path) -> dict[int, float]:
    """Minutes of training at each logged step of a run (its ``metrics.jsonl``)."""
    rows = [json.loads(line) for line in (run / "metrics.jsonl").read_text().splitlines() if line.strip()]
    return {r["step"]: r["elapsed_s"] / 60 for r in rows if "elapsed_s" in r}


def score_checkpoints(policy: Any, run: Path, steps: list[int], episodes: int = 20,
                      out: str = "probe_scores.jsonl", seeds: list[int] | None = None,
                      eval_steps: int = 600) -> Iterator[tuple[int, dict[str, Any]]]:
    """Load each checkpoint's weights (``run/checkpoints/<step>``, ``steps`` of them) into
    ``policy`` (a policy that is an ``nn.Module``, run at 64 px) and score it x
    ``eval_steps`` steps in T-push's MuJoCo on ``seeds`` (default: the validation seeds,
    ``episodes`` of them); each score is appended to ``run / out`` as one JSON line and
    yielded as (step, {mean_max_iou, success_rate, seconds}) once it is done, for the caller
    to report while the next one runs."""
    seeds = list(range(VAL_SEED, VAL_SEED + episodes)) if seeds is None else seeds
    for step in steps:
        policy.load_state_dict(load_tensors(run / "checkpoints" / f"{step:08d}" / "model.safetensors"))
        policy.eval()
        policy.image_size = 64
        torch.manual_seed(0)  # the policy's sampling noise
        t0 = time.time()
        r = rollout(policy, "pusht", seeds, eval_steps, progress=False)
        res = summarize(r["iou"].max(1), seeds, r["success_score"])
        seconds = time.time() - t0
        with open(run / out, "a") as f:
            f.write(json.dumps({"step": step, "mean_max_iou": res["mean_max_iou"], "success": res["success_rate"]})
                    + "\n")
        yield step, {"mean_max_iou": res["mean_max_iou"], "success_rate": res["success_rate"],
                     "seconds": seconds}
