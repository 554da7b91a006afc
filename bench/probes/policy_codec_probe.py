"""A probe of issue 25 (not a feature): the `dp` preset with its image encoder replaced
by the shipped world model's frozen codec encoder (8 x 8 x 8 latents, standardised) and a
small trainable head (two 3x3 convs, then a linear layer; ``--head mlp``: two linear
layers). The latents of the training frames are computed once, under ``--variants`` fixed
random shifts of up to 4 px (the first unshifted), so a step costs only the head and the
UNet. Scores on 20 validation seeds x 600 steps go to runs/pol/NAME/proto_scores.jsonl.

    MUJOCO_GL=egl OMP_NUM_THREADS=1 python bench/probes/policy_codec_probe.py --name proto-codec \
        --steps 10000 --variants 5 --eval-at 4000,7000,10000
"""
import argparse
import dataclasses
import time
from pathlib import Path

import torch
from torch import nn

from iwsim.core import trainer
from iwsim.eval.policy_runs import score_checkpoints
from iwsim.policies import PRESETS
from iwsim.policies.common import random_shift
from iwsim.policies.data import parse_mixture
from iwsim.policies.diffusion.config import DiffusionConfig
from iwsim.policies.diffusion.model import DiffusionPolicy
from iwsim.policies.train import PolicyTask
from iwsim.world_model.model import WorldModel

p = argparse.ArgumentParser()
p.add_argument("--name", required=True)
p.add_argument("--steps", type=int, default=20000)
p.add_argument("--variants", type=int, default=5)
p.add_argument("--eval-at", default="")
p.add_argument("--head", default="conv")
p.add_argument("--lr", type=float, default=3e-4)
args = p.parse_args()
torch.set_num_threads(1)

wm = WorldModel.load("checkpoints/pusht-64")
codec = wm.codec.eval().requires_grad_(False)


class LatentHead(nn.Module):
    def __init__(self, c, hw, out, kind):
        super().__init__()
        if kind == "conv":
            self.net = nn.Sequential(nn.Conv2d(c, 64, 3, padding=1), nn.GroupNorm(8, 64), nn.ReLU(),
                                     nn.Conv2d(64, 64, 3, padding=1), nn.GroupNorm(8, 64), nn.ReLU(),
                                     nn.Flatten(), nn.Linear(64 * hw * hw, out))
        else:
            self.net = nn.Sequential(nn.Flatten(), nn.Linear(c * hw * hw, 512), nn.Mish(), nn.Linear(512, out))

    def forward(self, x):
        return self.net(x)


class CodecDP(DiffusionPolicy):
    def __init__(self, cfg, an, sn, mean, scale):
        super().__init__(cfg, an, sn)
        c, h, w = codec.latent_shape
        self.encoder = LatentHead(c, h, cfg.image_features, args.head)
        self.register_buffer("z_mean", mean)
        self.register_buffer("z_scale", scale)

    def condition(self, image, agent_pos):
        b, to = image.shape[:2]
        x = image.flatten(0, 1)
        if x.shape[1] == 3:
            with torch.no_grad():
                x = codec.encode(x)
        x = (x - self.z_mean) / self.z_scale
        return torch.cat([self.encoder(x).view(b, to, -1), agent_pos], -1).flatten(1)


class LatentTask(PolicyTask):
    def __init__(self, cfg, sources):
        super().__init__(cfg, sources)
        img = self.data.img
        g = torch.Generator().manual_seed(7)
        offs = [(4, 4)] + [tuple(torch.randint(0, 9, (2,), generator=g).tolist()) for _ in range(args.variants - 1)]
        t0 = time.time()
        zs = []
        for dy, dx in offs:
            parts = []
            for i in range(0, len(img), 512):
                x = img[i:i + 512].permute(0, 3, 1, 2).float()[:, None] / 127.5 - 1
                n = len(x)
                x = random_shift(x, 4, torch.tensor([[dy] * n, [dx] * n]))[:, 0]
                with torch.no_grad():
                    parts.append(codec.encode(x))
            zs.append(torch.cat(parts))
        self.z = torch.stack(zs)  # (K, N, C, h, w)
        print(f"encoded {len(offs)} x {len(img)} frames in {time.time() - t0:.0f}s", flush=True)
        mean = self.z[0].mean((0, 2, 3))[:, None, None]
        scale = self.z[0].std((0, 2, 3))[:, None, None]
        with torch.random.fork_rng():
            torch.manual_seed(cfg.train.seed)
            self.module = CodecDP(from_cfg, *self.data.normalizers(), mean, scale)

    def batch(self, step, generator, part, device):
        t = torch.randint(0, self.data.n_frames, (self.cfg.train.batch_size,), generator=generator)
        k = torch.randint(0, self.z.shape[0], (len(t),), generator=generator)
        torch.manual_seed(int(torch.randint(2**62, (1,), generator=generator)))
        b = self.data.batch(t[part], self.action_norm, self.state_norm)
        obs, _, _ = self.data.windows(t[part])
        b.image = self.z[k[part][:, None], obs]
        return b

    @torch.no_grad()
    def evaluate(self, module, step, out_dir):
        return {}


from_cfg = DiffusionConfig()
base = PRESETS["dp"]
cfg = dataclasses.replace(base, train=dataclasses.replace(base.train, steps=args.steps, lr=args.lr, eval_every=10**9,
                                                              checkpoint_every=1000, seed=0))
task = LatentTask(cfg, parse_mixture("runs/experiments/demos/sim_expert.zarr:100"))
run = Path("runs/pol") / args.name
t0 = time.time()
trainer.train(task, cfg.train, run, task.config(), device=torch.device("cpu"), progress=False)
print(f"trained in {(time.time() - t0) / 60:.1f} min", flush=True)
for step, r in score_checkpoints(task.module, run, [int(x) for x in args.eval_at.split(",") if x],
                                 out="proto_scores.jsonl"):
    print(f"{args.name} @{step}: mean max IoU {r['mean_max_iou']:.3f} success {r['success_rate']:.2f} "
          f"({r['seconds']:.0f}s)", flush=True)
