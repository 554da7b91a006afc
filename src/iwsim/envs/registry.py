"""The Task registry and the generic task of any robot's data.

- :data:`REGISTRY`: the built-in tasks by name (T-push, pile sweeping); a new built-in task
  is a module under ``envs/`` with a :class:`~iwsim.envs.task.Task` subclass, listed here.
- :class:`DatasetTask`: any other robot's task, built from an episode store's attributes
  (action size, names, bounds, fps; the positions-in-image declaration if the store has
  one), its teleop step per dimension from the spread of the store's actions, and its
  initial frames from the store's episodes (``seed`` picks the episode: ``seed % episodes``,
  its first frame and first action).
- :func:`task_from_config`: the task a world-model checkpoint records, or for checkpoints
  from before the Task seam, the task of the store it was trained on, else T-push when its
  actions are 4-D (every such checkpoint iwsim made was T-push), else a generic task with
  the checkpoint's action bounds.

Only this module and ``envs/`` import a task's module (``tests/test_layers.py``).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from iwsim.core.errors import InputError
from iwsim.data.store import EpisodeStore, StoreError
from iwsim.data.views import store_cameras
from iwsim.envs.pilesweep.task import PileSweepTask
from iwsim.envs.pusht.task import PushTTask
from iwsim.envs.task import Bindings, Start, Task

REGISTRY: dict[str, Callable[[], Task]] = {PushTTask.kind: PushTTask,  # built without arguments
                                           PileSweepTask.kind: PileSweepTask}
# The task the commands and the studies default to: its name (``kind``), frame size
# (``image_size``), evaluation horizon (``horizon``) and shipped world model (``checkpoint``).
DEFAULT_TASK: type[PushTTask] = PushTTask
# Every built-in task's pixel experts (demonstrators), e.g. T-push's "expert" and "expert-wide".
ANY_EXPERTS = tuple(dict.fromkeys(e for make in REGISTRY.values() for e in make().pixel_experts))
# Per-frame arrays a start reads from a store (whichever the store has), besides the task's state_keys.
RECORD_KEYS = ("state", "target", "action")
STEP_OF_SPREAD = 0.1  # a teleop step is this share of the standard deviation of a dimension's actions


def get_task(name: str) -> Task:
    """The built-in task ``name``, or one :class:`InputError` line."""
    if name not in REGISTRY:
        raise InputError(f"unknown task {name!r}; the built-in tasks are {', '.join(sorted(REGISTRY))} (any other "
                         "robot's task comes with its world model's checkpoint or its store).")
    return REGISTRY[name]()


def shipped_world_model(task: Task | None = None) -> str:
    """The world model shipped for ``task`` (None: the default task's), or one line of error
    asking for one (a task without a shipped model)."""
    task = DEFAULT_TASK() if task is None else task
    if task.checkpoint is None:
        raise InputError(f"task {task.name!r} has no shipped world model; pass --world-model CHECKPOINT (a world "
                         f"model of {task.name!r}).")
    return task.checkpoint


@dataclass(frozen=True)
class DatasetTask(Task):
    """The generic task (see :class:`~iwsim.envs.task.Task`) whose initial frames are the
    first frames of a store's episodes."""

    def initial_frames(self, image_size: int, store: str | None = None,
                       cameras: tuple[str, ...] = ("top",)) -> StoreStarts:
        path = store or self.store
        if path is None:
            raise InputError(f"task {self.name!r} has no store of episodes to start from; give one "
                             "(store=... / --store).")
        return StoreStarts(self, path, image_size, cameras=cameras)


def foreign_task(path: str | Path, task: Task) -> str | None:
    """The name of the built-in task whose episodes the store at ``path`` holds, when it is
    not ``task`` (itself built in); else None (the same task, or a store or task of some
    robot's own data, which has no name to compare)."""
    own = task_from_store(path)
    return own.name if own.kind in REGISTRY and task.kind in REGISTRY and own.name != task.name else None


class StoreStarts:
    """Initial frames from a store: ``draw(seed)`` is the first frame of episode ``seed %
    episodes`` (``first=True``), or a random frame of a random episode drawn from ``seed``."""

    def __init__(self, task: Task, path: str | Path, image_size: int, first: bool = True,
                 cameras: tuple[str, ...] | None = None) -> None:
        try:
            self.store = EpisodeStore.open(path, "r")
        except (StoreError, OSError) as e:
            raise InputError(f"cannot read the episodes of task {task.name!r} at {path}: {e}") from None
        other = foreign_task(path, task)
        if other is not None:
            raise InputError(f"{path} holds episodes of task {other!r}; the world model is of {task.name!r}: start "
                             "from a store of its own task.")
        size = self.store.array("img").shape[1]
        if size != image_size:
            raise InputError(f"{path} holds {size}x{size} frames; the world model needs {image_size}x{image_size}.")
        if self.store.n_episodes == 0:
            raise InputError(f"{path} holds no episodes to start from.")
        views = store_cameras(self.store.attrs, self.store.keys)
        if cameras is not None and len(cameras) > 1 and views != tuple(cameras):
            raise InputError(f"{path} holds the views {list(views)}; the world model sees {list(cameras)}.")
        self._multi = cameras is not None and len(cameras) > 1
        self.task, self.path, self.first = task, Path(path), first

    def draw(self, seed: int, state: object = None) -> Start:
        del state
        ends = self.store.episode_ends
        if self.first:
            e = int(seed) % len(ends)
            i = 0 if e == 0 else int(ends[e - 1])
        else:
            rng = np.random.default_rng(seed)
            e = int(rng.integers(len(ends)))
            start = 0 if e == 0 else int(ends[e - 1])
            i = int(rng.integers(start, ends[e]))
        record = {k: np.asarray(self.store.array(k)[i]) for k in (*RECORD_KEYS, *self.task.state_keys)
                  if k in self.store.keys}
        if self._multi:  # (frames imports torch, which the command line's parser must not)
            from iwsim.data.frames import read_frames

            frame = read_frames(self.store, slice(i, i + 1))[0]
        else:
            frame = np.asarray(self.store.array("img")[i])
        return self.task.start_from_record(frame, record)

    def close(self) -> None:
        pass


def _floats(value: Any, n: int) -> tuple[float, ...] | None:
    """``value`` (anything) as n finite floats, or None."""
    try:
        out = tuple(float(v) for v in value)
    except (TypeError, ValueError):
        return None
    return out if len(out) == n and all(math.isfinite(v) for v in out) else None


def task_from_store(path: str | Path, action_low: Any = None, action_high: Any = None) -> Task:
    """The task of the episodes in the store at ``path``: the built-in task its ``task``
    attribute names (when the action sizes agree), else a :class:`DatasetTask` from its
    attributes and actions. ``action_low`` / ``action_high`` (a world model's
    normalisation bounds) take precedence over the store's."""
    try:
        store = EpisodeStore.open(path, "r")
    except (StoreError, OSError) as e:
        raise InputError(f"cannot read the store {path}: {e}") from None
    if "action" not in store.keys:
        raise InputError(f"{path} has no data/action to build a task from.")
    array = store.array("target" if "target" in store.keys else "action")
    if len(array.shape) != 2 or not array.shape[0]:
        raise InputError(f"{path}: data/action must be (frames, action_dim) with frames, got {array.shape}.")
    attrs, n = store.attrs, array.shape[1]
    name = str(attrs.get("task") or Path(path).name.removesuffix(".zarr"))
    if name in REGISTRY and REGISTRY[name]().action_dim == n:
        return REGISTRY[name]()  # (without reading the actions: a large store loads as fast)
    actions = np.asarray(array[:], np.float64)
    low = _floats(action_low, n) or _floats(attrs.get("action_low"), n) or tuple(actions.min(0))
    high = _floats(action_high, n) or _floats(attrs.get("action_high"), n) or tuple(actions.max(0))
    low, high = tuple(min(a, b - 1e-3) for a, b in zip(low, high)), high  # a constant dimension still moves
    names = attrs.get("action_names")
    names = tuple(str(v) for v in names) if isinstance(names, list) and len(names) == n else ()
    span = np.asarray(high) - np.asarray(low)
    step = np.maximum(STEP_OF_SPREAD * actions.std(0), span / 1000)
    points, view = attrs.get("action_points"), attrs.get("view_half")
    fps = attrs.get("fps")
    return DatasetTask(name=name, action_low=low, action_high=high, action_names=names,
                       fps=float(fps) if isinstance(fps, int | float) and fps > 0 else 10.0,
                       action_step=tuple(float(v) for v in step),
                       action_points=tuple(tuple(p) for p in points) if points and view else (),
                       view_half=float(view) if points and view else None, store=str(path))


def task_from_dict(d: object) -> Task:
    """A task from the JSON form :meth:`Task.describe` writes; bad input is one line."""
    if not isinstance(d, dict) or not isinstance(d.get("kind"), str):
        raise InputError(f"a task description must be a JSON object with a 'kind', got {str(d)[:80]}.")
    kind = d["kind"]
    if kind in REGISTRY:
        return REGISTRY[kind]()
    if kind != DatasetTask.kind:
        raise InputError(f"unknown task kind {kind!r}; expected {DatasetTask.kind} or one of {sorted(REGISTRY)}.")
    fields = {k: v for k, v in d.items() if k != "kind"}
    try:
        n = len(fields["action_low"])
        bindings = fields.pop("bindings", None)
        if bindings is not None:
            fields["bindings"] = Bindings.from_dict(bindings, n, fields.get("view_half"))
        return DatasetTask(**fields)
    except (TypeError, KeyError) as e:
        raise InputError(f"task description {str(d)[:80]}... is incomplete or malformed: {e}") from None


def task_from_config(config: dict, where: str | Path = "config.json") -> Task:
    """The task of a world-model checkpoint's ``config`` (see the module docstring)."""
    if "task" in config:
        try:
            return task_from_dict(config["task"])
        except InputError as e:
            raise InputError(f"{where}: {e}") from None
    # a file's config: every entry may be of any JSON type (a policy's provenance.data is a list)
    norm = config.get("action_norm")
    low, high = (norm.get("low"), norm.get("high")) if isinstance(norm, dict) else (None, None)
    provenance = config.get("provenance")
    data = config.get("data") or (provenance.get("data") if isinstance(provenance, dict) else None)
    if isinstance(data, str) and data and Path(data).is_dir():
        try:
            return task_from_store(data, low, high)
        except InputError:
            pass  # not a readable store any more: as if it were gone
    if not (isinstance(low, list) and isinstance(high, list) and len(high) == len(low)):
        low = high = []
    n = len(low)
    if n and not all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in [*low, *high]):
        n = 0
    if n == PushTTask().action_dim:
        return PushTTask()
    if not n:
        raise InputError(f"{where} has no action bounds (action_norm: low and high, numbers of one length) to "
                         "describe its task by.")
    return DatasetTask(name="generic", action_low=tuple(low), action_high=tuple(high))


def task_of(model: Any) -> Task:
    """A world model's task: the one its checkpoint records (``model.task``), or for a model
    built in code, T-push when its actions are 4-D, else a generic task on its action bounds."""
    task = getattr(model, "task", None)
    if task is not None:
        return task
    return task_from_config({"action_norm": {"low": model.action_low.tolist(), "high": model.action_high.tolist()}})
