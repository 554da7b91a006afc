"""The world model as a Gymnasium environment, with its task's spaces.

    env = gym.make("iwsim/WorldModel-v0", checkpoint="checkpoints/pusht-64")
    obs, info = env.reset(seed=100000)   # T-push: the MuJoCo task's initial frame for that seed
    obs, reward, terminated, truncated, info = env.step(action)

The task (:class:`iwsim.envs.task.Task`) is the one the checkpoint records (``task=``
overrides it): its action space, how a command becomes the executed motion, its pixel
scorer and its initial frames. Initial frames come from ``reset_source``: the task's own
(``"mujoco"`` for T-push, a fresh MuJoCo reset with the given seed, so a policy starts
from the same state in both environments; ``"dataset"`` for any other robot's task, the
first frame of its store's episode ``seed % episodes``), ``"store"`` (a random frame of
the episode store ``store``), or ``reset(options={"frame": f})``.

A model of several camera views (``WorldModel.cameras``) observes ``pixels`` as {camera:
(H, W, 3) uint8} (gym-aloha's convention; one view: the frame itself), starts from every
view of MuJoCo's reset (or of a store's frame), takes ``reset(options={"frame": {camera:
frame}})`` and renders its views one above the other; its pixel scorer reads the first
view (the tabletop tasks' top camera).

``agent_pos`` of a T-push (or pile-sweeping) model: each pusher's executed setpoint where
the frame shows it near the setpoint, and where the frame shows it when contact holds it
back (:meth:`iwsim.envs.tabletop.task.TabletopTask.observe`); where the frame does not show it,
the model's own prediction for a model trained to predict the robot's state (``--variant
state``: the dynamics takes and predicts the store's ``data/state``, starting from the
start's ``agent_pos``), else its last position. A task without a pixel reading reports
the state such a model predicts. ``info["iou"]`` and the reward come
from the pixel scorer, so nothing but the model's outputs and the commands is used.
Actions are commanded targets, approached at the task's speed limit exactly as MuJoCo
does (:func:`iwsim.envs.tabletop.scene.limit_targets`, starting from the pushers' positions at
reset). A task without a scorer reports ``info["score"] = None`` and reward 0, and its
``agent_pos`` is the executed command. Either way the model is
conditioned on the executed motion (``info["target"]``).

:class:`WorldModelVectorEnv` steps many environments in one forward pass. Its episodes
run in lockstep (all start together and are truncated together after
``max_episode_steps``), which is what policy evaluation needs.
"""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np
from gymnasium.vector import AutoresetMode, VectorEnv
from gymnasium.vector.utils import batch_space

from iwsim.core.errors import InputError
from iwsim.data.views import split_views, stack_views, tile_views, unstack_views
from iwsim.envs.registry import StoreStarts, get_task, task_of
from iwsim.envs.task import Start, Task
from iwsim.world_model import StreamState, WorldModel

STORE = "store"
# What the environment observes, versioned: results measured in an environment of another
# version are other results (:func:`iwsim.experiments.common.fingerprint`). 2: T-push's
# ``agent_pos`` at the setpoints of pushers seen near them.
OBSERVATION_VERSION = 2
# The same for the models that predict the robot's state, whose observation alone changed
# (:func:`iwsim.experiments.common.fingerprint`). 2: their ``agent_pos`` read off the frame
# like the others', their prediction only for a pusher the frame does not show.
STATE_OBSERVATION_VERSION = 2


