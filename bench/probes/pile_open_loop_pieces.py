"""Issue 45: is it the decoder or the dynamics that loses a pile model's pieces, and what do
inference settings do to it? Each model rolled out open loop on 20 held-out play episodes
(199 steps, the yardstick's first item): the share of frames whose piece count is the first
frame's within one, the shares under and over it, PSNR, and the mean count every 20 steps
beside MuJoCo's. Several models with one dynamics and other decoders (``iwsim export-model
--decoder``) or other inference settings (``--rest-threshold``, ``--delta-deadband``) tell
the parts apart in ~4 minutes a model (one thread):

    MUJOCO_GL=egl python bench/probes/pile_open_loop_pieces.py runs/pile_wm_3000 runs/pile_wm_3000_plain
"""
import sys

import numpy as np
import torch

from iwsim.data.store import EpisodeStore
from iwsim.envs.pilesweep.pixels import count_pieces, piece_fraction
from iwsim.envs.tabletop.palette import pixel_centers
from iwsim.eval.rollout import open_loop
from iwsim.world_model import WorldModel

STORE, EPISODES, STEPS, EVERY = "data/pile_play_eval.zarr", list(range(20)), 199, 20
STILL = 0.002  # m: a piece that moves less over the episode is untouched


def untouched_drawn(store: EpisodeStore, pred: np.ndarray, steps: tuple[int, ...]) -> tuple[int, int, list[float]]:
    """Pieces in view over the episodes, those untouched, and the share of the untouched
    ones the model still draws at each of ``steps`` (indices into ``pred``'s steps)."""
    size = pred.shape[-2]
    centres = pixel_centers(size).reshape(-1, 2)
    fraction = piece_fraction(pred[:, list(steps)])  # (E, len(steps), H, W): only the steps asked for
    total, drawn = 0, np.zeros(len(steps))
    pieces = 0
    for i, e in enumerate(EPISODES):
        xy = store.episode(e)["pieces"][1:STEPS + 1]  # (T, P, 2), aligned with pred
        seen = np.isfinite(xy[0, :, 0]) & (np.abs(xy[0]).max(1) < 0.3)  # padded and parked pieces are out
        pieces += int(seen.sum())
        still = seen & (np.linalg.norm(xy - xy[:1], axis=-1).max(0) < STILL)
        for j in np.flatnonzero(still):
            y, x = divmod(int(np.argmin(((centres - xy[0, j]) ** 2).sum(1))), size)
            near = fraction[i, :, max(y - 1, 0):y + 2, max(x - 1, 0):x + 2]
            drawn += near.reshape(len(steps), -1).max(1) > 0.3
            total += 1
    return pieces, total, (drawn / max(total, 1)).tolist()


def main(*models: str) -> None:
    torch.set_num_threads(1)
    store = EpisodeStore.open(STORE, "r")
    first = count_pieces(np.stack([store.episode(e)["img"][0] for e in EPISODES]))[1]  # (E,)
    for name in models:
        r = open_loop(WorldModel.load(name), store, EPISODES, STEPS)
        seen, truth = count_pieces(r.pred)[1], count_pieces(r.truth)[1]  # (E, T)
        off = seen - first[:, None]
        print(f"{name}: kept {np.mean(np.abs(off) <= 1):.1%} (under {np.mean(off < -1):.1%}, over "
              f"{np.mean(off > 1):.1%}), PSNR {r.psnr.mean():.2f}")
        print("  seen, model ", " ".join(f"{v:5.1f}" for v in seen.mean(0)[::EVERY]))
        print("  seen, MuJoCo", " ".join(f"{v:5.1f}" for v in truth.mean(0)[::EVERY]))
        pieces, still, drawn = untouched_drawn(store, r.pred, (99, STEPS - 1))
        print(f"  {still} of {pieces} pieces untouched; drawn at steps 100 / {STEPS}: "
              + " / ".join(f"{d:.0%}" for d in drawn))


if __name__ == "__main__":
    main(*sys.argv[1:])
