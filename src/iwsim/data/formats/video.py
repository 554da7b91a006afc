"""MP4 videos with PyAV: H.264 in yuv420p, one frame per time step (LeRobot's layout)."""

from __future__ import annotations

from fractions import Fraction
from pathlib import Path
from typing import Final

import numpy as np

from iwsim.data.formats.common import FormatError

CODEC: Final = "libx264"  # written as H.264; info.json names it "h264" as LeRobot's readers report it
CODEC_NAME = "h264"
PIX_FMT = "yuv420p"
OPTIONS = {"crf": "18", "g": "2"}  # near-lossless; a key frame every 2 frames for fast seeking, as LeRobot


class VideoWriter:
    """Append (T, H, W, 3) uint8 frames to one MP4 at ``fps``; frame n has pts n."""

    def __init__(self, path: Path, fps: int, height: int, width: int) -> None:
        import av

        if height % 2 or width % 2:
            raise FormatError(f"{path}: yuv420p video needs even frame sizes, got {height}x{width}.")
        path.parent.mkdir(parents=True, exist_ok=True)
        self.path, self.frames = path, 0
        self._container = av.open(str(path), "w")
        self._stream = self._container.add_stream(CODEC, rate=fps, options=OPTIONS)
        self._stream.width, self._stream.height, self._stream.pix_fmt = width, height, PIX_FMT
        self._stream.time_base = Fraction(1, fps)

    def write(self, frames: np.ndarray) -> None:
        import av

        for f in frames:
            frame = av.VideoFrame.from_ndarray(np.ascontiguousarray(f), format="rgb24")
            frame.pts = self.frames
            self.frames += 1
            for packet in self._stream.encode(frame):
                self._container.mux(packet)

    @property
    def size(self) -> int:
        """Bytes written so far (the file appears only once the encoder gives its first
        packet, which a few short episodes may not yet have made)."""
        return self.path.stat().st_size if self.path.exists() else 0

    def close(self) -> None:
        for packet in self._stream.encode():
            self._container.mux(packet)
        self._container.close()


def write_episode_video(path: Path, frames: np.ndarray, fps: int) -> None:
    """One episode's (T, H, W, 3) uint8 frames as a LeRobot MP4 at ``path`` (the videos
    people watch are :func:`iwsim.eval.video.write_video`'s)."""
    writer = VideoWriter(path, fps, frames.shape[1], frames.shape[2])
    try:
        writer.write(frames)
    finally:
        writer.close()


def read_video(path: Path) -> np.ndarray:
    """All frames of the first video stream as uint8 (N, H, W, 3) RGB."""
    import av

    if not path.is_file():
        raise FormatError(f"{path}: video file is missing.")
    try:
        with av.open(str(path)) as container:
            frames = [f.to_ndarray(format="rgb24") for f in container.decode(video=0)]
    except (av.error.FFmpegError, IndexError, ValueError) as e:
        raise FormatError(f"{path}: not a readable video ({' '.join(str(e).split())[:120]}).") from None
    if not frames:
        raise FormatError(f"{path}: the video holds no frames.")
    return np.stack(frames)


def probe(path: Path) -> dict:
    """Codec, pixel format, size and frame count of the first video stream."""
    import av

    try:
        with av.open(str(path)) as container:
            s = container.streams.video[0]
            n = sum(1 for _ in container.demux(s) if _.size)
            return {"codec": s.codec_context.name, "pix_fmt": s.pix_fmt, "height": s.height, "width": s.width,
                    "frames": n}
    except (av.error.FFmpegError, IndexError, ValueError) as e:
        raise FormatError(f"{path}: not a readable video ({' '.join(str(e).split())[:120]}).") from None
