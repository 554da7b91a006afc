"""Reading tabletop frames (:mod:`iwsim.envs.tabletop.scene`) by colour: the pixel grid, the
share of each palette surface in each pixel, and the pushers' positions.

These read nothing but RGB frames, so they work on MuJoCo frames and world-model frames
alike. The camera is orthographic and top-down, so pixel (i, j) looks at the world point
``(x, y) = (-V + (j + 0.5) s, V - (i + 0.5) s)`` with ``V = view_half`` and pixel size
``s = 2 V / W``.
"""

from __future__ import annotations

from itertools import combinations
from typing import cast

import numpy as np

from iwsim.core.errors import InputError
from iwsim.envs.tabletop.scene import VIEW_HALF

CHUNK_PIXELS = 2**19  # pixels Palette.fractions models at once (128 frames of 64 x 64: ~0.5 GB)


def pixel_centers(image_size: int, view_half: float = VIEW_HALF) -> np.ndarray:
    """(H, W, 2) world (x, y) of each pixel centre."""
    s = 2 * view_half / image_size
    c = -view_half + (np.arange(image_size) + 0.5) * s
    xx, yy = np.meshgrid(c, -c)
    return np.stack([xx, yy], axis=-1)


def world_to_pixel(xy: np.ndarray, image_size: int, view_half: float = VIEW_HALF) -> np.ndarray:
    """(..., 2) world (x, y) -> (..., 2) continuous pixel (col, row) coordinates."""
    s = 2 * view_half / image_size
    xy = np.asarray(xy, dtype=np.float64)
    return np.stack([(xy[..., 0] + view_half) / s - 0.5, (view_half - xy[..., 1]) / s - 0.5], axis=-1)


def check_frames(frame: np.ndarray) -> np.ndarray:
    """``frame`` as an array of RGB frames (..., H, W, 3) with H == W, or an InputError."""
    frame = np.asarray(frame)
    if frame.ndim < 3 or frame.shape[-1] != 3 or frame.shape[-2] != frame.shape[-3]:
        raise InputError(f"expected RGB frames of shape (..., H, W, 3) with H == W, got {frame.shape}.")
    return frame


