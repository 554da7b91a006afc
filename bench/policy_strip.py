"""Frame strips of a policy's episodes in MuJoCo (one row per seed, a frame every 25 steps):
what the campaign's diagnostics in bench/results/policies/runs.md show.

    MUJOCO_GL=egl OMP_NUM_THREADS=1 python bench/policy_strip.py runs/pol/dp-turned25/checkpoints/00004000 \
        --start goal-turned --out outputs/diag_turned.png
"""

from __future__ import annotations

import argparse

import numpy as np
import torch
from PIL import Image

from iwsim.core.errors import reporting_errors
from iwsim.eval.policy import rollout
from iwsim.policies.factory import load_policy

SEEDS = (200001, 200002, 200005, 200007, 200013, 200003)  # validation seeds, failures of dp-base among them


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("checkpoint")
    p.add_argument("--start", default="random", help="MuJoCo's initial states (iwsim.envs.pusht.sim.STARTS)")
    p.add_argument("--steps", type=int, default=300)
    p.add_argument("--every", type=int, default=25)
    p.add_argument("--out", required=True)
    args = p.parse_args()
    torch.manual_seed(0)  # the policy's sampling noise
    r = rollout(load_policy(args.checkpoint), "pusht", list(SEEDS), args.steps, record=len(SEEDS), progress=False,
                start=args.start)
    print("max IoU per seed:", dict(zip(SEEDS, r["iou"].max(1).round(2).tolist())))
    rows = [np.concatenate(list(r["frames"][i, ::args.every]), 1) for i in range(len(SEEDS))]
    image = Image.fromarray(np.concatenate(rows, 0))
    image.resize((image.width * 2, image.height * 2), Image.NEAREST).save(args.out)


if __name__ == "__main__":
    raise SystemExit(reporting_errors("policy_strip.py", main))
