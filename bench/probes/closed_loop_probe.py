"""Is a family's offset the model's dynamics or what the policy observes in it? (issue 41)

For one operator family (:mod:`iwsim.yardstick.families`) from its first states:
1. open loop: the motion MuJoCo executed in each episode (its speed-limited setpoints,
   what the model is conditioned on) replayed in the world model from the same first
   frame, scored beside MuJoCo (the dynamics alone);
2. closed loop: the family driven inside the world model, and its actions replayed in
   MuJoCo (what the policy did there, scored by the ground truth);
3. the pushers as read from the open-loop model frames against MuJoCo's frames (mm).

    MUJOCO_GL=egl python bench/probes/closed_loop_probe.py --model checkpoints/pusht-64 \
        --families expert,lag3,pause --episodes 8
    # learned policies: each checkpoint (or every checkpoint of a run) from the same first states
    MUJOCO_GL=egl python bench/probes/closed_loop_probe.py --families "" --zoo RUN/checkpoints/00003000 ...
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
import torch

from iwsim.core.errors import reporting_errors
from iwsim.envs.pusht.pixels import pixel_iou, pusher_positions
from iwsim.eval.policy import rollout
from iwsim.policies.factory import load_policy
from iwsim.policies.scripted import ScriptedBatch
from iwsim.world_model import WorldModel
from iwsim.yardstick import families


class Replay:
    """Recorded actions (E, T, A) as a policy, one step per call."""

    obs_horizon, n_action_steps, kind = 1, 1, "scripted"

    def __init__(self, actions: np.ndarray) -> None:
        self.actions, self.t = actions, 0

    def reset(self) -> None:
        self.t = 0

    def predict_action(self, obs: dict) -> np.ndarray:
        self.t += 1
        return self.actions[:, self.t - 1][:, None]


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--model", default="checkpoints/pusht-64")
    p.add_argument("--families", default="expert,lag3,pause")
    p.add_argument("--episodes", type=int, default=8)
    p.add_argument("--steps", type=int, default=300)
    p.add_argument("--zoo", nargs="*", default=[], help="policy checkpoints or runs: the learned family, "
                   "each checkpoint from --episodes first states")
    args = p.parse_args()
    torch.set_num_threads(1)
    wm = WorldModel.load(args.model)
    seeds = [families.SEED + i for i in range(args.episodes)]
    print("| family | MuJoCo | open loop in the model | closed loop in the model | its actions in MuJoCo "
          "| pusher read, model vs MuJoCo frames: median / p90 mm |")
    print("|---|---|---|---|---|---|")
    runs = [(name, lambda name=name: ScriptedBatch(families.FAMILIES[name][0]))
            for name in args.families.split(",") if name]
    runs += [(f"{Path(c).parent.parent.name}-{Path(c).name}", lambda c=c: load_policy(c, torch.device("cpu")))
             for c in families.zoo_sources(args.zoo)]
    for name, make in runs:
        torch.manual_seed(0)  # a learned policy's sampling noise, as the studies seed it
        m = rollout(make(), "pusht", seeds, args.steps, record=len(seeds), progress=False)
        open_loop = wm.rollout(m["frames"][:, 0], m["target"], seed=list(range(len(seeds))))
        open_iou = np.array([[pixel_iou(f) for f in ep] for ep in open_loop]).max(1)
        torch.manual_seed(0)
        w = rollout(make(), "world-model", seeds, args.steps, world_model=wm, progress=False)
        back = rollout(Replay(w["action"]), "pusht", seeds, args.steps, progress=False)
        size = m["frames"].shape[-2]
        truth, _ = pusher_positions(m["frames"][:, 1:].reshape(-1, size, size, 3))
        drawn, _ = pusher_positions(open_loop.reshape(-1, size, size, 3))
        err = np.linalg.norm((truth - drawn).reshape(-1, 2, 2), axis=-1) * 1000
        print(f"| {name} | {m['iou'].max(1).mean():.3f} | {open_iou.mean():.3f} | {w['iou'].max(1).mean():.3f} | "
              f"{back['iou'].max(1).mean():.3f} | {np.nanmedian(err):.1f} / {np.nanquantile(err, 0.9):.1f} |",
              flush=True)


if __name__ == "__main__":
    raise SystemExit(reporting_errors("closed_loop_probe.py", main))
