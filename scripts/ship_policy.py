"""Ship a trained policy as a reference checkpoint: its weights in half precision (the
normalisers and any other small tensors stay float32), its config with where it came from,
and the scores of the shipped file itself, closed loop in MuJoCo on the test seeds, in
``metrics.json``. The README beside it is written by hand.

    python scripts/ship_policy.py --checkpoint runs/pol/dp-wide/checkpoints/00004000 \\
        --out checkpoints/dp-pusht-64 --command "python bench/policy_runs.py ..." --train-minutes 25

``iwsim eval policy --checkpoint checkpoints/dp-pusht-64 --out outputs/dp`` then scores it
again (in MuJoCo or, with ``--env world-model``, in the shipped world model).
"""

from __future__ import annotations

import argparse
import sys
import tempfile
from pathlib import Path

import torch

from iwsim.core.checkpoint import load_model_dir, save_model_dir
from iwsim.core.errors import reporting_errors
from iwsim.envs.registry import DEFAULT_TASK
from iwsim.eval.policy import rollout, summarize
from iwsim.eval.policy_runs import TEST_SEED  # bench/policy_runs.py's and iwsim eval policy's
from iwsim.policies.factory import KIND, load_policy

SMALL = 4096  # tensors with fewer elements stay float32


def half(tensors: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
    """Large float32 tensors as float16 (the weights); the rest as they are."""
    return {k: v.half() if v.dtype == torch.float32 and v.numel() >= SMALL else v for k, v in tensors.items()}


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--checkpoint", required=True, help="a policy checkpoint directory (one step of a run)")
    p.add_argument("--out", required=True, help="the reference checkpoint to write (e.g. checkpoints/dp-pusht-64)")
    p.add_argument("--command", required=True, help="the command that trained it (recorded in metrics.json)")
    p.add_argument("--train-minutes", type=float, required=True, help="its training time (recorded)")
    p.add_argument("--episodes", type=int, default=50)
    p.add_argument("--steps", type=int, default=DEFAULT_TASK.horizon)
    p.add_argument("--force", action="store_true", help="replace an existing --out")
    args = p.parse_args(argv)

    config, tensors = load_model_dir(args.checkpoint, KIND)
    config = {**config, "shipped_from": str(args.checkpoint)}
    tensors = half(tensors)
    with tempfile.TemporaryDirectory() as tmp:  # score the file that ships, not the float32 one
        staged = save_model_dir(Path(tmp) / "policy", tensors, config)
        policy = load_policy(staged)
        seeds = list(range(TEST_SEED, TEST_SEED + args.episodes))
        torch.manual_seed(0)  # the policy's sampling noise, as bench/policy_runs.py
        result = rollout(policy, DEFAULT_TASK.kind, seeds, args.steps, image_size=policy.image_size,
                         progress=sys.stderr.isatty())
    scores = summarize(result["iou"].max(1), seeds, result["success_score"])
    metrics = {"mujoco_test": {**scores, "episodes": args.episodes, "steps": args.steps, "first_seed": TEST_SEED},
               "train_command": args.command, "train_minutes_one_thread": args.train_minutes}
    save_model_dir(Path(args.out), tensors, config, force=args.force, json_files={"metrics.json": metrics})
    size = sum(f.stat().st_size for f in Path(args.out).iterdir()) / 2**20
    print(f"{args.out}: {size:.1f} MB; {args.episodes} test seeds x {args.steps} steps: mean max IoU "
          f"{scores['mean_max_iou']:.3f}, success {scores['success_rate']:.2f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(reporting_errors("ship_policy.py", main))
