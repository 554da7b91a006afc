"""Scoring pile sweeping from pixels alone: the pieces in the tray and the pieces seen.

These read nothing but RGB frames (:mod:`iwsim.envs.tabletop.palette`'s colour model with the
task's palette), so they score MuJoCo frames and world-model frames alike.

Counting (measured in ``bench/bench_pilesweep.py``): a piece is ~3 pixels at 64 px and
pieces in a pile touch, so connected components alone undercount. Each component of
piece colour counts as its piece-coloured area over one piece's area, rounded; a
component of one piece is in the tray when its centroid is (the simulator's rule: the
centre), and a component of several pieces is split into that many pieces by k-means on
its pixels, each in the tray when its centre is.
"""

from __future__ import annotations

from functools import lru_cache

import numpy as np

from iwsim.envs.pilesweep.sim import PALETTE, PIECE_RADIUS, in_tray
from iwsim.envs.tabletop.palette import Palette, check_frames, pixel_centers, pusher_centroids
from iwsim.envs.tabletop.scene import VIEW_HALF

PALETTE_MODEL = Palette(PALETTE, first="piece")
MIN_FRACTION = 0.1  # a pixel with more piece colour than this belongs to a component
_EIGHT = np.ones((3, 3), bool)  # components connect diagonally too (a piece's anti-aliased corners)


def piece_area(image_size: int) -> float:
    """One piece's area in pixels at ``image_size``."""
    return float(np.pi * PIECE_RADIUS**2 / (2 * VIEW_HALF / image_size) ** 2)


@lru_cache(maxsize=8)
def _grid(image_size: int) -> tuple[np.ndarray, np.ndarray]:
    centres = pixel_centers(image_size)
    return centres, in_tray(centres)


def piece_fraction(frames: np.ndarray) -> np.ndarray:
    """(..., H, W, 3) uint8 frames -> (..., H, W) float32 share of each pixel that is piece."""
    return PALETTE_MODEL.fractions(frames, ("piece",))[..., 0, :, :]


def find_pieces(fraction: np.ndarray) -> np.ndarray:
    """The pieces seen in one frame's piece fraction (H, W): (n, 2) world positions, one
    per piece (see the module docstring), n = 0 when none is seen."""
    from scipy import ndimage  # here: half a second of every iwsim process's start-up, which imports the tasks

    size = fraction.shape[-1]
    centres, _ = _grid(size)
    one = piece_area(size)
    labels, n = ndimage.label(fraction > MIN_FRACTION, structure=_EIGHT)
    out: list[np.ndarray] = []
    for k, box in enumerate(ndimage.find_objects(labels), start=1):
        if box is None:
            continue
        inside = labels[box] == k
        w = fraction[box][inside].astype(np.float64)
        xy = centres[box][inside]
        count = int(np.rint(w.sum() / one))
        if count == 1:
            out.append((w[:, None] * xy).sum(0) / w.sum())
        elif count > 1:
            out.extend(_split(xy, w, count))
    return np.array(out).reshape(-1, 2)


def _split(xy: np.ndarray, w: np.ndarray, k: int, iterations: int = 8) -> np.ndarray:
    """``k`` centres (k, 2) of weighted points ``xy`` (m, 2): weighted k-means from
    farthest-point seeds (deterministic)."""
    centres = [xy[int(np.argmax(w))]]
    for _ in range(1, k):
        d = np.min(np.linalg.norm(xy[:, None] - np.array(centres)[None], axis=-1), axis=1)
        centres.append(xy[int(np.argmax(d * w))])
    c = np.array(centres)
    for _ in range(iterations):
        nearest = np.argmin(np.linalg.norm(xy[:, None] - c[None], axis=-1), axis=1)
        for j in range(k):
            mine = nearest == j
            if mine.any():
                c[j] = (w[mine, None] * xy[mine]).sum(0) / w[mine].sum()
    return c


def count_pieces(frames: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Pieces in the tray and pieces seen, (...) int64 each, of (..., H, W, 3) uint8 frames."""
    frames = check_frames(frames)
    # frame by frame: the colour model's arrays of a whole batch at once run far slower
    found = [find_pieces(piece_fraction(f)) for f in frames.reshape(-1, *frames.shape[-3:])]
    inside = np.array([int(in_tray(p).sum()) for p in found], np.int64)
    seen = np.array([len(p) for p in found], np.int64)
    return inside.reshape(frames.shape[:-3]), seen.reshape(frames.shape[:-3])


def read_frames(frames: np.ndarray, min_pixels: float = 1.0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """:func:`tray_share`, and the pushers' positions (..., 4) and found (..., 2) of
    (..., H, W, 3) frames (see :func:`~iwsim.envs.tabletop.palette.pusher_centroids`), in one pass
    of the colour model."""
    frames = check_frames(frames)
    flat = frames.reshape(-1, *frames.shape[-3:])
    fractions = np.stack([PALETTE_MODEL.fractions(f, ("piece", "left", "right")) for f in flat])
    found = [find_pieces(f) for f in fractions[:, 0]]
    share = np.array([in_tray(p).sum() / max(len(p), 1) for p in found])
    pos, seen, _ = pusher_centroids(fractions[:, 1:], min_pixels)
    lead = frames.shape[:-3]
    return share.reshape(lead), pos.reshape(*lead, 4), seen.reshape(*lead, 2)


def tray_share(frames: np.ndarray) -> np.ndarray:
    """The task's score from pixels: pieces in the tray over pieces seen, (...) float64 of
    (..., H, W, 3) frames (0 where no piece is seen)."""
    inside, seen = count_pieces(frames)
    return inside / np.maximum(seen, 1)


def pieces_kept(frames: np.ndarray) -> np.ndarray:
    """For world-model rollouts: the pieces seen in each frame over those seen in the
    first, (..., T) float64 of (..., T, H, W, 3) frames (1.0: none lost or made up)."""
    _, seen = count_pieces(frames)
    return seen / np.maximum(seen[..., :1], 1)
