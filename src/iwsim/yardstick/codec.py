"""The codec's ceiling (the yardstick's item 6, ``bench/codec_ceiling.py``): the frames of a
store that score as a T-push success, encoded and decoded by a model's codec; a take in the
model can only be kept if its frames can be."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

from iwsim.data.store import EpisodeStore
from iwsim.envs.pusht import pixels
from iwsim.experiments.demos import PUSHT
from iwsim.world_model import WorldModel


@torch.inference_mode()
def reconstruction_scores(wm: WorldModel, frames: np.ndarray) -> np.ndarray:
    """The pixel IoU (N,) of each of ``frames`` (N, H, W, 3) uint8 encoded and decoded by
    the model's codec."""
    return np.asarray(pixels.pixel_iou(np.concatenate([wm.decode(wm.encode(frames[i:i + 256]))
                                                       for i in range(0, len(frames), 256)])))


def codec_ceiling(wm: WorldModel, frames: np.ndarray | None) -> float | None:
    """The share of ``frames`` (success frames, :func:`goal_frames`) whose reconstruction
    by the model's codec still scores as a success (None without frames)."""
    if frames is None:
        return None
    return float((reconstruction_scores(wm, frames) >= PUSHT.success_score).mean())


def goal_frames(path: Path) -> np.ndarray | None:
    """The frames of a store that score as a success (None when it has none, e.g. MuJoCo's
    teleoperation store after a run whose takes were too short to succeed)."""
    store = EpisodeStore.open(path, "r")
    if store.n_episodes == 0:
        return None
    img = store.array("img")[:]
    img = img[pixels.pixel_iou(img) >= PUSHT.success_score]
    return img if len(img) else None
