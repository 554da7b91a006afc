"""The Task seam: what play, ``iwsim/WorldModel-v0``, policy evaluation and the studies need
to know about a robot beyond its frames and actions.

A :class:`Task` holds the action space (bounds, names, fps), how a command becomes the
motion the robot executes (:meth:`Task.executed`; the identity within the bounds unless a
task says otherwise, e.g. T-push's speed limit), an optional scorer from pixels
(:meth:`Task.observe`; none by default, and then episodes report no score rather than a
fake one), the optional declaration of which action entries are positions in the image
(``action_points`` with ``view_half``, which the dynamics turns into action maps),
teleoperation bindings (:class:`Bindings`) and its initial frames (:meth:`Task.start`).
A task with a ground truth (a simulator) adds it (:meth:`Task.ground_truth_env`), its
scripted policies (:meth:`Task.record_episode`; those that read only the observation, so
that they run inside a world model too: :meth:`Task.pixel_policy`) and its defaults for
the commands and the studies (frame size, evaluation horizon, shipped world model).

This base class is the generic task of any robot's data; a built-in task (T-push,
:mod:`iwsim.envs.pusht.task`) subclasses it and registers itself by name. The registry,
and the generic task whose initial frames come from a dataset, live one layer up in
:mod:`iwsim.envs.registry` (they read episode stores).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, fields
from typing import TYPE_CHECKING, Any, ClassVar, Protocol

import gymnasium as gym
import numpy as np

from iwsim.core.errors import InputError
from iwsim.envs import pixels_space

if TYPE_CHECKING:
    from iwsim.envs.tabletop.scripting import ScriptedPolicy

# Keys the play page keeps for itself (record, discard, restart, store start, side by side; Shift+S / Enter save).
RESERVED_KEYS = ("c", "q", "r", "t", "b")
# Default keys of a generic task: (increase, decrease) for its first dimensions.
DEFAULT_KEY_PAIRS = (("d", "a"), ("w", "s"), ("l", "j"), ("i", "k"))
# Default gamepad axes: (axis, sign) for the first dimensions (a stick's "up" is negative).
DEFAULT_AXES = ((0, 1.0), (1, -1.0), (2, 1.0), (3, -1.0))
MAX_GAMEPAD_AXES = 16


@dataclass(frozen=True)
class Start:
    """An initial frame (H, W, 3) uint8 (of several views: stacked along the channels,
    :func:`iwsim.data.views.stack_views`), the observation's ``agent_pos``, the command the
    robot holds there (A,) (the setpoint the first step moves from) and, when known, the
    ground-truth simulator's state that renders it."""

    frame: np.ndarray
    agent_pos: np.ndarray
    command: np.ndarray
    state: np.ndarray | None = None


class InitialFrames(Protocol):
    """A task's own initial frames: ``draw(seed, state=None) -> Start``, then ``close()``."""

    def draw(self, seed: int, state: object = None) -> Start: ...

    def close(self) -> None: ...


