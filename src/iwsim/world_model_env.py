"""The world model as a Gymnasium environment, with the spaces of ``iwsim/BimanualPushT-v0``.

    env = gym.make("iwsim/WorldModel-v0", checkpoint="checkpoints/pusht-64")
    obs, info = env.reset(seed=100000)   # the MuJoCo task's initial frame for that seed
    obs, reward, terminated, truncated, info = env.step(action)

Initial frames come from ``reset_source``: ``"mujoco"`` (a fresh MuJoCo reset with the
given seed, so a policy starts from the same state in both environments), ``"store"``
(a random frame of the episode store ``store``), or ``reset(options={"frame": f})``.
``agent_pos`` is read from the frame (the pushers' colours), and ``info["iou"]``
and the reward come from the pixel scorer, so nothing but the model's pixels is used.
Actions are commanded targets, approached at the task's speed limit exactly as MuJoCo
does (:func:`iwsim.envs.pusht.limit_targets`, starting from the pushers' positions at
reset); the model is conditioned on that executed motion (``info["target"]``).

:class:`WorldModelVectorEnv` steps many environments in one forward pass. Its episodes
run in lockstep (all start together and are truncated together after
``max_episode_steps``), which is what policy evaluation needs.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np
from gymnasium.vector import AutoresetMode, VectorEnv
from gymnasium.vector.utils import batch_space

from iwsim.data.store import EpisodeStore
from iwsim.envs import make_env
from iwsim.envs.pixels import pixel_iou, pusher_positions, read_frames
from iwsim.envs.pusht import CONTROL_HZ, SUCCESS_IOU, WORKSPACE, check_actions, limit_targets, spaces
from iwsim.errors import InputError
from iwsim.world_model import WorldModel

SOURCES = ("mujoco", "store")


@dataclass(frozen=True)
class Start:
    """An initial frame (H, W, 3) uint8, its pusher positions (4,) and, when known, the
    MuJoCo state ``[lx, ly, rx, ry, bx, by, byaw]`` that renders it (``reset_to_state``)."""

    frame: np.ndarray
    agent_pos: np.ndarray
    state: np.ndarray | None


class Starts:
    """Initial frames from MuJoCo resets or from a random frame of an episode store."""

    def __init__(self, source: str, image_size: int, store: str | Path | None, task: str) -> None:
        if source not in SOURCES:
            raise InputError(f"reset_source must be one of {SOURCES}, got {source!r}.")
        if source == "store" and store is None:
            raise InputError("reset_source 'store' needs store=<path of an episode store>.")
        self.source, self.image_size, self.task = source, image_size, task
        self._env: gym.Env | None = None
        self._store = None
        if store is not None:
            self._store = EpisodeStore.open(store, "r")
            size = self._store.array("img").shape[1]
            if size != image_size:
                raise InputError(f"{store} holds {size}x{size} frames; the world model needs "
                                 f"{image_size}x{image_size}.")

    @property
    def has_store(self) -> bool:
        return self._store is not None

    def draw(self, seed: int, source: str | None = None, state: Any = None) -> Start:
        """The start for ``seed`` (and, for MuJoCo, an explicit ``state`` if given)."""
        source = source or self.source
        if source == "mujoco":
            if self._env is None:
                self._env = make_env(self.task, self.image_size)
            obs, _ = self._env.reset(seed=int(seed), options=None if state is None else {"reset_to_state": state})
            return Start(obs["pixels"], obs["agent_pos"], self._env.unwrapped.get_state())
        if source != "store" or self._store is None:
            raise InputError(f"reset source {source!r} is not available; expected one of {SOURCES} "
                             "(and a store for 'store').")
        rng = np.random.default_rng(seed)
        ends = self._store.episode_ends
        e = int(rng.integers(len(ends)))
        start = 0 if e == 0 else int(ends[e - 1])
        i = int(rng.integers(start, ends[e]))
        frame = np.asarray(self._store.array("img")[i])
        if "state" not in self._store.keys:
            return Start(frame, read_agent_pos(frame[None], np.zeros((1, 4), np.float32))[0], None)
        pos = np.asarray(self._store.array("state")[i], dtype=np.float32)
        state = None
        if "block_pose" in self._store.keys:
            state = np.concatenate([pos, self._store.array("block_pose")[i]]).astype(np.float64)
        return Start(frame, pos, state)

    def close(self) -> None:
        if self._env is not None:
            self._env.close()
            self._env = None


def read_agent_pos(frames: np.ndarray, previous: np.ndarray) -> np.ndarray:
    """Pusher positions read from frames (B, H, W, 3); a pusher not seen keeps its previous position."""
    return _hold_unseen(*pusher_positions(frames), previous)


def observe(frames: np.ndarray, previous: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Pixel IoU (B,) and pusher positions (B, 4) (as :func:`read_agent_pos`) of frames
    (B, H, W, 3), in one pass of the colour segmentation."""
    iou, pos, found = read_frames(frames)
    return iou, _hold_unseen(pos, found, previous)


