"""Writing frames people look at: MP4 videos (ffmpeg via imageio), written atomically."""

from __future__ import annotations

import os
from pathlib import Path

import imageio.v2 as imageio
import numpy as np

from iwsim.core.errors import InputError


def upscale(frames: np.ndarray, factor: int) -> np.ndarray:
    """(..., H, W, C) -> (..., H*f, W*f, C) by pixel repetition (keeps pixels crisp)."""
    return np.repeat(np.repeat(frames, factor, axis=-3), factor, axis=-2)


def score_bar(values: np.ndarray, width: int, height: int, threshold: float) -> np.ndarray:
    """(T,) scores in [0, 1] -> (T, height, width, 3) uint8 bars: green at or above
    ``threshold``, orange below, on dark grey."""
    values = np.clip(np.asarray(values, dtype=np.float64), 0.0, 1.0)
    bars = np.full((len(values), height, width, 3), 40, np.uint8)
    for bar, v in zip(bars, values):
        bar[:, : int(round(v * width))] = (60, 190, 80) if v >= threshold else (230, 140, 40)
    return bars


def write_video(path: str | os.PathLike, frames: np.ndarray, fps: float) -> Path:
    """Write (T, H, W, 3) uint8 frames to an H.264 MP4 for people to watch at ``path``; the
    file appears only when complete (datasets' videos: :mod:`iwsim.data.formats.video`).
    H and W should be multiples of 16 for every player to accept them."""
    frames = np.asarray(frames)
    if frames.ndim != 4 or frames.shape[-1] != 3 or frames.dtype != np.uint8:
        raise InputError(f"expected (T, H, W, 3) uint8 frames, got {frames.shape} {frames.dtype}.")
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.stem}.tmp{path.suffix}")
    writer = imageio.get_writer(tmp, fps=fps, codec="libx264", quality=8, macro_block_size=1, ffmpeg_log_level="error")
    with writer:  # (not `as`: imageio's stub types what __enter__ returns, the writer itself, as its base class)
        for f in frames:
            writer.append_data(f)
    os.replace(tmp, path)
    return path