@dataclass(frozen=True)
class Bindings:
    """Teleoperation of a task's action dimensions in the play page.

    ``keys``: (key, dimension, sign) — a held key moves that dimension at ``speed`` (units
    per second) in the sign's direction, and a tap by one control step's worth.
    ``axes``: (gamepad axis, dimension, sign), a full stick moves at ``speed``.
    ``drag``: (x dimension, y dimension) pairs that are positions in the image (the task's
    ``action_points``), dragged with the mouse on the frame. ``legend``: lines the page shows.
    """

    keys: tuple[tuple[str, int, float], ...] = ()
    axes: tuple[tuple[int, int, float], ...] = ()
    speed: tuple[float, ...] = ()
    drag: tuple[tuple[int, int], ...] = ()
    drag_speed: float = 0.0  # the fastest a dragged position follows the mouse (units per second)
    legend: tuple[str, ...] = ()

    def check(self, action_dim: int, view_half: float | None) -> Bindings:
        """This, or an :class:`InputError` naming the first bad binding."""
        def dim(d: object, what: str) -> None:
            if isinstance(d, bool) or not isinstance(d, int) or not 0 <= d < action_dim:
                raise InputError(f"binding {what}: dimension {d!r} is not one of the task's 0..{action_dim - 1}.")

        def sign(s: object, what: str) -> None:
            if s not in (1, -1, 1.0, -1.0) or isinstance(s, bool):
                raise InputError(f"binding {what}: sign must be 1 or -1, got {s!r}.")

        seen = set()
        for key, d, s in self.keys:
            if not (isinstance(key, str) and len(key) == 1 and key.isprintable() and key == key.lower()
                    and not key.isspace()):
                raise InputError(f"binding key {key!r}: expected one lower-case character.")
            if key in RESERVED_KEYS:
                raise InputError(f"binding key {key!r} is taken by the page ({', '.join(RESERVED_KEYS)} are).")
            if key in seen:
                raise InputError(f"binding key {key!r} is bound twice.")
            seen.add(key)
            dim(d, f"key {key!r}")
            sign(s, f"key {key!r}")
        for axis, d, s in self.axes:
            if isinstance(axis, bool) or not isinstance(axis, int) or not 0 <= axis < MAX_GAMEPAD_AXES:
                raise InputError(f"binding axis {axis!r}: expected a gamepad axis 0..{MAX_GAMEPAD_AXES - 1}.")
            dim(d, f"axis {axis}")
            sign(s, f"axis {axis}")
        if len(self.speed) != action_dim or not all(isinstance(v, int | float) and math.isfinite(v) and v > 0
                                                     for v in self.speed):
            raise InputError(f"binding speed must be {action_dim} positive numbers (units per second, one per "
                             f"dimension), got {list(self.speed)}.")
        for pair in self.drag:
            if len(pair) != 2:
                raise InputError(f"binding drag {list(pair)}: expected an (x, y) pair of dimensions.")
            for d in pair:
                dim(d, f"drag {list(pair)}")
            if view_half is None:
                raise InputError("binding drag needs a task that declares view_half (where its positions are "
                                 "in the image).")
        if self.drag and not (isinstance(self.drag_speed, int | float) and math.isfinite(self.drag_speed)
                              and self.drag_speed > 0):
            raise InputError(f"binding drag_speed must be a positive number, got {self.drag_speed!r}.")
        return self

    def to_dict(self) -> dict[str, Any]:
        return {"keys": {k: [d, float(s)] for k, d, s in self.keys}, "axes": [list(a) for a in self.axes],
                "speed": [float(v) for v in self.speed], "drag": [list(p) for p in self.drag],
                "drag_speed": float(self.drag_speed), "legend": list(self.legend)}

    @classmethod
    def from_dict(cls, d: object, action_dim: int, view_half: float | None = None) -> Bindings:
        """Bindings from their JSON form (as :meth:`to_dict` writes it), checked; bad
        input is one :class:`InputError` line."""
        if not isinstance(d, dict):
            raise InputError(f"bindings must be a JSON object with keys, axes, speed, got {type(d).__name__}.")
        unknown = set(d) - {"keys", "axes", "speed", "drag", "drag_speed", "legend"}
        if unknown:
            raise InputError(f"unknown binding fields {sorted(unknown)}; expected keys, axes, speed, drag, "
                             "drag_speed, legend.")
        keys, axes = d.get("keys", {}), d.get("axes", [])
        if not isinstance(keys, dict) or not all(isinstance(v, list) and len(v) == 2 for v in keys.values()):
            raise InputError('binding keys must be an object {"key": [dimension, sign], ...}.')
        if not isinstance(axes, list) or not all(isinstance(v, list) and len(v) == 3 for v in axes):
            raise InputError("binding axes must be a list of [axis, dimension, sign].")
        speed, drag, legend = d.get("speed"), d.get("drag", []), d.get("legend", [])
        if not isinstance(speed, list) or not isinstance(drag, list) or not isinstance(legend, list):
            raise InputError("binding speed, drag and legend must be lists.")
        return cls(tuple((k, v[0], v[1]) for k, v in keys.items()), tuple(tuple(a) for a in axes), tuple(speed),
                   tuple(tuple(p) if isinstance(p, list) else (p,) for p in drag), d.get("drag_speed", 0.0),
                   tuple(str(x) for x in legend)).check(action_dim, view_half)


