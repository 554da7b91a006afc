"""Frames between disk and models: uint8 (..., H, W, 3) <-> float (..., 3, H, W) in [-1, 1].

This is the one place where the conversion happens, and where frames are read from an
episode store for training without loading the store into memory.
"""

from __future__ import annotations

import numpy as np
import torch

from iwsim.core.errors import InputError
from iwsim.data.store import EpisodeStore


def to_model(frames: np.ndarray | torch.Tensor) -> torch.Tensor:
    """uint8 (..., H, W, 3) -> float32 (..., 3, H, W) in [-1, 1]."""
    x = torch.as_tensor(frames)
    if x.dtype != torch.uint8 or x.ndim < 3 or x.shape[-1] != 3:
        raise InputError(f"expected uint8 frames of shape (..., H, W, 3), got {tuple(x.shape)} {x.dtype}.")
    return x.movedim(-1, -3).float().div(127.5).sub(1.0)


def to_uint8(x: torch.Tensor) -> np.ndarray:
    """float (..., 3, H, W) in [-1, 1] -> uint8 (..., H, W, 3) numpy (rounded, clipped)."""
    return x.detach().float().add(1.0).mul(127.5).round().clamp(0, 255).to(torch.uint8).movedim(-3, -1).cpu().numpy()


def split_episodes(n_episodes: int, holdout_every: int) -> tuple[list[int], list[int]]:
    """A fixed split: episode i is held out iff i % holdout_every == holdout_every - 1."""
    held = [i for i in range(n_episodes) if i % holdout_every == holdout_every - 1]
    if not held and n_episodes > 1:
        held = [n_episodes - 1]  # small stores still get a held-out episode
    held_set = set(held)
    return [i for i in range(n_episodes) if i not in held_set], held


class FrameSource:
    """Random access to the frames of some episodes of a store, read chunk by chunk.

    ``frames(idx)`` maps indices in ``[0, len(self))`` (over the chosen episodes, in
    order) to uint8 (B, H, W, 3) frames.
    """

    def __init__(self, store: EpisodeStore, episodes: list[int]) -> None:
        if not episodes:
            raise InputError(f"{store.path} has no episodes to read for this split.")
        ends = store.episode_ends
        starts = np.concatenate([[0], ends[:-1]])
        self.store = store
        self.global_index = np.concatenate([np.arange(starts[e], ends[e]) for e in episodes])
        self._img = store.array("img")

    def __len__(self) -> int:
        return len(self.global_index)

    def frames(self, idx: np.ndarray) -> np.ndarray:
        g = self.global_index[np.asarray(idx)]
        uniq, inverse = np.unique(g, return_inverse=True)
        return self._img.oindex[uniq][inverse]
