"""Bimanual T-pushing as a :class:`~iwsim.envs.task.Task`: the pushers' speed limit as the
command-to-executed map, the pixel IoU as the scorer, ``agent_pos`` from the setpoints and
the pushers seen in the frame, MuJoCo resets as initial frames and MuJoCo itself side by
side in play. The one place outside ``envs/pusht.py`` and ``envs/pixels.py`` that knows
about them."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Any

import gymnasium as gym
import numpy as np

from iwsim.envs import make_env
from iwsim.envs.pixels import pixel_iou, pusher_positions, read_frames
from iwsim.envs.pusht import (
    CONTROL_HZ,
    IMAGE_SIZE,
    MAX_STEP,
    SUCCESS_IOU,
    VIEW_HALF,
    WORKSPACE,
    BimanualPushTEnv,
    TaskSpec,
    check_actions,
    limit_targets,
    spaces,
)
from iwsim.envs.task import Bindings, Start, Task

KEY_SPEED = 0.2  # m/s of a target under a held key or a full stick (one key tap: 2 cm)
DRAG_SPEED = 0.3  # m/s at most when a target follows the mouse (the play data's top speed)
SPEC = TaskSpec()
# A pusher seen within this distance (m) of its setpoint is reported at the setpoint. MuJoCo's
# pushers track their setpoints to ~1.3 mm in free space and stop up to ~25 mm short in
# contact (the expert squeezes 20 mm into the stem); a world model draws them 2-4 mm off
# (median; p90 8-9 mm, about a pixel at 64 px), enough to stall the expert's 4 mm approach.
SETPOINT_TOLERANCE = 0.008

# WASD moves the left pusher, IJKL the right one; the left stick the left, the right stick the right.
BINDINGS = Bindings(
    keys=(("w", 1, 1.0), ("s", 1, -1.0), ("a", 0, -1.0), ("d", 0, 1.0),
          ("i", 3, 1.0), ("k", 3, -1.0), ("j", 2, -1.0), ("l", 2, 1.0)),
    axes=((0, 0, 1.0), (1, 1, -1.0), (2, 2, 1.0), (3, 3, -1.0)),
    speed=(KEY_SPEED,) * 4, drag=SPEC.action_points, drag_speed=DRAG_SPEED,
    legend=("left pusher: W A S D or the left stick; right pusher: I J K L or the right stick; "
            "a tap nudges by one step; drag a pusher's ring on the frame.",
            "S moves, so save is Shift+S or Enter."))


@dataclass(frozen=True)
class PushTTask(Task):
    """``iwsim/BimanualPushT-v0`` behind the Task seam (actions ``[lx, ly, rx, ry]`` in metres)."""

    name: str = SPEC.name
    action_low: tuple[float, ...] = SPEC.action_low
    action_high: tuple[float, ...] = SPEC.action_high
    action_names: tuple[str, ...] = SPEC.action_names
    fps: float = float(CONTROL_HZ)
    action_step: tuple[float, ...] = (KEY_SPEED / CONTROL_HZ,) * 4
    action_points: tuple[tuple[int, int], ...] = SPEC.action_points
    view_half: float | None = VIEW_HALF
    bindings: Bindings | None = BINDINGS

    kind = "pusht"
    score_name = "IoU"
    success_score = SUCCESS_IOU
    start_source = "mujoco"
    clip_commands = True  # MuJoCo clips targets to the workspace
    has_ground_truth = True
    # T-push's defaults, read by the commands and the studies through iwsim.tasks.DEFAULT_TASK:
    image_size = IMAGE_SIZE  # the frames collected, trained on and evaluated at (the shipped model's)
    horizon = 600  # steps of an evaluation episode (the paper's T-push horizon)
    checkpoint = "checkpoints/pusht-64"  # the shipped world model

    def spaces(self, image_size: int) -> tuple[gym.spaces.Box, gym.spaces.Dict]:
        return spaces(image_size)

    def check_actions(self, actions: object, shape: tuple[int, ...]) -> np.ndarray:
        return check_actions(actions, shape)

    def executed(self, setpoint: np.ndarray, command: np.ndarray) -> np.ndarray:
        return limit_targets(setpoint, command, MAX_STEP)

    def score(self, frames: np.ndarray) -> np.ndarray:
        return np.asarray(pixel_iou(frames), np.float64)

    def observe(self, frames: np.ndarray, setpoint: np.ndarray, previous: np.ndarray
                ) -> tuple[np.ndarray, np.ndarray]:
        """Pixel IoU (B,) and the pushers' positions (B, 4) after a step that executed
        ``setpoint`` (B, 4), from frames (B, H, W, 3) in one pass: a pusher seen within
        :data:`SETPOINT_TOLERANCE` of its setpoint is at the setpoint (the frame draws it
        only to about a pixel), one seen further away (held back by contact) where it is
        seen, and one not seen keeps its ``previous`` position."""
        iou, pos, found = read_frames(frames)
        setpoint = np.asarray(setpoint, np.float64)
        near = np.linalg.norm((pos - setpoint).reshape(*pos.shape[:-1], 2, 2), axis=-1) <= SETPOINT_TOLERANCE
        pos = np.where(np.repeat(near, 2, axis=-1), setpoint, pos)
        return iou, _hold_unseen(pos, found, previous)

    def read_agent_pos(self, frames: np.ndarray, previous: np.ndarray) -> np.ndarray:
        return _hold_unseen(*pusher_positions(frames), previous)

    def initial_frames(self, image_size: int, store: str | None = None) -> MujocoStarts:
        return MujocoStarts(image_size)

    def start_from_frame(self, frame: np.ndarray, agent_pos: object = None) -> Start:
        pos = self.read_agent_pos(frame[None], np.zeros((1, 4), np.float32))[0] if agent_pos is None else \
            np.asarray(agent_pos, np.float32)
        return Start(frame, pos, pos.astype(np.float64), None)

    def start_from_record(self, frame: np.ndarray, record: dict[str, np.ndarray]) -> Start:
        if "state" not in record:
            return self.start_from_frame(frame)
        pos = np.asarray(record["state"], dtype=np.float32)
        state = None if "block_pose" not in record else np.concatenate([pos, record["block_pose"]]).astype(np.float64)
        return Start(frame, pos, pos.astype(np.float64), state)

    def store_attrs(self) -> dict[str, Any]:
        spec = dataclasses.asdict(SPEC)
        spec["task"] = spec.pop("name")
        return spec

    def ground_truth_env(self, image_size: int) -> gym.Env:
        return make_env("pusht", image_size)


class MujocoStarts:
    """T-push's initial frames: MuJoCo resets (seeded; or an explicit ``[lx, ly, rx, ry, bx,
    by, byaw]`` state)."""

    def __init__(self, image_size: int) -> None:
        self.image_size = image_size
        self._env: gym.Env | None = None

    def draw(self, seed: int, state: object = None) -> Start:
        if self._env is None:
            self._env = make_env("pusht", self.image_size)
        obs, _ = self._env.reset(seed=int(seed), options=None if state is None else {"reset_to_state": state})
        pos = obs["agent_pos"]
        sim = self._env.unwrapped
        assert isinstance(sim, BimanualPushTEnv)  # what make_env("pusht") wraps
        return Start(obs["pixels"], pos, pos.astype(np.float64), sim.get_state())

    def close(self) -> None:
        if self._env is not None:
            self._env.close()
            self._env = None


def _hold_unseen(pos: np.ndarray, found: np.ndarray, previous: np.ndarray) -> np.ndarray:
    pos = np.where(np.repeat(~found, 2, axis=-1), previous, pos)
    return np.clip(pos, -WORKSPACE, WORKSPACE).astype(np.float32)
