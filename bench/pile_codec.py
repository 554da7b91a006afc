"""Can a codec keep a pile? Pile sweeping's pieces through stage 1, on held-out frames.

    MUJOCO_GL=egl python bench/pile_codec.py x8=runs/pile_codec_x8 \\
        --data data/pile_play_eval.zarr data/pile_expert_eval.zarr --out bench/results/pilesweep/codec.md

Each codec (a stage-1 run, or a world model's codec) encodes and decodes every ``--every``-th
frame of the stores; the pixel scorer (:mod:`iwsim.envs.pilesweep.pixels`) then counts the
pieces on the reconstruction and on the original. Printed per codec and store: PSNR, the
share of frames whose reconstruction shows the original's number of pieces within +-1
(the world-model target's "pieces kept"), the mean absolute error of the pieces seen and of
the pieces in the tray. The scorer's own counts on the originals are the reference: a codec
that keeps every piece scores 100% and 0 errors whatever the scorer misses.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
import torch

from iwsim.core.checkpoint import resolve_checkpoint, write_text_atomic
from iwsim.core.errors import reporting_errors
from iwsim.core.metrics import psnr
from iwsim.core.resources import set_threads
from iwsim.data.frames import to_model, to_uint8
from iwsim.data.store import EpisodeStore
from iwsim.envs.pilesweep.pixels import count_pieces
from iwsim.eval.records import command_line
from iwsim.world_model.codecs import load_codec
from iwsim.world_model.codecs.base import reconstruct


def held_frames(path: Path, every: int) -> np.ndarray:
    """Every ``every``-th frame (N, H, W, 3) uint8 of a store."""
    return EpisodeStore.open(path, "r").array("img")[::every]


def score(codec, frames: np.ndarray) -> dict[str, float]:
    """The reconstruction's PSNR and its piece counts against the original's."""
    with torch.inference_mode():
        x = to_model(frames)
        y = reconstruct(codec, x, 1, chunk=256)
    recon = to_uint8(y)
    tray0, seen0 = count_pieces(frames)
    tray1, seen1 = count_pieces(recon)
    return {"frames": len(frames), "psnr": float(psnr((x + 1) / 2, (y + 1) / 2).mean()),
            "kept": float((np.abs(seen1 - seen0) <= 1).mean()), "seen_err": float(np.abs(seen1 - seen0).mean()),
            "tray_err": float(np.abs(tray1 - tray0).mean()), "pieces": float(seen0.mean())}


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("codecs", nargs="+", help="NAME=RUN: stage-1 runs (their last checkpoint) or world models")
    p.add_argument("--data", nargs="+", type=Path, default=[Path("data/pile_play_eval.zarr")],
                   help="held-out pile-sweeping stores (default: %(default)s)")
    p.add_argument("--every", type=int, default=5, help="score every this-many-th frame (default: %(default)s)")
    p.add_argument("--out", type=Path, help="also write the table here (markdown)")
    p.add_argument("--threads", type=int, default=1, help="torch threads (default: %(default)s)")
    args = p.parse_args(argv)
    if args.every < 1:
        p.error(f"--every must be >= 1, got {args.every}")
    set_threads(args.threads)
    stores = {path: held_frames(path, args.every) for path in args.data}
    lines = [f"`{command_line(__file__)}`", "",
             "| codec | store | frames | pieces (scorer, originals) | PSNR (dB) | pieces kept (+-1) | "
             "pieces seen, abs err | pieces in tray, abs err |", "|---|---|---|---|---|---|---|---|"]
    for item in args.codecs:
        name, sep, path = item.partition("=")
        if not sep:
            p.error(f"codecs are NAME=RUN, got {item!r}")
        codec = load_codec(resolve_checkpoint(path))
        for store, frames in stores.items():
            r = score(codec, frames)
            lines.append(f"| {name} | {store} | {r['frames']} | {r['pieces']:.1f} | {r['psnr']:.2f} | "
                         f"{100 * r['kept']:.1f}% | {r['seen_err']:.2f} | {r['tray_err']:.2f} |")
            print(lines[-1], flush=True)
    if args.out:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        write_text_atomic(args.out, "\n".join(lines) + "\n")  # whole or absent: the recipe skips it when present
    return 0


if __name__ == "__main__":
    raise SystemExit(reporting_errors("pile_codec.py", main))
