"""The codec's ceiling on a store's success frames: can a take in the model be kept at all?

    MUJOCO_GL=egl python bench/codec_ceiling.py --data data/expert_eval.zarr \\
        shipped=checkpoints/pusht-64 dec900=runs/dec_contact/checkpoints/00000900

The frames of the store that score as a success (pixel IoU >= the task's threshold) are
encoded and decoded by each model's codec; printed: the share whose reconstruction still
scores as a success (as the yardstick's `goal frames kept by the codec`) and the mean
score of the reconstructions against that of the originals.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from iwsim.core.errors import reporting_errors
from iwsim.core.resources import set_threads
from iwsim.envs.pusht import pixels
from iwsim.experiments.demos import PUSHT
from iwsim.world_model import WorldModel
from iwsim.yardstick.codec import goal_frames, reconstruction_scores


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("models", nargs="+", help="NAME=CHECKPOINT world models")
    p.add_argument("--data", default="data/expert_eval.zarr", help="store with success frames (default: %(default)s)")
    p.add_argument("--threads", type=int, default=1, help="torch threads (default: %(default)s)")
    args = p.parse_args(argv)
    set_threads(args.threads)
    goal = goal_frames(Path(args.data))
    if goal is None:
        p.error(f"{args.data} holds no frame scoring >= {PUSHT.success_score}")
    print(f"{args.data}: {len(goal)} success frames, mean pixel IoU {pixels.pixel_iou(goal).mean():.3f}")
    for item in args.models:
        name, sep, path = item.partition("=")
        if not sep:
            p.error(f"models are NAME=CHECKPOINT, got {item!r}")
        rec = reconstruction_scores(WorldModel.load(path), goal)
        print(f"{name}: kept {(rec >= PUSHT.success_score).mean():.0%}, mean pixel IoU of the reconstructions "
              f"{rec.mean():.3f}", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(reporting_errors("codec_ceiling.py", main))