def _hold_unseen(pos: np.ndarray, found: np.ndarray, previous: np.ndarray) -> np.ndarray:
    pos = np.where(np.repeat(~found, 2, axis=-1), previous, pos)
    return np.clip(pos, -WORKSPACE, WORKSPACE).astype(np.float32)


def _load(model: WorldModel | None, checkpoint: str | Path | None, device: str) -> WorldModel:
    if model is not None:
        return model
    if checkpoint is None:
        raise InputError("WorldModel-v0 needs checkpoint=<world-model checkpoint directory> (or model=...).")
    return WorldModel.load(checkpoint, device)


class WorldModelEnv(gym.Env):
    """One world-model rollout behind the Gymnasium API (see the module docstring)."""

    metadata = {"render_modes": ["rgb_array"], "render_fps": CONTROL_HZ}

    def __init__(self, checkpoint: str | Path | None = None, *, model: WorldModel | None = None,
                 reset_source: str = "mujoco", store: str | Path | None = None, task: str = "pusht",
                 device: str = "cpu", render_mode: str | None = "rgb_array",
                 terminate_on_success: bool = False) -> None:
        if render_mode not in (None, "rgb_array"):
            raise InputError(f"render_mode must be 'rgb_array' or None, got {render_mode!r}.")
        self.model = _load(model, checkpoint, device)
        if self.model.action_dim != 4:
            raise InputError(f"the world model takes {self.model.action_dim}-D actions; {task} needs 4.")
        self.render_mode, self.terminate_on_success = render_mode, terminate_on_success
        self.action_space, self.observation_space = spaces(self.model.image_size)
        self._starts = Starts(reset_source, self.model.image_size, store, task)
        self._frame: np.ndarray | None = None
        self._agent_pos = np.zeros(4, np.float32)

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        super().reset(seed=seed)
        options = dict(options or {})
        unknown = set(options) - {"frame", "agent_pos", "source", "reset_to_state"}
        if unknown:
            raise InputError(f"unknown reset options {sorted(unknown)}; expected frame, agent_pos, source, "
                             "reset_to_state.")
        # the start's seed and the model's noise seed: the given seed, as in the vector env
        draw = int(self.np_random.integers(2**31)) if seed is None else seed
        if "frame" in options:
            frame = self.model.check_frames(np.asarray(options["frame"])[None], 4).numpy()[0]
            pos = options.get("agent_pos")
            pos = read_agent_pos(frame[None], np.zeros((1, 4), np.float32))[0] if pos is None else pos
        else:
            start = self._starts.draw(draw, options.get("source"), options.get("reset_to_state"))
            frame, pos = start.frame, start.agent_pos
        self.model.reset(frame[None], seed=draw)
        self._frame, self._agent_pos = frame, np.asarray(pos, dtype=np.float32)
        self._setpoint = self._agent_pos.astype(np.float64)
        return self._obs(), self._info()

    def step(self, action):
        if self._frame is None:
            raise RuntimeError("call reset() before step().")
        self._setpoint = limit_targets(self._setpoint, check_actions(action, (4,)))
        self._frame = self.model.step(self._setpoint.astype(np.float32)[None])[0]
        self._agent_pos = read_agent_pos(self._frame[None], self._agent_pos[None])[0]
        info = {**self._info(), "target": self._setpoint.astype(np.float32)}
        terminated = bool(self.terminate_on_success and info["is_success"])
        return self._obs(), float(info["iou"]), terminated, False, info

    def _obs(self) -> dict[str, np.ndarray]:
        return {"pixels": self._frame, "agent_pos": self._agent_pos.copy()}

    def _info(self) -> dict[str, Any]:
        iou = float(pixel_iou(self._frame))
        return {"iou": iou, "is_success": iou >= SUCCESS_IOU}

    def render(self):
        return None if self.render_mode is None else self._frame

    def close(self) -> None:
        self._starts.close()


