"""The tasks: their MuJoCo ground truth, scripted policies and pixel scorers, one folder
each (:mod:`iwsim.envs.pusht`, :mod:`iwsim.envs.pilesweep`, over the shared
:mod:`iwsim.envs.tabletop`); the Task seam every other layer reaches them through
(:mod:`iwsim.envs.task`), the registry of tasks (:mod:`iwsim.envs.registry`, also the generic
task of any robot's store) and collection into a store (:mod:`iwsim.envs.collect`). The
Gymnasium envs over a learned world model live with the model, in
:mod:`iwsim.world_model.env`."""

from __future__ import annotations

import os
from collections import OrderedDict

os.environ.setdefault("MUJOCO_GL", "egl")  # before any task module imports mujoco: headless rendering

import gymnasium as gym  # noqa: E402
import numpy as np  # noqa: E402

from iwsim.core.errors import InputError  # noqa: E402

TASKS = {"pusht": "iwsim/BimanualPushT-v0", "pilesweep": "iwsim/PileSweep-v0"}
IMAGE_SIZES = (64, 96, 128)  # what the MuJoCo tasks render
SMALLEST_FRAME_BYTES = min(IMAGE_SIZES) ** 2 * 3  # an RGB frame's lower bound, for memory checks
# The scripted policies of each task, by name (its scripted module makes them; iwsim collect records them).
POLICIES = {"pusht": ("play", "play-broad", "play-press", "expert", "expert-wide", "expert-noisy", "expert-lagged",
                      "expert-hands", "expert-imprecise"),
            "pilesweep": ("play", "expert", "expert-noisy", "expert-lagged")}


def pixels_space(image_size: int, cameras: tuple[str, ...] = ("top",)) -> gym.spaces.Space:
    """An observation's ``pixels``: one (H, W, 3) uint8 frame, or {camera: frame} with several
    cameras (gym-aloha's convention; LeRobot reads either as ``observation.image(s)``)."""
    frame = gym.spaces.Box(0, 255, (image_size, image_size, 3), np.uint8)
    # in the cameras' order (a plain dict would be sorted by name, putting "side" before "top"): the
    # first is the view a pixel scorer and a scripted pixel policy read (iwsim.data.views.first_view)
    return frame if len(cameras) == 1 else gym.spaces.Dict(OrderedDict((c, frame) for c in cameras))


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
