"""A probe of issue 25 (not a feature): is Diffusion Policy held back by what it sees, or
by what it must do? The `dp` preset's UNet, optimizer and EMA, with the image encoder
replaced by the block pose the pixel expert itself acts on: ``estimate_block_pose`` of
each frame (x, y, cos yaw, sin yaw; ``--features keypoints``: the T's 8 corners), beside
agent_pos, for the To = 2 observed steps.
Poses of the training frames are estimated once; at evaluation, from every observed frame.
If this policy learns the task, the image policy's gap is perception; if it stalls the
same way, it is the imitation itself (the actions, the data, the policy class).
Scores on 20 validation seeds x 600 steps go to runs/pol/NAME/probe_scores.jsonl;
with ``--on-train``, also from the first states of the training takes themselves (the
memorisation test: a policy that cannot replay its own takes is not fitted) to
train_scores.jsonl.

    MUJOCO_GL=egl OMP_NUM_THREADS=1 python bench/probes/policy_state_probe.py --name probe-pose \
        --steps 6000 --eval-at 2000,4000,6000
    # issue 44's budget test: the curve to convergence, constant learning rate
    MUJOCO_GL=egl OMP_NUM_THREADS=1 python bench/probes/policy_state_probe.py --name probe-pose-40k \
        --steps 40000 --lr-decay constant --eval-at 5000,10000,20000,40000
"""
import argparse
import dataclasses
import time
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import torch

from iwsim.core import trainer
from iwsim.core.errors import reporting_errors
from iwsim.data.store import EpisodeStore
from iwsim.envs.pusht import geometry as geo
from iwsim.envs.pusht.pixels import estimate_block_pose
from iwsim.envs.pusht.sim import VIEW_HALF
from iwsim.eval.policy_runs import score_checkpoints
from iwsim.policies import PRESETS
from iwsim.policies.data import parse_mixture
from iwsim.policies.diffusion.model import DiffusionPolicy
from iwsim.policies.train import PolicyTask

CORNERS = np.concatenate(geo.T_PARTS)  # (8, 2): the T's corners in the block frame
FEATURES = {"pose": 4, "keypoints": 16}


def pose_features(frames: np.ndarray, kind: str) -> np.ndarray:
    """(N, H, W, 3) uint8 -> (N, F) from the estimated block pose; zeros where the block is
    not found. ``pose``: x / VIEW_HALF, y / VIEW_HALF, cos, sin of the yaw; ``keypoints``:
    the T's 8 corners in the world / VIEW_HALF (as the reference's low-dim PushT)."""
    out = np.zeros((len(frames), FEATURES[kind]), np.float32)
    for i, f in enumerate(frames):
        est = estimate_block_pose(f)
        if est.found:
            x, y, yaw = est.pose
            out[i] = ((x / VIEW_HALF, y / VIEW_HALF, np.cos(yaw), np.sin(yaw)) if kind == "pose"
                      else (geo.to_world(CORNERS, est.pose) / VIEW_HALF).reshape(-1))
    return out


class PoseDP(DiffusionPolicy):
    """The condition: per observed step, its pose features (4, or 16 keypoint coordinates) and
    normalised agent_pos."""

    def __init__(self, cfg, action_norm, state_norm, kind="pose"):
        super().__init__(dataclasses.replace(cfg, image_features=FEATURES[kind]), action_norm, state_norm)
        self.encoder, self.features = None, kind

    def condition(self, image, agent_pos):
        if image.ndim == 5:  # frames at evaluation: (B, To, 3, H, W) in [-1, 1]
            frames = ((image.permute(0, 1, 3, 4, 2) + 1) * 127.5).round().clamp(0, 255).to(torch.uint8)
            b, to = frames.shape[:2]
            image = torch.from_numpy(pose_features(frames.flatten(0, 1).numpy(), self.features)).view(b, to, -1)
        return torch.cat([image, agent_pos], -1).flatten(1)


class PoseTask(PolicyTask):
    def __init__(self, cfg, sources, kind):
        super().__init__(cfg, sources)
        t0 = time.time()
        self.pose = torch.from_numpy(pose_features(self.data.img.numpy(), kind))
        print(f"estimated {len(self.pose)} poses in {time.time() - t0:.0f}s, "
              f"{(self.pose.abs().sum(1) == 0).float().mean():.1%} not found", flush=True)
        with torch.random.fork_rng():
            torch.manual_seed(cfg.train.seed)
            self.module = PoseDP(self.module.cfg, self.action_norm, self.state_norm, kind)

    def batch(self, step, generator, part, device):
        t = torch.randint(0, self.data.n_frames, (self.cfg.train.batch_size,), generator=generator)
        torch.manual_seed(int(torch.randint(2**62, (1,), generator=generator)))
        b = self.data.batch(t[part], self.action_norm, self.state_norm, self.relative)
        b.image = self.pose[self.data.windows(t[part])[0]]
        return b

    @torch.no_grad()
    def evaluate(self, module, step, out_dir):
        return {}


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--name", required=True)
    p.add_argument("--data", default="runs/experiments/demos/sim_expert.zarr:100")
    p.add_argument("--steps", type=int, default=6000)
    p.add_argument("--eval-at", default="")
    p.add_argument("--episodes", type=int, default=20)
    p.add_argument("--features", choices=tuple(FEATURES), default="pose")
    p.add_argument("--relative", action="store_true", help="actions as offsets from the current agent_pos")
    p.add_argument("--lr-decay", choices=("cosine", "constant"), default="cosine")
    p.add_argument("--on-train", action="store_true",
                   help="also score from the training takes' own first states (at most 20)")
    args = p.parse_args()
    torch.set_num_threads(1)
    base = PRESETS["dp"]
    train = dataclasses.replace(base.train, steps=args.steps, eval_every=10**9, checkpoint_every=1000, seed=0,
                                lr_decay=args.lr_decay)
    cfg = dataclasses.replace(base, model={**base.model, "relative_actions": args.relative}, train=train)
    task = PoseTask(cfg, parse_mixture(args.data), args.features)
    run = Path("runs/pol") / args.name
    t0 = time.time()
    trainer.train(task, cfg.train, run, task.config(), device=torch.device("cpu"), progress=False)
    print(f"trained in {(time.time() - t0) / 60:.1f} min", flush=True)
    steps = [int(x) for x in args.eval_at.split(",") if x]
    report(args.name, score_checkpoints(task.module, run, steps, args.episodes))
    if args.on_train:
        src = parse_mixture(args.data)[0]
        seeds = EpisodeStore.open(src.path).attrs["seeds"][:min(src.episodes or 20, 20)]
        report(f"{args.name} (own takes)", score_checkpoints(task.module, run, steps, out="train_scores.jsonl",
                                                             seeds=seeds))


def report(name: str, scores: Iterator[tuple[int, dict]]) -> None:
    """One line per checkpoint, as each is scored."""
    for step, r in scores:
        print(f"{name} @{step}: mean max IoU {r['mean_max_iou']:.3f} success {r['success_rate']:.2f} "
              f"({r['seconds']:.0f}s)", flush=True)


if __name__ == "__main__":
    raise SystemExit(reporting_errors("policy_state_probe.py", main))
