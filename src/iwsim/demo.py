"""``iwsim demo`` (``make demo``): the scripted expert solving the T-pushing task.

Collects a few expert episodes into an episode store and writes them as one video with an
IoU bar under each frame. Later stages replace this with the world model.
"""

from __future__ import annotations

import argparse
import logging
from pathlib import Path

import numpy as np

from iwsim.data.collect import collect
from iwsim.data.store import EpisodeStore
from iwsim.envs.pusht import CONTROL_HZ, SUCCESS_IOU
from iwsim.eval.video import score_bar, upscale, write_video

log = logging.getLogger(__name__)


def main(args: argparse.Namespace) -> int:
    out = Path(args.out)
    store_path = out / "pusht_expert.zarr"
    collect(
        "pusht",
        "expert",
        args.episodes,
        out=store_path,
        steps=args.steps,
        image_size=args.image_size,
        workers=args.workers,
        seed=args.seed,
    )
    store = EpisodeStore.open(store_path)
    scale = max(1, 256 // args.image_size)
    clips = []
    for i in range(args.episodes):
        ep = store.episode(i)
        frames = upscale(ep["img"], scale)
        bar = score_bar(ep["iou"], frames.shape[2], 8, SUCCESS_IOU)
        clips.append(np.concatenate([frames, bar], axis=1))
        log.info("episode %d (seed %d): max IoU %.3f", i, store.seeds[i], float(ep["iou"].max()))
    video = write_video(out / "pusht_expert.mp4", np.concatenate(clips), fps=2 * CONTROL_HZ)
    print(f"Expert demo video: {video.resolve()}")
    return 0