class WorldModelVectorEnv(VectorEnv):
    """``num_envs`` world-model rollouts stepped in one batched forward pass.

    ``reset(seed=s)`` starts env i from seed ``s + i``. All episodes are truncated together
    after ``max_episode_steps``; the following ``step`` resets them all (Gymnasium's
    next-step autoreset) from the next seeds.
    """

    metadata = {"render_modes": ["rgb_array"], "render_fps": CONTROL_HZ, "autoreset_mode": AutoresetMode.NEXT_STEP}

    def __init__(self, num_envs: int, checkpoint: str | Path | None = None, *, model: WorldModel | None = None,
                 reset_source: str = "mujoco", store: str | Path | None = None, task: str = "pusht",
                 device: str = "cpu", max_episode_steps: int = 600) -> None:
        if num_envs < 1 or max_episode_steps < 1:
            raise InputError(f"num_envs and max_episode_steps must be >= 1, got {num_envs}, {max_episode_steps}.")
        self.model = _load(model, checkpoint, device)
        self.num_envs, self.max_episode_steps = num_envs, max_episode_steps
        self.single_action_space, self.single_observation_space = spaces(self.model.image_size)
        self.action_space = batch_space(self.single_action_space, num_envs)
        self.observation_space = batch_space(self.single_observation_space, num_envs)
        self.render_mode = "rgb_array"
        self._starts = Starts(reset_source, self.model.image_size, store, task)
        self._frames: np.ndarray | None = None
        self._agent_pos = np.zeros((num_envs, 4), np.float32)
        self._t = 0
        self._next_seed = 0
        self._needs_reset = False

    def reset(self, *, seed: int | list[int] | None = None, options: dict | None = None):
        options = dict(options or {})
        if seed is None:
            seeds = [self._next_seed + i for i in range(self.num_envs)]
        elif isinstance(seed, int):
            seeds = [seed + i for i in range(self.num_envs)]
        else:
            seeds = [int(s) for s in seed]
            if len(seeds) != self.num_envs:
                raise InputError(f"got {len(seeds)} seeds for {self.num_envs} environments.")
        self._next_seed = max(seeds) + 1
        if "frames" in options:
            frames = self.model.check_frames(np.asarray(options["frames"]), 4).numpy()
            if len(frames) != self.num_envs:
                raise InputError(f"got {len(frames)} frames for {self.num_envs} environments.")
            pos = np.asarray(options.get("agent_pos", read_agent_pos(frames, np.zeros((len(frames), 4), np.float32))))
        else:
            drawn = [self._starts.draw(s, options.get("source")) for s in seeds]
            frames = np.stack([d.frame for d in drawn])
            pos = np.stack([d.agent_pos for d in drawn])
        self.model.reset(frames, seed=seeds)
        self._frames, self._agent_pos = frames, pos.astype(np.float32)
        self._setpoint = self._agent_pos.astype(np.float64)
        self._t, self._needs_reset = 0, False
        return self._obs(), self._info()

    def step(self, actions):
        if self._frames is None:
            raise RuntimeError("call reset() before step().")
        if self._needs_reset:  # next-step autoreset: this step's actions are ignored
            obs, info = self.reset()
            zeros = np.zeros(self.num_envs, dtype=bool)
            return obs, np.zeros(self.num_envs), zeros, zeros.copy(), info
        self._setpoint = limit_targets(self._setpoint, check_actions(actions, (self.num_envs, 4)))
        self._frames = self.model.step(self._setpoint.astype(np.float32))
        self._agent_pos = read_agent_pos(self._frames, self._agent_pos)
        self._t += 1
        info = {**self._info(), "target": self._setpoint.astype(np.float32)}
        truncated = np.full(self.num_envs, self._t >= self.max_episode_steps)
        self._needs_reset = bool(truncated.all())
        return self._obs(), info["iou"].astype(np.float64), np.zeros(self.num_envs, dtype=bool), truncated, info

    def _obs(self) -> dict[str, np.ndarray]:
        return {"pixels": self._frames, "agent_pos": self._agent_pos.copy()}

    def _info(self) -> dict[str, np.ndarray]:
        iou = np.asarray(pixel_iou(self._frames), dtype=np.float64)
        return {"iou": iou, "is_success": iou >= SUCCESS_IOU}

    def render(self):
        return self._frames

    def close_extras(self, **kwargs: Any) -> None:
        self._starts.close()
