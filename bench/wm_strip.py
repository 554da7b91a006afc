"""A policy's episode inside a world model next to the same episode in MuJoCo: one row
each (world model, then MuJoCo), a frame every --every steps from the same seed, and each
row's max IoU. It shows what a world-model score measures, e.g. why the policy-eval study's
world model scores a learned policy far above MuJoCo.

    MUJOCO_GL=egl python bench/wm_strip.py \\
        --policy runs/experiments/policy_eval/runs/sim_expert-*/dp-100demos/checkpoints/00003000 \\
        --seed 100007 --steps 300 --every 30 --out bench/results/experiments/policy_eval/dp_strip.png
"""

from __future__ import annotations

import argparse
from pathlib import Path

from iwsim.core.errors import reporting_errors
from iwsim.core.resources import set_threads
from iwsim.policies.factory import load_policy
from iwsim.policies.scripted import ScriptedBatch
from iwsim.yardstick.studies import strip


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--policy", required=True, help="a policy checkpoint, or a scripted policy name (expert, play)")
    p.add_argument("--world-model", default="checkpoints/pusht-64")
    p.add_argument("--seed", type=int, default=100000)
    p.add_argument("--steps", type=int, default=200)
    p.add_argument("--every", type=int, default=20)
    p.add_argument("--out", type=Path, required=True)
    p.add_argument("--threads", type=int)
    args = p.parse_args(argv)
    set_threads(args.threads)
    path = Path(args.policy)
    make = (lambda: load_policy(path)) if path.exists() else (lambda: ScriptedBatch(args.policy))
    args.out.parent.mkdir(parents=True, exist_ok=True)
    wm, mujoco = strip(args.out, [args.world_model, None], args.seed, args.steps, args.every, make)
    print(f"{args.out}: max IoU {wm:.3f} in the world model, {mujoco:.3f} in MuJoCo (seed {args.seed}, "
          f"{args.steps} steps; rows: world model, MuJoCo; a frame every {args.every} steps)")
    return 0


if __name__ == "__main__":
    raise SystemExit(reporting_errors("wm_strip.py", main))