class Palette:
    """A task's surfaces and their colours as rendered (8-bit), with the model of a pixel
    as the best mix of two of them (anti-aliased edges blend two surfaces; a colour with
    itself is a pure pixel). ``colours``: name -> RGB in [0, 1]; ``first`` is listed first
    (it wins ties between equally good mixes)."""

    def __init__(self, colours: dict[str, tuple[float, float, float]], first: str) -> None:
        self.names = [first] + [n for n in colours if n != first]
        self.colours = np.array([np.round(np.array(colours[n]) * 255) for n in self.names], dtype=np.float32)
        self.pairs = np.array([(i, i) for i in range(len(self.names))]
                              + list(combinations(range(len(self.names)), 2)))

    def fractions(self, frame: np.ndarray, names: tuple[str, ...]) -> np.ndarray:
        """(..., H, W, 3) uint8 frames -> (..., K, H, W) float32 fraction of each pixel that
        shows each of the K surfaces ``names``: that surface's share of the pixel's best mix."""
        for name in names:
            if name not in self.names:
                raise InputError(f"unknown surface {name!r}; expected one of {self.names}.")
        frame = check_frames(frame)
        hw = frame.shape[-3] * frame.shape[-2]
        if frame.size // 3 > CHUNK_PIXELS and frame.size // (3 * hw) > 1:
            # a few frames at a time: every pair's (..., H, W, P) float64 arrays for the 3840 frames of
            # the yardstick's play part at once took 17 GB
            flat = frame.reshape(-1, *frame.shape[-3:])
            per = max(1, CHUNK_PIXELS // hw)
            parts = [self.fractions(flat[i:i + per], names) for i in range(0, len(flat), per)]
            return np.concatenate(parts).reshape(*frame.shape[:-3], len(names), *frame.shape[-3:-1])
        p = frame.astype(np.float64)  # (..., H, W, 3)
        a = self.colours[self.pairs[:, 0]].astype(np.float64)
        b = self.colours[self.pairs[:, 1]].astype(np.float64)  # (P, 3)
        d = b - a
        dd = (d * d).sum(-1)
        # every pair at once, by inner products: with x = p - a, the second colour's share is
        # gamma = clip(x.d / d.d, 0, 1) and the error |x - gamma d|^2 = x.x - 2 gamma x.d + gamma^2 d.d
        xd = p @ d.T - (a * d).sum(-1)  # (..., H, W, P)
        xx = (p * p).sum(-1, keepdims=True) - 2 * p @ a.T + (a * a).sum(-1)
        gamma = np.clip(xd / np.maximum(dd, 1e-12), 0, 1)  # a pair of one colour twice has d = 0
        err = xx - 2 * gamma * xd + gamma**2 * dd
        best = err.argmin(-1)[..., None]  # the first pair of least error
        gamma = np.take_along_axis(gamma, best, -1)[..., 0]
        first, second = self.pairs[best[..., 0], 0], self.pairs[best[..., 0], 1]
        out = [(1 - gamma) * (first == k) + gamma * (second == k) for k in map(self.names.index, names)]
        return np.stack(out, axis=-3).astype(np.float32)

    def pusher_positions(self, frame: np.ndarray, min_pixels: float = 1.0) -> tuple[np.ndarray, np.ndarray]:
        """Pusher centres from (..., H, W, 3) frames: positions (..., 4) float32 ``[lx, ly,
        rx, ry]`` in metres and found (..., 2) bool (see :func:`pusher_centroids`)."""
        xy, found, _ = pusher_centroids(self.fractions(frame, ("left", "right")), min_pixels)
        return xy, found


def pusher_centroids(fractions: np.ndarray, min_pixels: float, radius: float = 2.5
                     ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Pusher positions (..., 4) ``[lx, ly, rx, ry]`` in metres, found (..., 2) and peak
    fractions (..., 2) from the two pushers' colour fractions (..., 2, H, W).

    A position is the fraction-weighted centroid of the pusher's colour within ``radius``
    px of its peak (the fraction map smoothed over 3 x 3 pixels), so the colour that
    generated frames leak elsewhere does not pull it: 0.2 px median error on autoencoder
    reconstructions, against 5.7 px for the centroid of all the colour. Found: at least
    ``min_pixels`` of that colour near its peak (else the position is NaN); with
    ``min_pixels`` <= 0 every pusher is found, one with no colour at all at its peak pixel.
    """
    size = fractions.shape[-1]
    pad = np.pad(fractions, [(0, 0)] * (fractions.ndim - 2) + [(1, 1), (1, 1)])
    smooth = cast(np.ndarray, sum(pad[..., i:i + size, j:j + size] for i in range(3) for j in range(3))) / 9
    rows, cols = np.divmod(smooth.reshape(*smooth.shape[:-2], -1).argmax(-1), size)
    yy, xx = np.mgrid[0:size, 0:size]
    near = (yy - rows[..., None, None]) ** 2 + (xx - cols[..., None, None]) ** 2 <= radius**2
    xy, found = centroids(fractions * near, max(min_pixels, 1e-6))
    if min_pixels <= 0:
        xy = np.where(np.isnan(xy), pixel_centers(size)[rows, cols].reshape(xy.shape), xy).astype(np.float32)
        found = np.ones_like(found)
    return xy, found, fractions.reshape(*fractions.shape[:-2], -1).max(-1)


def centroids(fractions: np.ndarray, min_pixels: float) -> tuple[np.ndarray, np.ndarray]:
    """Centroids (..., 2K) and found (..., K) of K surfaces' fractions (..., K, H, W)."""
    centers = pixel_centers(fractions.shape[-1])
    total = fractions.sum(axis=(-2, -1))
    xy = np.einsum("...khw,hwc->...kc", fractions, centers) / np.maximum(total, 1e-9)[..., None]
    found = total >= min_pixels
    xy = np.where(found[..., None], xy, np.nan)
    return xy.reshape(*xy.shape[:-2], -1).astype(np.float32), found
