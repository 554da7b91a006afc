"""Frames between disk and models: uint8 (..., H, W, 3) <-> float (..., 3, H, W) in [-1, 1].

This is the one place where the conversion happens, and where frames are read from an
episode store for training without loading the store into memory.
"""

from __future__ import annotations

import numpy as np
import torch

from iwsim.core.errors import InputError
from iwsim.data.store import EpisodeStore
from iwsim.data.views import stack_views, store_cameras, view_keys


def to_model(frames: np.ndarray | torch.Tensor, views: int = 1) -> torch.Tensor:
    """uint8 (..., H, W, 3) -> float32 (..., 3, H, W) in [-1, 1]; with ``views`` > 1, the
    views of a frame stacked along the channels: (..., H, W, 3V) -> (..., 3V, H, W), view v
    in channels 3v..3v+2."""
    x = torch.as_tensor(frames)
    if x.dtype != torch.uint8 or x.ndim < 3 or x.shape[-1] != 3 * views:
        raise InputError(f"expected uint8 frames of shape (..., H, W, {3 * views}), got {tuple(x.shape)} {x.dtype}.")
    return x.movedim(-1, -3).float().div(127.5).sub(1.0)


def to_uint8(x: torch.Tensor) -> np.ndarray:
    """float (..., 3, H, W) in [-1, 1] -> uint8 (..., H, W, 3) numpy (rounded, clipped); views
    stacked along the channels stay stacked: (..., 3V, H, W) -> (..., H, W, 3V)."""
    return x.detach().float().add(1.0).mul(127.5).round().clamp(0, 255).to(torch.uint8).movedim(-3, -1).cpu().numpy()


def split_episodes(n_episodes: int, holdout_every: int) -> tuple[list[int], list[int]]:
    """A fixed split: episode i is held out iff i % holdout_every == holdout_every - 1."""
    held = [i for i in range(n_episodes) if i % holdout_every == holdout_every - 1]
    if not held and n_episodes > 1:
        held = [n_episodes - 1]  # small stores still get a held-out episode
    held_set = set(held)
    return [i for i in range(n_episodes) if i not in held_set], held


def view_arrays(store: EpisodeStore) -> list:
    """The store's view arrays (each (N, H, W, 3) uint8), in view order (:mod:`iwsim.data.views`)."""
    return [store.array(k) for k in view_keys(store_cameras(store.attrs, store.keys)).values()]


def read_frames(store: EpisodeStore, selection: slice | np.ndarray) -> np.ndarray:
    """Frames ``selection`` (a slice, or indices in any order) of every view of the store,
    stacked along the channels (:func:`stack_views`): (B, H, W, 3V) uint8."""
    if isinstance(selection, slice):
        return stack_views([np.asarray(a[selection]) for a in view_arrays(store)])
    idx = np.asarray(selection)
    uniq, inverse = np.unique(idx, return_inverse=True)
    return stack_views([np.asarray(a.oindex[uniq])[inverse] for a in view_arrays(store)])


class FrameSource:
    """Random access to the frames of some episodes of a store, read chunk by chunk.

    ``frames(idx)`` maps indices in ``[0, len(self))`` to uint8 (B, H, W, 3) frames: the
    chosen episodes' frames in order, of the store's first view, then (a store with several
    views, :mod:`iwsim.data.views`) of each further view in turn, so that a codec shared by
    the views trains on all of them.
    """

    def __init__(self, store: EpisodeStore, episodes: list[int]) -> None:
        if not episodes:
            raise InputError(f"{store.path} has no episodes to read for this split.")
        ends = store.episode_ends
        starts = np.concatenate([[0], ends[:-1]])
        self.store = store
        self.global_index = np.concatenate([np.arange(starts[e], ends[e]) for e in episodes])
        self._views = view_arrays(store)

    def __len__(self) -> int:
        return len(self.global_index) * len(self._views)

    def frames(self, idx: np.ndarray) -> np.ndarray:
        idx = np.asarray(idx)
        n = len(self.global_index)
        view, g = np.divmod(idx, n)
        g = self.global_index[g]
        out = np.empty((len(idx), *self._views[0].shape[1:]), np.uint8)
        for v in np.unique(view):
            at = view == v
            uniq, inverse = np.unique(g[at], return_inverse=True)
            out[at] = self._views[v].oindex[uniq][inverse]
        return out
