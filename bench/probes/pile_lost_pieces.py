"""Issue 45: where does a pile model's credit for a policy come from? The pieces the pixel
scorer sees in the tray and in all, every 20 steps (mean over episodes), closed loop in
MuJoCo and in the world model from the same first states (the study's seeds):

    MUJOCO_GL=egl python bench/probes/pile_lost_pieces.py checkpoints/pilesweep-64 \\
        expert runs/experiments/pilesweep/policy_eval/runs/expert-258b0869/dp-25demos/checkpoints/00003000

A POLICY is a scripted policy of the task or a policy checkpoint.
"""
import sys

import torch

from iwsim.core.resources import set_threads
from iwsim.envs.pilesweep.pixels import count_pieces
from iwsim.eval.policy import rollout
from iwsim.policies.factory import load_policy
from iwsim.policies.scripted import KINDS, ScriptedBatch
from iwsim.world_model import WorldModel

SEEDS = list(range(100000, 100006))
STEPS, EVERY = 200, 20


def main(model: str, *policies: str) -> None:
    set_threads(1)
    wm = WorldModel.load(model)
    for name in policies:
        for env in ("pilesweep", "world-model"):
            policy = ScriptedBatch(name, task="pilesweep") if name in KINDS else load_policy(name)
            torch.manual_seed(0)
            r = rollout(policy, env, SEEDS, STEPS, world_model=wm if env == "world-model" else None,
                        record=len(SEEDS), progress=False)
            inside, seen = count_pieces(r["frames"][:, ::EVERY])
            print(f"{name} in {env}, steps 0-{STEPS} every {EVERY}:")
            print("  seen     ", " ".join(f"{v:5.1f}" for v in seen.mean(0)))
            print("  in tray  ", " ".join(f"{v:5.1f}" for v in inside.mean(0)))


if __name__ == "__main__":
    main(*sys.argv[1:])