class Starts:
    """Initial frames: the task's own (``task.start_source``: MuJoCo resets for T-push, a
    dataset episode's first frame for a generic task) or a random frame of the episode
    store ``store`` (source ``"store"``)."""

    def __init__(self, task: Task, image_size: int, store: str | Path | None, source: str | None = None,
                 cameras: tuple[str, ...] = ("top",)) -> None:
        self.task, self.image_size, self.cameras = task, image_size, tuple(cameras)
        self.sources = (task.start_source, STORE)
        self.source = source or task.start_source
        if self.source not in self.sources:
            raise InputError(f"reset_source must be one of {self.sources}, got {self.source!r}.")
        if self.source == STORE and store is None:
            raise InputError("reset_source 'store' needs store=<path of an episode store>.")
        self._own = None
        self._store = None if store is None else StoreStarts(task, store, image_size, first=False,
                                                             cameras=self.cameras)
        self._store_path = None if store is None else str(store)
        if self.source == task.start_source:
            self._own = task.initial_frames(image_size, self._store_path, self.cameras)

    @property
    def has_store(self) -> bool:
        return self._store is not None

    def draw(self, seed: int, source: str | None = None, state: Any = None) -> Start:
        """The start for ``seed`` (and an explicit ground-truth ``state`` if given)."""
        source = source or self.source
        if source == self.task.start_source:
            if self._own is None:
                self._own = self.task.initial_frames(self.image_size, self._store_path, self.cameras)
            return self._own.draw(int(seed), state)
        if source != STORE or self._store is None:
            raise InputError(f"reset source {source!r} is not available; expected one of {self.sources} "
                             "(and a store for 'store').")
        return self._store.draw(int(seed))

    def close(self) -> None:
        for frames in (self._own, self._store):
            if frames is not None:
                frames.close()
        self._own = None


def resolve_task(model: WorldModel, task: str | Task | None) -> Task:
    """``task`` (a built-in name or a Task), else the model's; its action size must be the model's."""
    task = task_of(model) if task is None else get_task(task) if isinstance(task, str) else task
    if task.action_dim != model.action_dim:
        raise InputError(f"the world model takes {model.action_dim}-D actions; task {task.name!r} needs "
                         f"{task.action_dim}.")
    return task


def predicts_agent_pos(model: WorldModel, task: Task) -> bool:
    """Whether the model predicts the robot's state that the task observes as ``agent_pos``."""
    return model.state_dim > 0 and model.state_dim == task.action_dim


def predicted_agent_pos(model: WorldModel, task: Task, state: StreamState | None = None) -> np.ndarray | None:
    """The model's predicted ``agent_pos`` (B, A) float32 at ``state`` (default: its current
    rollouts'), within the bounds of the task's ``agent_pos`` (its action bounds, as
    :meth:`Task.spaces` declares: a robot stays in its workspace); None for a model that
    does not predict it."""
    own = model.robot_state(state) if predicts_agent_pos(model, task) else None
    if own is None:
        return None
    return np.clip(own, task.action_low, task.action_high).astype(np.float32)


class Views:
    """A model's camera views at the env's boundary: its frames are the views stacked along
    the channels (:class:`~iwsim.world_model.WorldModel`); observations give ``pixels`` as one
    frame for one view and {camera: frame} for several; the task's pixel scorer reads the
    first view."""

    def __init__(self, cameras: tuple[str, ...]) -> None:
        self.cameras = tuple(cameras)

    def pixels(self, frames: np.ndarray) -> np.ndarray | dict[str, np.ndarray]:
        """``pixels`` of frames (..., H, W, 3V)."""
        if len(self.cameras) == 1:
            return frames
        return dict(zip(self.cameras, unstack_views(frames, len(self.cameras)), strict=True))

    def first(self, frames: np.ndarray) -> np.ndarray:
        """The first view of frames (..., H, W, 3V): what the task's scorer reads."""
        return frames[..., :3]

    def stacked(self, pixels: Any) -> np.ndarray:
        """Frames given as ``pixels`` are ({camera: frame} or, for one view, a frame) -> (..., H, W, 3V)."""
        if len(self.cameras) == 1:
            return np.asarray(pixels)
        if isinstance(pixels, Mapping):
            return stack_views([np.asarray(v) for v in split_views(pixels, self.cameras).values()])
        return np.asarray(pixels)  # already stacked (checked by the model)

    def picture(self, frames: np.ndarray) -> np.ndarray:
        """What ``render`` shows: the views one above the other."""
        return frames if len(self.cameras) == 1 else tile_views(frames)


def _load(model: WorldModel | None, checkpoint: str | Path | None, device: str) -> WorldModel:
    if model is not None:
        return model
    if checkpoint is None:
        raise InputError("WorldModel-v0 needs checkpoint=<world-model checkpoint directory> (or model=...).")
    return WorldModel.load(checkpoint, device)


