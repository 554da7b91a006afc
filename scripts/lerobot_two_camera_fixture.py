"""Write the test fixture ``tests/data/lerobot_two_cameras``: a LeRobotDataset v3.0 of two
cameras written by LeRobot's own writer, so that the importer (``iwsim data import --format
lerobot-v3``) is checked against the real thing, not only against our reading of its
specification.

It runs in a side venv with the real ``lerobot`` package, which cannot live in the project's
venv, and it does not import iwsim. Make the side venv once, outside the repository::

    python3 -m venv /tmp/lrenv
    /tmp/lrenv/bin/pip install torch==2.14.1 torchvision==0.29.1
    /tmp/lrenv/bin/pip install --no-deps lerobot==0.4.4
    /tmp/lrenv/bin/pip install "datasets>=4,<5" "huggingface-hub>=0.34.2,<0.36" "av>=15,<16" \\
        "jsonlines>=4,<5" "packaging>=24.2,<26" draccus==0.10.0 "einops>=0.8,<0.9" \\
        "deepdiff>=7.0.1,<9" "termcolor>=2.4,<4" "imageio>=2.34,<3" "accelerate>=1.10,<2" pillow

(``--no-deps`` keeps pip from replacing torch or pulling LeRobot's robot and training extras;
the list is what ``lerobot.datasets.lerobot_dataset`` needs to import and write. torchcodec is
not needed to write.) Then, from the repository's root::

    HF_HUB_OFFLINE=1 /tmp/lrenv/bin/python scripts/lerobot_two_camera_fixture.py \\
        --out tests/data/lerobot_two_cameras

It writes 2 episodes of 12 frames at 10 fps: the video features ``observation.images.top``
and ``observation.images.side`` (64 x 64 RGB), ``observation.state`` and ``action`` (4
float32 each) and one task, with LeRobot's default video codec (AV1 by ``libsvtav1``, crf 30,
yuv420p, a key frame every 2 frames; iwsim's reader decodes it with libdav1d; ``--vcodec
h264`` writes H.264 instead). Each view is a flat background with a coloured square moving
across it (right in ``top``, down in ``side``), in a different colour and background per view,
so a test can tell the views apart and every frame from its neighbours. Beside the
dataset, ``<out>.npz`` holds exactly what was written (``top``, ``side``: (E, T, 64, 64, 3)
uint8; ``state``, ``action``: (E, T, 4) float32; ``task``) for the test to compare the
imported store with (``tests/test_formats_lerobot.py``). The content is deterministic (seed
0); the encoder's bytes may differ between runs.
"""

from __future__ import annotations

import argparse
import shutil
from pathlib import Path

import numpy as np

EPISODES, FRAMES, SIZE, FPS, DIM = 2, 12, 64, 10, 4
SQUARE = 16  # side of the moving square, in pixels
TASK = "push the block to the target"
# Per view: its background, the square's colour, the axis the square moves along (0: down, 1: right),
# its step in pixels a frame and where it starts in each episode. The square differs from its
# background in brightness, not only in hue: SVT-AV1 at LeRobot's crf 30 finds motion in the luma
# plane, and a green square on grey of about the same luma came back 2-3 px off in the inter frames.
VIEWS = {"top": ((30, 40, 90), (230, 60, 40), 1, 4, (2, 13)),
         "side": ((110, 110, 110), (240, 220, 40), 0, 5, (3, 9))}


def view_frames(view: str, episode: int) -> np.ndarray:
    """(FRAMES, SIZE, SIZE, 3) uint8: ``view``'s square in ``episode``."""
    background, colour, axis, step, starts = VIEWS[view]
    frames = np.empty((FRAMES, SIZE, SIZE, 3), np.uint8)
    frames[:] = background
    for t in range(FRAMES):
        along = (starts[episode] + step * t) % (SIZE - SQUARE)
        across = SIZE // 2 - SQUARE // 2
        y, x = (along, across) if axis == 0 else (across, along)
        frames[t, y:y + SQUARE, x:x + SQUARE] = colour
    return frames


def make_episodes(seed: int = 0) -> dict[str, np.ndarray]:
    """What the fixture holds: {"top", "side": (E, T, H, W, 3) uint8, "state", "action": (E, T, D) float32}."""
    rng = np.random.default_rng(seed)
    out = {v: np.stack([view_frames(v, e) for e in range(EPISODES)]) for v in VIEWS}
    for v in VIEWS:  # so a frame read from the wrong time or episode cannot pass for the right one
        assert len({f.tobytes() for f in out[v].reshape(-1, SIZE, SIZE, 3)}) == EPISODES * FRAMES, v
    out["state"] = rng.normal(size=(EPISODES, FRAMES, DIM)).astype(np.float32)
    out["action"] = rng.uniform(-1, 1, size=(EPISODES, FRAMES, DIM)).astype(np.float32)
    return out


def features() -> dict[str, dict]:
    video = {"dtype": "video", "shape": (SIZE, SIZE, 3), "names": ["height", "width", "channels"]}
    return {
        **{f"observation.images.{v}": dict(video) for v in VIEWS},
        "observation.state": {"dtype": "float32", "shape": (DIM,), "names": [f"state_{i}" for i in range(DIM)]},
        "action": {"dtype": "float32", "shape": (DIM,), "names": [f"action_{i}" for i in range(DIM)]},
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--out", type=Path, required=True, help="the dataset directory (replaced if it exists)")
    parser.add_argument("--vcodec", default="libsvtav1", help="LeRobot's video codec option (default: its own)")
    args = parser.parse_args()

    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    if args.out.exists():
        shutil.rmtree(args.out)
    episodes = make_episodes()
    dataset = LeRobotDataset.create(repo_id="iwsim/lerobot_two_cameras", root=args.out, fps=FPS, features=features(),
                                    robot_type="iwsim_fixture", use_videos=True, vcodec=args.vcodec)
    for e in range(EPISODES):
        for t in range(FRAMES):
            dataset.add_frame({**{f"observation.images.{v}": episodes[v][e, t] for v in VIEWS},
                               "observation.state": episodes["state"][e, t], "action": episodes["action"][e, t],
                               "task": TASK})
        dataset.save_episode()
    dataset.finalize()
    np.savez_compressed(args.out.with_suffix(".npz"), **episodes, task=np.array(TASK))
    print(f"wrote {args.out} and {args.out.with_suffix('.npz')} ({args.vcodec})")


if __name__ == "__main__":
    main()
