"""What the tabletop tasks (:mod:`iwsim.envs.tabletop.scene`) share behind the Task seam: the
pushers' speed limit as the command-to-executed map, their teleop bindings, ``agent_pos``
from the setpoints and the pushers seen in the frame, MuJoCo resets as initial frames and
MuJoCo itself side by side in play. A tabletop task (:class:`TabletopTask`) adds its
name, palette, spec, pixel scorer and scripted policies."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Any, ClassVar

import gymnasium as gym
import numpy as np

from iwsim.core.errors import InputError
from iwsim.data.views import stack_views
from iwsim.envs import POLICIES, make_env
from iwsim.envs.tabletop.palette import Palette
from iwsim.envs.tabletop.scene import (
    ACTION_NAMES,
    ACTION_POINTS,
    CAMERAS,
    CONTROL_HZ,
    MAX_STEP,
    VIEW_HALF,
    WORKSPACE,
    TabletopEnv,
    TabletopSpec,
    check_actions,
    limit_targets,
    spaces,
)
from iwsim.envs.tabletop.scripting import camera_kwargs
from iwsim.envs.task import Bindings, Start, Task

KEY_SPEED = 0.2  # m/s of a target under a held key or a full stick (one key tap: 2 cm)
DRAG_SPEED = 0.3  # m/s at most when a target follows the mouse (the play data's top speed)
# A pusher seen within this distance (m) of its setpoint is reported at the setpoint. MuJoCo's
# pushers track their setpoints closely in free space and stop short in contact (T-push's
# expert squeezes 20 mm into the stem); a world model draws them a few mm off, enough to
# stall the expert's 4 mm approach if read from pixels alone (bench/pusher_state.py and
# the yardstick record both).
SETPOINT_TOLERANCE = 0.008

# WASD moves the left pusher, IJKL the right one; the left stick the left, the right stick the right.
BINDINGS = Bindings(
    keys=(("w", 1, 1.0), ("s", 1, -1.0), ("a", 0, -1.0), ("d", 0, 1.0),
          ("i", 3, 1.0), ("k", 3, -1.0), ("j", 2, -1.0), ("l", 2, 1.0)),
    axes=((0, 0, 1.0), (1, 1, -1.0), (2, 2, 1.0), (3, 3, -1.0)),
    speed=(KEY_SPEED,) * 4, drag=ACTION_POINTS, drag_speed=DRAG_SPEED,
    legend=("left pusher: W A S D or the left stick; right pusher: I J K L or the right stick; "
            "a tap nudges by one step; drag a pusher's ring on the frame.",
            "S moves, so save is Shift+S or Enter."))


@dataclass(frozen=True)
class TabletopTask(Task):
    """A tabletop task behind the Task seam (actions ``[lx, ly, rx, ry]`` in metres).

    A subclass names its ``kind`` (its key in ``iwsim.envs.TASKS``), ``spec`` (what its
    stores carry), ``palette`` (its colour model) and ``state_keys``, and reads its frames
    (:meth:`read`: scores and the pushers in one pass of the colour model)."""

    action_low: tuple[float, ...] = (-WORKSPACE,) * 4
    action_high: tuple[float, ...] = (WORKSPACE,) * 4
    action_names: tuple[str, ...] = ACTION_NAMES
    fps: float = float(CONTROL_HZ)
    action_step: tuple[float, ...] = (KEY_SPEED / CONTROL_HZ,) * 4
    action_points: tuple[tuple[int, int], ...] = ACTION_POINTS
    view_half: float | None = VIEW_HALF
    bindings: Bindings | None = BINDINGS

    cameras = CAMERAS
    start_source = "mujoco"
    clip_commands = True  # MuJoCo clips targets to the workspace
    has_ground_truth = True
    spec: ClassVar[TabletopSpec]
    palette: ClassVar[Palette]

    @property
    def scripted_policies(self) -> tuple[str, ...]:
        return POLICIES[self.kind]

    def spaces(self, image_size: int, cameras: tuple[str, ...] = ("top",)) -> tuple[gym.spaces.Box, gym.spaces.Dict]:
        return spaces(image_size, cameras)

    def check_actions(self, actions: object, shape: tuple[int, ...]) -> np.ndarray:
        return check_actions(actions, shape)

    def executed(self, setpoint: np.ndarray, command: np.ndarray) -> np.ndarray:
        return limit_targets(setpoint, command, MAX_STEP)

    def read(self, frames: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Scores (B,), pusher positions (B, 4) and found (B, 2) of frames (B, H, W, 3)."""
        raise NotImplementedError

    def observe(self, frames: np.ndarray, setpoint: np.ndarray, previous: np.ndarray,
                predicted: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        """Scores (B,) and the pushers' positions (B, 4) after a step that executed
        ``setpoint`` (B, 4), from frames (B, H, W, 3) in one pass: a pusher seen within
        :data:`SETPOINT_TOLERANCE` of its setpoint is at the setpoint (the frame draws it
        only to about a pixel), one seen further away (held back by contact) where it is
        seen, and one not seen where a world model ``predicted`` (B, 4) it, else at its
        ``previous`` position. (A model's own prediction only where the frame does not show the
        pusher: a state head on 8 x 8 latents misses contact by ~14 mm where the frame's
        reading is off by ~5, and a closed loop reading the head's breaks; bench/results/ablations.md.)"""
        scores, pos, found = self.read(frames)
        setpoint = np.asarray(setpoint, np.float64)
        near = np.linalg.norm((pos - setpoint).reshape(*pos.shape[:-1], 2, 2), axis=-1) <= SETPOINT_TOLERANCE
        pos = np.where(np.repeat(near, 2, axis=-1), setpoint, pos)
        return scores, _hold_unseen(pos, found, previous if predicted is None else predicted)

    def read_agent_pos(self, frames: np.ndarray, previous: np.ndarray) -> np.ndarray:
        return _hold_unseen(*self.palette.pusher_positions(frames), previous)

    def initial_frames(self, image_size: int, store: str | None = None,
                       cameras: tuple[str, ...] = ("top",)) -> MujocoStarts:
        return MujocoStarts(self.kind, image_size, cameras)

    def start_from_frame(self, frame: np.ndarray, agent_pos: object = None) -> Start:
        top = frame[None, ..., :3]  # the first view (the top camera's) shows where the pushers are
        pos = self.read_agent_pos(top, np.zeros((1, 4), np.float32))[0] if agent_pos is None else \
            np.asarray(agent_pos, np.float32)
        return Start(frame, pos, pos.astype(np.float64), None)

    def start_from_record(self, frame: np.ndarray, record: dict[str, np.ndarray]) -> Start:
        if "state" not in record:
            return self.start_from_frame(frame)
        pos = np.asarray(record["state"], dtype=np.float32)
        state = None if not all(k in record for k in self.state_keys) else \
            np.concatenate([pos, *(np.ravel(record[k]) for k in self.state_keys)]).astype(np.float64)
        return Start(frame, pos, pos.astype(np.float64), state)

    def store_attrs(self) -> dict[str, Any]:
        spec = dataclasses.asdict(self.spec)
        spec["task"] = spec.pop("name")
        return spec

    def ground_truth_env(self, image_size: int | None = None, start: str = "random",
                         cameras: tuple[str, ...] = ("top",)) -> gym.Env:
        if start not in self.starts:
            raise InputError(f"start must be one of {', '.join(self.starts)} for task {self.name!r}, got {start!r}.")
        return make_env(self.kind, image_size, **({} if start == "random" else {"start": start}),
                        **camera_kwargs(cameras))


class MujocoStarts:
    """A tabletop task's initial frames: MuJoCo resets of task ``kind`` (seeded; or an
    explicit state, as its environment's ``reset_to_state`` takes it), seen by ``cameras``
    (several: stacked along the channels)."""

    def __init__(self, kind: str, image_size: int, cameras: tuple[str, ...] = ("top",)) -> None:
        self.kind, self.image_size, self.cameras = kind, image_size, tuple(cameras)
        self._env: gym.Env | None = None

    def draw(self, seed: int, state: object = None) -> Start:
        if self._env is None:
            self._env = make_env(self.kind, self.image_size, **camera_kwargs(self.cameras))
        obs, _ = self._env.reset(seed=int(seed), options=None if state is None else {"reset_to_state": state})
        pos = obs["agent_pos"]
        sim = self._env.unwrapped
        assert isinstance(sim, TabletopEnv)  # what make_env makes of a tabletop task
        pixels = obs["pixels"]
        frame = stack_views([pixels[c] for c in self.cameras]) if isinstance(pixels, dict) else pixels
        return Start(frame, pos, pos.astype(np.float64), sim.get_state())

    def close(self) -> None:
        if self._env is not None:
            self._env.close()
            self._env = None


def _hold_unseen(pos: np.ndarray, found: np.ndarray, previous: np.ndarray) -> np.ndarray:
    pos = np.where(np.repeat(~found, 2, axis=-1), previous, pos)
    return np.clip(pos, -WORKSPACE, WORKSPACE).astype(np.float32)