class WorldModelEnv(gym.Env):
    """One world-model rollout behind the Gymnasium API (see the module docstring)."""

    metadata = {"render_modes": ["rgb_array"], "render_fps": 10}

    def __init__(self, checkpoint: str | Path | None = None, *, model: WorldModel | None = None,
                 reset_source: str | None = None, store: str | Path | None = None, task: str | Task | None = None,
                 device: str = "cpu", render_mode: str | None = "rgb_array",
                 terminate_on_success: bool = False) -> None:
        if render_mode not in (None, "rgb_array"):
            raise InputError(f"render_mode must be 'rgb_array' or None, got {render_mode!r}.")
        self.model = _load(model, checkpoint, device)
        self.task = resolve_task(self.model, task)
        self.metadata = {**self.metadata, "render_fps": self.task.fps}
        self.render_mode, self.terminate_on_success = render_mode, terminate_on_success
        self.views = Views(self.model.cameras)
        self.action_space, self.observation_space = self.task.spaces(self.model.image_size, self.views.cameras)
        self._starts = Starts(self.task, self.model.image_size, store, reset_source, self.views.cameras)
        self._frame: np.ndarray | None = None
        self._agent_pos = np.zeros(self.task.action_dim, np.float32)
        self._own_pos = predicts_agent_pos(self.model, self.task)

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
            frame = self.model.check_frames(self.views.stacked(options["frame"])[None], 4).numpy()[0]
            start = self.task.start_from_frame(frame, options.get("agent_pos"))
        else:
            start = self._starts.draw(draw, options.get("source"), options.get("reset_to_state"))
        self._frame, self._agent_pos = start.frame, np.asarray(start.agent_pos, dtype=np.float32)
        self.model.reset(start.frame[None], seed=draw, held=np.asarray(start.command, np.float32)[None],
                         state=self._agent_pos[None] if self._own_pos else None)
        self._setpoint = np.asarray(start.command, np.float64)
        return self._obs(), self._info(self.task.score(self.views.first(self._frame[None])))

    def step(self, action):
        if self._frame is None:
            raise RuntimeError("call reset() before step().")
        task = self.task
        self._setpoint = task.executed(self._setpoint, task.check_actions(action, (task.action_dim,)))
        self._frame = self.model.step(self._setpoint.astype(np.float32)[None])[0]
        score, pos = task.observe(self.views.first(self._frame[None]), self._setpoint[None], self._agent_pos[None],
                                  predicted_agent_pos(self.model, task))
        self._agent_pos = pos[0]
        info = {**self._info(score), "target": self._setpoint.astype(np.float32)}
        terminated = bool(self.terminate_on_success and info.get("is_success"))
        return self._obs(), 0.0 if score is None else float(score[0]), terminated, False, info

    def _obs(self) -> dict[str, Any]:
        assert self._frame is not None  # set by reset
        return {"pixels": self.views.pixels(self._frame), "agent_pos": self._agent_pos.copy()}

    def _info(self, score: np.ndarray | None) -> dict[str, Any]:
        """``info[score_key]``: the task's pixel score (None: the task has no scorer), and
        ``is_success`` where the task defines success."""
        out: dict[str, Any] = {score_key(self.task): None if score is None else float(score[0])}
        success = self.task.is_success(score)
        if success is not None:
            out["is_success"] = bool(success[0])
        return out

    def render(self):
        return None if self.render_mode is None or self._frame is None else self.views.picture(self._frame)

    def close(self) -> None:
        self._starts.close()


def score_key(task: Task) -> str:
    """The ``info`` key of a task's score: ``iou`` for T-push (as ever), else ``score``."""
    return "iou" if task.score_name == "IoU" else "score"


