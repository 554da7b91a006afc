"""What the issue-25 probes share: scoring their own checkpoints closed-loop in MuJoCo."""

import json
import time
from pathlib import Path

import torch

from iwsim.checkpoint import load_tensors
from iwsim.eval.policy import rollout, summarize


def score_checkpoints(policy: torch.nn.Module, run: Path, name: str, steps: list[int], episodes: int = 20,
                      out: str = "probe_scores.jsonl", seeds: list[int] | None = None) -> None:
    """Load each checkpoint's weights into ``policy`` and score it x 600 steps on ``seeds``
    (default: the validation seeds 200000 + i, ``episodes`` of them); one line each is
    printed and appended to ``run / out``."""
    seeds = list(range(200000, 200000 + episodes)) if seeds is None else seeds
    for step in steps:
        policy.load_state_dict(load_tensors(run / "checkpoints" / f"{step:08d}" / "model.safetensors"))
        policy.eval()
        policy.image_size = 64
        torch.manual_seed(0)  # the policy's sampling noise
        t0 = time.time()
        r = rollout(policy, "pusht", seeds, 600, progress=False)
        res = summarize(r["iou"].max(1), seeds, r["success_score"])
        print(f"{name} @{step}: mean max IoU {res['mean_max_iou']:.3f} success {res['success_rate']:.2f} "
              f"({time.time() - t0:.0f}s)", flush=True)
        with open(run / out, "a") as f:
            f.write(json.dumps({"step": step, "mean_max_iou": res["mean_max_iou"], "success": res["success_rate"]})
                    + "\n")
