"""Pile sweeping as a :class:`~iwsim.envs.task.Task`: the tabletop's pushers
(:mod:`iwsim.envs.tabletop.task`), the share of the pieces seen that lie in the tray as
the scorer (:mod:`iwsim.envs.pilesweep.pixels`) and the task's scripted policies
(:mod:`iwsim.envs.pilesweep.scripted`: all read only the frame, so the expert and play run
inside a world model too). Its simulator for evaluation (:meth:`PileSweepTask.ground_truth_env`)
reports the pieces padded to one shape, so that a vector env steps many. The task's own
defaults live here and in :mod:`iwsim.envs.pilesweep.sim`."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import gymnasium as gym
import numpy as np

from iwsim.envs.pilesweep import scripted as pilesweep_scripted
from iwsim.envs.pilesweep.pixels import PALETTE_MODEL, read_frames, tray_share
from iwsim.envs.pilesweep.sim import HORIZON, IMAGE_SIZE, SUCCESS, TaskSpec, padded
from iwsim.envs.tabletop.scripting import ScriptedPolicy
from iwsim.envs.tabletop.task import TabletopTask

SPEC = TaskSpec()


@dataclass(frozen=True)
class PileSweepTask(TabletopTask):
    """``iwsim/PileSweep-v0`` behind the Task seam (actions ``[lx, ly, rx, ry]`` in metres).
    Its score from pixels is the pieces seen in the tray over the pieces seen (the
    simulator's: over the pieces there are; the two agree while a frame shows every piece)."""

    name: str = SPEC.name

    kind = "pilesweep"
    score_name = "share in tray"
    success_score = SUCCESS
    spec = SPEC
    palette = PALETTE_MODEL
    state_keys = ("pieces",)
    episode_score = "score"
    image_size = IMAGE_SIZE  # the frames collected, trained on and evaluated at
    horizon = HORIZON  # steps of an evaluation episode (the paper's pile-sweeping horizon)
    pixel_policies = pilesweep_scripted.PIXEL_POLICIES
    pixel_experts = ("expert",)
    pixel_reading = "pieces"
    checkpoint = "checkpoints/pilesweep-64"  # the shipped world model

    def score(self, frames: np.ndarray) -> np.ndarray:
        return np.asarray(tray_share(frames), np.float64)

    def read(self, frames: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        return read_frames(frames)

    def ground_truth_env(self, image_size: int | None = None, start: str = "random",
                         cameras: tuple[str, ...] = ("top",)) -> gym.Env:
        return PaddedPieces(super().ground_truth_env(image_size, start, cameras))

    def pixel_policy(self, kind: str, seed: int, rng: np.random.Generator, miss: float = 0.0) -> ScriptedPolicy:
        return pilesweep_scripted.pixel_policy(kind, seed, rng, miss)

    def record_episode(self, policy: str, seed: int, steps: int, image_size: int,
                       cameras: tuple[str, ...] = ("top",)) -> dict[str, np.ndarray]:
        return pilesweep_scripted.record_episode(policy, seed, steps, image_size, cameras)


class PaddedPieces(gym.Wrapper):
    """``info["pieces"]`` padded to one shape (:func:`~iwsim.envs.pilesweep.sim.padded`, NaN past
    the episode's pieces), as stores hold it: a vector env stacks its environments' infos,
    whose piles differ in size."""

    def reset(self, **kwargs: Any) -> tuple[Any, dict[str, Any]]:
        obs, info = self.env.reset(**kwargs)
        return obs, {**info, "pieces": padded(info["pieces"])}

    def step(self, action: Any) -> tuple[Any, Any, bool, bool, dict[str, Any]]:
        obs, reward, terminated, truncated, info = self.env.step(action)
        return obs, reward, terminated, truncated, {**info, "pieces": padded(info["pieces"])}
