"""A probe of issue 64 (not a feature): how crisply does a codec render the T? Frames of a
held-out store (every 20th of each episode), encoded and decoded by each codec; the T's
outline fit (``iwsim.envs.pusht.pixels.estimate_block_pose``) on the reconstructions against the
frames' own, and the share that still fits crisply (>= 0.9, the yardstick's CRISP). It
bounds what a world model on that codec can show after contact.

    MUJOCO_GL=egl python bench/probes/codec_t_fit.py --data data/play_eval.zarr \
        shipped=checkpoints/pusht-64 x4=runs/pt_codec_x4_8000
"""
import argparse

import numpy as np
import torch

from iwsim.core.checkpoint import resolve_checkpoint
from iwsim.data.frames import to_model, to_uint8
from iwsim.data.store import EpisodeStore
from iwsim.envs.pusht import pixels
from iwsim.world_model.codecs import load_codec

p = argparse.ArgumentParser()
p.add_argument("codecs", nargs="+", help="NAME=CHECKPOINT_OR_RUN (a stage-1 run or a world model)")
p.add_argument("--data", default="data/play_eval.zarr")
p.add_argument("--every", type=int, default=20)
args = p.parse_args()
torch.set_num_threads(1)
store = EpisodeStore.open(args.data)
ends = np.concatenate([[0], store.episode_ends])
index = np.concatenate([np.arange(a, b, args.every) for a, b in zip(ends[:-1], ends[1:])])
frames = store.array("img")[:][index]


def fits(x: np.ndarray) -> np.ndarray:
    return np.array([pixels.estimate_block_pose(f).fit_iou for f in x])


own = fits(frames)
print(f"{len(frames)} frames of {args.data}: the frames' own T fit {own.mean():.3f}, crisp {np.mean(own >= 0.9):.0%}")
for item in args.codecs:
    name, _, path = item.partition("=")
    codec = load_codec(resolve_checkpoint(path)).eval()
    with torch.inference_mode():
        rec = np.concatenate([to_uint8(codec.decode(codec.encode(to_model(torch.from_numpy(frames[i:i + 64])))))
                              for i in range(0, len(frames), 64)])
    f = fits(rec)
    print(f"{name}: latents {tuple(codec.latent_shape)}, T fit {f.mean():.3f} (frames' own {own.mean():.3f}), "
          f"crisp {np.mean(f >= 0.9):.0%}, fit lost {np.mean(own - f):+.3f}")
