"""Tasks (MuJoCo ground truth), their scripted policies (:mod:`iwsim.envs.scripted`) and
pixel scorers (:mod:`iwsim.envs.pixels`): the ground truth only. The Gymnasium envs over a
learned world model live above the models, in :mod:`iwsim.world_model_env`."""

from __future__ import annotations

import gymnasium as gym
from gymnasium.envs.registration import register, registry

from iwsim.errors import InputError

if "iwsim/BimanualPushT-v0" not in registry:
    register(
        id="iwsim/BimanualPushT-v0",
        entry_point="iwsim.envs.pusht:BimanualPushTEnv",
        max_episode_steps=600,  # the paper's evaluation horizon
    )

if "iwsim/WorldModel-v0" not in registry:
    register(
        id="iwsim/WorldModel-v0",
        entry_point="iwsim.world_model_env:WorldModelEnv",
        max_episode_steps=600,
    )

TASKS = {"pusht": "iwsim/BimanualPushT-v0"}
IMAGE_SIZES = (64, 96, 128)  # what the MuJoCo tasks render
SMALLEST_FRAME_BYTES = min(IMAGE_SIZES) ** 2 * 3  # an RGB frame's lower bound, for memory checks
POLICIES = ("play", "play-broad", "expert", "expert-noisy", "expert-lagged", "expert-hands",
            "expert-imprecise")


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
