"""Tasks (MuJoCo ground truth), their scripted policies and pixel scorers: the ground truth
only. Two tasks share one tabletop (:mod:`iwsim.envs.tabletop`): T-push (:mod:`iwsim.envs.pusht`,
:mod:`iwsim.envs.pixels`, :mod:`iwsim.envs.scripted`) and pile sweeping
(:mod:`iwsim.envs.pilesweep` and its ``_pixels`` and ``_scripted`` modules). The Gymnasium
envs over a learned world model live above the models, in :mod:`iwsim.world_model_env`."""

from __future__ import annotations

import os

os.environ.setdefault("MUJOCO_GL", "egl")  # before any task module imports mujoco: headless rendering

import gymnasium as gym  # noqa: E402
from gymnasium.envs.registration import register, registry  # noqa: E402

from iwsim.errors import InputError  # noqa: E402

if "iwsim/BimanualPushT-v0" not in registry:
    register(
        id="iwsim/BimanualPushT-v0",
        entry_point="iwsim.envs.pusht:BimanualPushTEnv",
        max_episode_steps=600,  # the paper's evaluation horizon
    )

if "iwsim/PileSweep-v0" not in registry:
    register(
        id="iwsim/PileSweep-v0",
        entry_point="iwsim.envs.pilesweep:PileSweepEnv",
        max_episode_steps=200,  # the paper's pile-sweeping horizon
    )

if "iwsim/WorldModel-v0" not in registry:
    register(
        id="iwsim/WorldModel-v0",
        entry_point="iwsim.world_model_env:WorldModelEnv",
        max_episode_steps=600,
    )

TASKS = {"pusht": "iwsim/BimanualPushT-v0", "pilesweep": "iwsim/PileSweep-v0"}
IMAGE_SIZES = (64, 96, 128)  # what the MuJoCo tasks render
SMALLEST_FRAME_BYTES = min(IMAGE_SIZES) ** 2 * 3  # an RGB frame's lower bound, for memory checks
# The scripted policies of each task, by name (its scripted module makes them; iwsim collect records them).
POLICIES = {"pusht": ("play", "play-broad", "play-press", "expert", "expert-wide", "expert-noisy", "expert-lagged",
                      "expert-hands", "expert-imprecise"),
            "pilesweep": ("play", "expert", "expert-noisy", "expert-lagged")}


def check_task(task: str) -> str:
    """Return the Gymnasium id of ``task`` or raise a one-line ValueError."""
    if task not in TASKS:
        raise InputError(f"unknown task {task!r}; expected one of {sorted(TASKS)}.")
    return TASKS[task]


def make_env(task: str, image_size: int | None = None, **kwargs) -> gym.Env:
    """The task's environment without a time limit (episode length is the caller's), its
    frames ``image_size`` pixels square (None: the task's own size, its environment's default)."""
    if image_size is not None:
        kwargs["image_size"] = image_size
    return gym.make(check_task(task), max_episode_steps=None, **kwargs)