def default_bindings(names: tuple[str, ...], step: tuple[float, ...], fps: float) -> Bindings:
    """Keys and gamepad axes for the first dimensions, moving a dimension by ``step`` per
    control step (sliders on the page cover every dimension)."""
    n = len(names)
    keys = tuple((k, d, s) for d, pair in enumerate(DEFAULT_KEY_PAIRS[:n]) for k, s in zip(pair, (1.0, -1.0)))
    axes = tuple((axis, d, s) for d, (axis, s) in enumerate(DEFAULT_AXES[:n]))
    legend = tuple(f"{names[d]}: {pair[0].upper()} / {pair[1].upper()} or gamepad axis {d}"
                   for d, pair in enumerate(DEFAULT_KEY_PAIRS[:n]))
    return Bindings(keys, axes, tuple(float(v) * fps for v in step),
                    legend=(*legend, "every dimension: the sliders; a tap moves one step."))


@dataclass(frozen=True)
class Task:
    """A robot task as the world model's callers see it (see the module docstring).

    The base class is the generic task: commands are executed as given (clipped to the
    bounds), there is no scorer, ``agent_pos`` is the executed command (the model predicts
    pixels only; for a position-controlled robot its setpoint is the best proprioception
    there is), and initial frames come from a dataset (:class:`iwsim.envs.registry.DatasetTask`).
    """

    name: str
    action_low: tuple[float, ...]
    action_high: tuple[float, ...]
    action_names: tuple[str, ...] = ()
    fps: float = 10.0
    action_step: tuple[float, ...] = ()  # a teleop step per dimension (default: 1/50 of the range)
    action_points: tuple[tuple[int, int], ...] = ()  # (x, y) entries that are positions in the image
    view_half: float | None = None  # the camera sees [-view_half, view_half]^2 in those units
    bindings: Bindings | None = None  # default: default_bindings
    store: str | None = None  # episodes whose first frames are the initial frames

    kind: ClassVar[str] = "generic"
    score_name: ClassVar[str | None] = None  # the pixel scorer's name, None: no scorer
    success_score: ClassVar[float | None] = None  # a score at or above this is a success
    start_source: ClassVar[str] = "dataset"  # the name of the task's own initial frames
    clip_commands: ClassVar[bool] = False  # True: a command beyond the bounds is clipped, not refused
    has_ground_truth: ClassVar[bool] = False  # ground_truth_env gives a simulator
    # Per-step arrays of a store that, after agent_pos (``state``), make the simulator's state
    # (start_from_record reads them; T-push: the block's pose).
    state_keys: ClassVar[tuple[str, ...]] = ()
    episode_score: ClassVar[str | None] = None  # the array of record_episode's episodes holding the score
    # A task with a ground truth: its defaults for the commands and the studies (None: none).
    image_size: ClassVar[int | None] = None  # the frames collected, trained on and evaluated at
    horizon: ClassVar[int | None] = None  # steps of an evaluation episode
    checkpoint: ClassVar[str | None] = None  # the shipped world model
    starts: ClassVar[tuple[str, ...]] = ("random",)  # the simulator's initial-state distributions
    cameras: ClassVar[tuple[str, ...]] = ()  # the simulator's cameras (the first: its pixel scorer's view)
    pixel_policies: ClassVar[tuple[str, ...]] = ()  # scripted policies that read only the observation
    pixel_experts: ClassVar[tuple[str, ...]] = ()  # those of them that do the task (demonstrators)
    pixel_reading: ClassVar[str] = "the frame"  # what they read from the frame (a demonstration store says)

    def __post_init__(self) -> None:
        low, high = tuple(float(v) for v in self.action_low), tuple(float(v) for v in self.action_high)
        if not low or len(low) != len(high) or not all(math.isfinite(a) and math.isfinite(b) and b > a
                                                       for a, b in zip(low, high)):
            raise InputError(f"task {self.name!r}: action bounds must be two equally long lists of finite values "
                             f"with high > low, got {list(low)} and {list(high)}.")
        n = len(low)
        names = tuple(str(v) for v in self.action_names) or tuple(f"a{i}" for i in range(n))
        if len(names) != n:
            raise InputError(f"task {self.name!r} has {n} action dimensions but {len(names)} names.")
        step = tuple(float(v) for v in self.action_step) or tuple((b - a) / 50 for a, b in zip(low, high))
        if len(step) != n or not all(math.isfinite(v) and v > 0 for v in step):
            raise InputError(f"task {self.name!r}: action_step must be {n} positive numbers, got {list(step)}.")
        if not (isinstance(self.fps, int | float) and math.isfinite(self.fps) and self.fps > 0):
            raise InputError(f"task {self.name!r}: fps must be positive, got {self.fps!r}.")
        points = tuple(tuple(int(i) for i in p) for p in self.action_points)
        if any(len(p) != 2 or not all(0 <= i < n for i in p) for p in points):
            raise InputError(f"task {self.name!r}: action_points must be (x, y) pairs of dimensions 0..{n - 1}, "
                             f"got {self.action_points!r}.")
        for name, value in (("action_low", low), ("action_high", high), ("action_names", names),
                            ("action_step", step), ("action_points", points), ("fps", float(self.fps))):
            object.__setattr__(self, name, value)
        bindings = self.bindings or self.default_bindings()
        object.__setattr__(self, "bindings", bindings.check(n, self.view_half))

    # -- the action space ---------------------------------------------------------------------
    @property
    def action_dim(self) -> int:
        return len(self.action_low)

    def default_bindings(self) -> Bindings:
        return default_bindings(self.action_names, self.action_step, self.fps)

    def spaces(self, image_size: int, cameras: tuple[str, ...] = ("top",)) -> tuple[gym.spaces.Box, gym.spaces.Dict]:
        """The action and observation spaces (``pixels`` (H, W, 3) uint8, or {camera: (H, W,
        3) uint8} with several ``cameras``; ``agent_pos`` (A,))."""
        low, high = np.asarray(self.action_low, np.float32), np.asarray(self.action_high, np.float32)
        obs = gym.spaces.Dict({"pixels": pixels_space(image_size, cameras),
                               "agent_pos": gym.spaces.Box(low, high, dtype=np.float32)})
        return gym.spaces.Box(low, high, dtype=np.float32), obs

    def check_actions(self, actions: object, shape: tuple[int, ...]) -> np.ndarray:
        """Commands as float64 of ``shape``, or an :class:`InputError` (before any state changes)."""
        a = np.asarray(actions, dtype=np.float64)
        if a.shape != shape or not np.all(np.isfinite(a)):
            raise InputError(f"expected finite actions of shape {shape} [{', '.join(self.action_names)}], got "
                             f"{a.shape if a.shape != shape else a.tolist()}.")
        return a

    def out_of_bounds(self, command: np.ndarray) -> str | None:
        """None if ``command`` (A,) is within the bounds (or this task clips), else one line
        naming the first entry outside them."""
        if self.clip_commands:
            return None
        low, high = np.asarray(self.action_low), np.asarray(self.action_high)
        tol = 1e-6 * (high - low)
        bad = np.nonzero((command < low - tol) | (command > high + tol))[0]
        if not len(bad):
            return None
        i = int(bad[0])
        return (f"action {self.action_names[i]} = {float(command[i]):g} is outside the task's bounds "
                f"[{low[i]:g}, {high[i]:g}]; the command is unchanged.")

    def executed(self, setpoint: np.ndarray, command: np.ndarray) -> np.ndarray:
        """The motion the robot executes (..., A) float64 when ``command`` (..., A) follows
        the previous executed ``setpoint``: here the command within the bounds."""
        del setpoint
        return np.clip(np.asarray(command, np.float64), self.action_low, self.action_high)

    # -- what frames say ------------------------------------------------------------------------
    def score(self, frames: np.ndarray) -> np.ndarray | None:
        """Scores (B,) float64 of frames (B, H, W, 3), or None: this task has no scorer."""
        del frames
        return None

    def plausibility(self, frames: np.ndarray) -> np.ndarray | None:
        """How well each of frames (B, H, W, 3) shows a scene this task can have (B,) in
        [0, 1] (1: its objects exactly as they can look), or None: this task cannot tell.
        A world model's frames that stop looking possible (a rigid block that bends) are
        frames whose score is least to be trusted (:mod:`iwsim.eval.trust`)."""
        del frames
        return None

    def command_lead(self, commands: np.ndarray, agent_pos: np.ndarray) -> np.ndarray | None:
        """How far each command (..., A) runs ahead of where the robot was when it was
        given (``agent_pos`` (..., A)): per step the largest distance over the
        ``action_points``, in units of ``view_half`` (..., ); None where the task declares no
        positions in the image or its ``agent_pos`` is not in the commands' space. A policy
        that presses its setpoints far beyond the robot (a learned policy against a block)
        drives a world model where its training data rarely went."""
        commands, agent_pos = np.asarray(commands, np.float64), np.asarray(agent_pos, np.float64)
        if not self.action_points or self.view_half is None or agent_pos.shape != commands.shape:
            return None
        gap = commands - agent_pos
        lead = np.stack([np.hypot(gap[..., x], gap[..., y]) for x, y in self.action_points], -1)
        return lead.max(-1) / self.view_half

    def observe(self, frames: np.ndarray, setpoint: np.ndarray, previous: np.ndarray,
                predicted: np.ndarray | None = None) -> tuple[np.ndarray | None, np.ndarray]:
        """Scores (B,) of frames (B, H, W, 3) (None without a scorer) and ``agent_pos``
        (B, A) after a step that executed ``setpoint`` (B, A): here the state a world model
        ``predicted`` (B, A) where it predicts one, else the setpoints."""
        del previous
        return self.score(frames), np.asarray(setpoint if predicted is None else predicted, np.float32).copy()

    def is_success(self, scores: np.ndarray | None) -> np.ndarray | None:
        return None if scores is None or self.success_score is None else np.asarray(scores) >= self.success_score

    # -- initial frames and the ground truth -----------------------------------------------------
    def initial_frames(self, image_size: int, store: str | None = None,
                       cameras: tuple[str, ...] = ("top",)) -> InitialFrames:
        """The source of this task's own initial frames (:meth:`InitialFrames.draw` per seed),
        of ``cameras`` stacked along the channels (:func:`iwsim.data.views.stack_views`)."""
        del image_size, store, cameras
        raise InputError(f"task {self.name!r} has no initial frames of its own; give a store of its episodes "
                         "(store=... / --store).")

    def start_from_frame(self, frame: np.ndarray, agent_pos: object = None) -> Start:
        """A start at a given frame: the command held there is ``agent_pos`` if given,
        else the middle of the bounds."""
        mid = (np.asarray(self.action_low) + np.asarray(self.action_high)) / 2
        command = mid if agent_pos is None else self.check_actions(agent_pos, (self.action_dim,))
        return Start(frame, command.astype(np.float32), command.astype(np.float64))

    def start_from_record(self, frame: np.ndarray, record: dict[str, np.ndarray]) -> Start:
        """A start at a stored frame, from that step's stored arrays (``target`` or
        ``action``: the command the robot held)."""
        key = "target" if "target" in record else "action"
        if key not in record or np.shape(record[key]) != (self.action_dim,):
            raise InputError(f"the store's frames need a {self.action_dim}-D data/action to start task "
                             f"{self.name!r} from them.")
        command = np.clip(np.asarray(record[key], np.float64), self.action_low, self.action_high)
        return Start(frame, command.astype(np.float32), command)

    def ground_truth_env(self, image_size: int | None = None, start: str = "random",
                         cameras: tuple[str, ...] = ("top",)) -> gym.Env | None:
        """The simulator the world model stands in for, if the task has one (side by side in
        play, policy evaluation): frames ``image_size`` pixels square (None: the task's own)
        from ``cameras`` (of :attr:`cameras`), initial states from the distribution ``start``
        (one of :attr:`starts`)."""
        del image_size, start, cameras
        return None

    @property
    def scripted_policies(self) -> tuple[str, ...]:
        """The names of the scripted policies :meth:`record_episode` runs (none without a simulator)."""
        return ()

    def pixel_policy(self, kind: str, seed: int, rng: np.random.Generator, miss: float = 0.0) -> ScriptedPolicy:
        """A scripted policy of :attr:`pixel_policies` that reads nothing but the observation
        (the frame and ``agent_pos``), so that it acts alike in the simulator and inside a
        world model: ``policy(obs, info) -> action`` after ``policy.reset(obs, info)``.
        ``seed`` randomises it (a play policy), ``rng`` draws what is drawn per episode;
        ``miss`` > 0 aims an expert at its object displaced by that much (a task may refuse)."""
        del seed, rng, miss
        raise InputError(f"task {self.name!r} has no scripted policies; {kind!r} needs a task with a simulator.")

    def record_episode(self, policy: str, seed: int, steps: int, image_size: int,
                       cameras: tuple[str, ...] = ("top",)) -> dict[str, np.ndarray]:
        """One seeded episode of the simulator under a scripted policy, in the episode
        store's layout (``img``, ``state``, ``action``, ``target``, ``n_contacts`` and the
        :attr:`episode_score` array, per step; ``iwsim collect`` records them), its frames
        from the simulator's ``cameras`` (:attr:`cameras`; the first is ``img``, each other
        ``img_<camera>``, :mod:`iwsim.data.views`)."""
        del seed, steps, image_size, cameras
        raise InputError(f"task {self.name!r} has no simulator to record {policy!r} episodes in.")

    # -- descriptions ------------------------------------------------------------------------------
    def describe(self) -> dict[str, Any]:
        """The JSON form a checkpoint records (:func:`iwsim.envs.registry.task_from_dict` reads it)."""
        out: dict[str, Any] = {"kind": self.kind}
        for f in fields(self):
            v = getattr(self, f.name)
            out[f.name] = v.to_dict() if isinstance(v, Bindings) else (
                [list(p) for p in v] if f.name == "action_points" else list(v) if isinstance(v, tuple) else v)
        return out

    def store_attrs(self) -> dict[str, Any]:
        """The root attributes a store of this task's episodes carries (what
        :func:`iwsim.envs.registry.task_from_store` reads back)."""
        out: dict[str, Any] = {"task": self.name, "fps": self.fps, "action_low": list(self.action_low),
                               "action_high": list(self.action_high), "action_names": list(self.action_names)}
        if self.action_points and self.view_half is not None:
            out.update(action_points=[list(p) for p in self.action_points], view_half=self.view_half)
        return out

    def page_info(self) -> dict[str, Any]:
        """What the play page needs: names, bounds, bindings, the scorer's name."""
        assert self.bindings is not None  # __post_init__ sets them
        return {"task": self.name, "action_names": list(self.action_names), "action_low": list(self.action_low),
                "action_high": list(self.action_high), "action_step": list(self.action_step),
                "view_half": self.view_half, "bindings": self.bindings.to_dict(), "score_name": self.score_name,
                "start_source": self.start_source}

