"""Bimanual T-pushing as a :class:`~iwsim.envs.task.Task`: the tabletop's pushers
(:mod:`iwsim.envs.tabletop.task`), the pixel IoU as the scorer and T-push's scripted
policies. Outside envs/pusht/, the rest of the code knows T-push only through it."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from iwsim.envs.pusht import scripted
from iwsim.envs.pusht.pixels import PALETTE_MODEL, estimate_block_pose, pixel_iou, read_frames
from iwsim.envs.pusht.sim import IMAGE_SIZE, STARTS, SUCCESS_IOU, TaskSpec
from iwsim.envs.tabletop.scripting import ScriptedPolicy
from iwsim.envs.tabletop.task import TabletopTask

SPEC = TaskSpec()


@dataclass(frozen=True)
class PushTTask(TabletopTask):
    """``iwsim/BimanualPushT-v0`` behind the Task seam (actions ``[lx, ly, rx, ry]`` in metres)."""

    name: str = SPEC.name

    kind = "pusht"
    score_name = "IoU"
    success_score = SUCCESS_IOU
    spec = SPEC
    palette = PALETTE_MODEL
    state_keys = ("block_pose",)
    episode_score = "iou"
    # T-push's defaults, read by the commands and the studies through iwsim.envs.registry.DEFAULT_TASK:
    image_size = IMAGE_SIZE  # the frames collected, trained on and evaluated at (the shipped model's)
    horizon = 600  # steps of an evaluation episode (the paper's T-push horizon)
    checkpoint = "checkpoints/pusht-64"  # the shipped world model
    starts = STARTS
    pixel_policies = scripted.PIXEL_POLICIES
    pixel_experts = tuple(scripted.EXPERTS)
    pixel_reading = "block pose"

    def score(self, frames: np.ndarray) -> np.ndarray:
        return np.asarray(pixel_iou(frames), np.float64)

    def plausibility(self, frames: np.ndarray) -> np.ndarray:
        """The fit of a rigid T's outline to the block's pixels (0 where too little block
        shows to fit one): about 0.95 in MuJoCo's frames, lower where the block bends."""
        return np.array([estimate_block_pose(f).fit_iou for f in frames], np.float64)

    def read(self, frames: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        return read_frames(frames)

    def pixel_policy(self, kind: str, seed: int, rng: np.random.Generator, miss: float = 0.0) -> ScriptedPolicy:
        return scripted.pixel_policy(kind, seed, rng, miss)

    def record_episode(self, policy: str, seed: int, steps: int, image_size: int,
                       cameras: tuple[str, ...] = ("top",)) -> dict[str, np.ndarray]:
        return scripted.record_episode("pusht", policy, seed, steps, image_size, cameras)