class WorldModelVectorEnv(VectorEnv):
    """``num_envs`` world-model rollouts stepped in one batched forward pass.

    ``reset(seed=s)`` starts env i from seed ``s + i``, the model's noise seeded alike
    (``options={"noise_offset": k}`` adds k to the noise seeds: another sample of the same
    starts). All episodes are truncated together
    after ``max_episode_steps``; the following ``step`` resets them all (Gymnasium's
    next-step autoreset) from the next seeds.
    """

    metadata = {"render_modes": ["rgb_array"], "render_fps": 10, "autoreset_mode": AutoresetMode.NEXT_STEP}

    def __init__(self, num_envs: int, checkpoint: str | Path | None = None, *, model: WorldModel | None = None,
                 reset_source: str | None = None, store: str | Path | None = None, task: str | Task | None = None,
                 device: str = "cpu", max_episode_steps: int = 600) -> None:
        if num_envs < 1 or max_episode_steps < 1:
            raise InputError(f"num_envs and max_episode_steps must be >= 1, got {num_envs}, {max_episode_steps}.")
        self.model = _load(model, checkpoint, device)
        self.task = resolve_task(self.model, task)
        self.metadata = {**self.metadata, "render_fps": self.task.fps}
        self.num_envs, self.max_episode_steps = num_envs, max_episode_steps
        self.views = Views(self.model.cameras)
        self.single_action_space, self.single_observation_space = self.task.spaces(self.model.image_size,
                                                                                   self.views.cameras)
        self.action_space = batch_space(self.single_action_space, num_envs)
        self.observation_space = batch_space(self.single_observation_space, num_envs)
        self.render_mode = "rgb_array"
        self._starts = Starts(self.task, self.model.image_size, store, reset_source, self.views.cameras)
        self._frames: np.ndarray | None = None
        self._agent_pos = np.zeros((num_envs, self.task.action_dim), np.float32)
        self._own_pos = predicts_agent_pos(self.model, self.task)
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
            frames = self.model.check_frames(self.views.stacked(options["frames"]), 4).numpy()
            if len(frames) != self.num_envs:
                raise InputError(f"got {len(frames)} frames for {self.num_envs} environments.")
            pos = options.get("agent_pos")
            drawn = [self.task.start_from_frame(f, None if pos is None else pos[i]) for i, f in enumerate(frames)]
        else:
            drawn = [self._starts.draw(s, options.get("source")) for s in seeds]
            frames = np.stack([d.frame for d in drawn])
        self._setpoint = np.stack([d.command for d in drawn]).astype(np.float64)
        self._frames = frames
        self._agent_pos = np.stack([d.agent_pos for d in drawn]).astype(np.float32)
        offset = int(options.get("noise_offset", 0))  # another sample of the same starts: other noise
        self.model.reset(frames, seed=[(s + offset) % 2**32 for s in seeds], held=self._setpoint.astype(np.float32),
                         state=self._agent_pos if self._own_pos else None)
        self._t, self._needs_reset = 0, False
        return self._obs(), self._info(self.task.score(self.views.first(self._frames)))

    def step(self, actions):
        if self._frames is None:
            raise RuntimeError("call reset() before step().")
        if self._needs_reset:  # next-step autoreset: this step's actions are ignored
            obs, info = self.reset()
            zeros = np.zeros(self.num_envs, dtype=bool)
            return obs, np.zeros(self.num_envs), zeros, zeros.copy(), info
        task = self.task
        self._setpoint = task.executed(self._setpoint, task.check_actions(actions, (self.num_envs, task.action_dim)))
        novelty = self.model.novelty_of(self.model.state, self._setpoint.astype(np.float32))
        self._frames = self.model.step(self._setpoint.astype(np.float32))
        score, pos = task.observe(self.views.first(self._frames), self._setpoint, self._agent_pos,
                                  predicted_agent_pos(self.model, task))
        self._agent_pos = pos
        self._t += 1
        info = {**self._info(score), "target": self._setpoint.astype(np.float32)}
        if novelty is not None:  # the trust signal: how unlike the training data this step's inputs are
            info["novelty"] = novelty
        truncated = np.full(self.num_envs, self._t >= self.max_episode_steps)
        self._needs_reset = bool(truncated.all())
        reward = np.zeros(self.num_envs) if score is None else np.asarray(score, np.float64)
        return self._obs(), reward, np.zeros(self.num_envs, dtype=bool), truncated, info

    def _obs(self) -> dict[str, Any]:
        assert self._frames is not None  # set by reset
        return {"pixels": self.views.pixels(self._frames), "agent_pos": self._agent_pos.copy()}

    def _info(self, score: np.ndarray | None) -> dict[str, Any]:
        """As :meth:`WorldModelEnv._info`, batched (the score None without a scorer)."""
        out: dict[str, Any] = {score_key(self.task): None if score is None else np.asarray(score, np.float64)}
        success = self.task.is_success(score)
        if success is not None:
            out["is_success"] = success
        return out

    def render(self):
        return None if self._frames is None else self.views.picture(self._frames)

    def close_extras(self, **kwargs: Any) -> None:
        self._starts.close()
