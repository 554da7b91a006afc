"""What the scripted policies of every tabletop task share (T-push's :mod:`iwsim.envs.pusht.scripted`,
pile sweeping's :mod:`iwsim.envs.pilesweep.scripted`): a human-like :class:`Hand`, the
degradations of graded skill (:class:`Degraded`: a hand, command noise, latency), the one
loop in which a scripted policy drives a simulator (:func:`run_policy`) and an episode's
arrays in the store's layout (:func:`record`).

A scripted policy is called as ``policy(obs, info) -> action`` after ``policy.reset(obs,
info)``; actions are absolute pusher targets ``[lx, ly, rx, ry]``.
"""

from __future__ import annotations

from collections import deque
from collections.abc import Generator, Iterable, Mapping
from dataclasses import dataclass
from typing import Any, Protocol

import gymnasium as gym
import numpy as np

from iwsim.core.errors import InputError
from iwsim.data import views
from iwsim.envs import make_env
from iwsim.envs.tabletop.scene import WORKSPACE

PAUSE_STEPS = (5, 20)  # a pause of the hand holds its command this many steps (inclusive)
JITTER_CORRELATION = 0.8  # the tremor's AR(1) coefficient: correlated over ~5 steps


class ScriptedPolicy(Protocol):
    def reset(self, obs: dict, info: dict) -> None: ...

    def __call__(self, obs: dict, info: dict) -> np.ndarray: ...


def check_policy(name: str, names: tuple[str, ...]) -> None:
    """An InputError unless ``name`` is one of a task's scripted policies ``names``."""
    if name not in names:
        raise InputError(f"unknown policy {name!r}; expected one of {list(names)}.")


def advance(p: np.ndarray, target: np.ndarray, max_step: float) -> np.ndarray:
    """The point at most ``max_step`` from ``p`` towards ``target`` (``target`` if closer)."""
    d = target - p
    n = float(np.linalg.norm(d))
    return target if n <= max_step else p + d * (max_step / n)


class Hand:
    """A human-like hand between a policy and the robot: ``hand(command) -> command``, one
    call per step, its randomness from ``rng``, starting at ``start`` (the pushers).

    ``lag``: a slow hand, a first-order low-pass of the commands with that time constant
    (steps; <= 1: none). ``pause``: the chance per step of holding the command still for
    :data:`PAUSE_STEPS` steps. ``jitter``: a tremor, stationary AR(1) noise of that std
    (m), correlated over ~5 steps. ``overshoot``: the hand leads its motion by that many
    steps (command + overshoot x its last change), so every stop overshoots and comes back.
    A hand with every field 0 passes commands through unchanged.
    """

    def __init__(self, rng: np.random.Generator, start: np.ndarray, lag: float = 0.0, pause: float = 0.0,
                 jitter: float = 0.0, overshoot: float = 0.0) -> None:
        self.rng, self.lag, self.pause, self.jitter, self.overshoot = rng, lag, pause, jitter, overshoot
        self.out = np.asarray(start, dtype=np.float64).copy()  # where the hand is (lag's state)
        self.prev: np.ndarray | None = None  # the previous command (overshoot's velocity)
        self.held = 0  # steps of the current pause still to hold
        self.tremor = np.zeros_like(self.out)

    def __call__(self, command: np.ndarray) -> np.ndarray:
        a = np.asarray(command, dtype=np.float64)
        if self.overshoot:
            lead = 0.0 if self.prev is None else self.overshoot * (a - self.prev)
            self.prev, a = a, a + lead
        if self.held > 0:
            self.held -= 1
            return self.out.copy()
        if self.pause and self.rng.random() < self.pause:
            self.held = int(self.rng.integers(PAUSE_STEPS[0], PAUSE_STEPS[1] + 1)) - 1
            return self.out.copy()
        self.out = self.out + (a - self.out) / self.lag if self.lag > 1 else a
        if self.jitter:
            c = JITTER_CORRELATION
            self.tremor = c * self.tremor + self.rng.normal(0.0, self.jitter * np.sqrt(1 - c * c), a.shape)
            return self.out + self.tremor
        return self.out.copy()


class Degraded:
    """A scripted policy of graded skill: its commands go through a :class:`Hand` (``lag``,
    ``pause``, ``jitter``, ``overshoot``, drawn from ``hand_rng``), get Gaussian ``noise``
    (std in metres per coordinate, drawn from ``rng``), are clipped to the workspace and
    execute ``latency`` steps late (the pushers hold their first positions until the first
    command arrives). All zero: the policy's own commands."""

    def __init__(self, policy: ScriptedPolicy, rng: np.random.Generator, hand_rng: np.random.Generator,
                 noise: float = 0.0, latency: int = 0, lag: float = 0.0, pause: float = 0.0, jitter: float = 0.0,
                 overshoot: float = 0.0) -> None:
        self.policy, self.rng, self.hand_rng, self.noise, self.latency = policy, rng, hand_rng, noise, latency
        self.hand_args = {"lag": lag, "pause": pause, "jitter": jitter, "overshoot": overshoot}

    def reset(self, obs: dict, info: dict) -> None:
        self.policy.reset(obs, info)
        start = np.asarray(obs["agent_pos"], dtype=np.float32)
        self.queue = deque([start.copy()] * self.latency, maxlen=self.latency + 1)
        self.hand = Hand(self.hand_rng, start, **self.hand_args)

    def __call__(self, obs: dict, info: dict) -> np.ndarray:
        a = self.hand(np.asarray(self.policy(obs, info), dtype=np.float64))
        if self.noise:
            a = a + self.rng.normal(0.0, self.noise, a.shape)
        self.queue.append(np.clip(a, -WORKSPACE, WORKSPACE).astype(np.float32))
        return self.queue.popleft()


@dataclass(frozen=True)
class Transition:
    """One step of a scripted episode: the observation and info before the action, the
    action (float32), and the observation and info after it (``next_info["target"]`` is
    the motion MuJoCo executed, what a world model is conditioned on)."""

    obs: dict[str, np.ndarray]
    info: dict[str, Any]
    action: np.ndarray
    next_obs: dict[str, np.ndarray]
    next_info: dict[str, Any]


def run_policy(policy: ScriptedPolicy, env: gym.Env | str, seed: int, steps: int,
               image_size: int | None = None, cameras: tuple[str, ...] = ("top",)) -> Generator[Transition, None, None]:
    """Drive ``env`` (an environment, or a task's name: its environment, frames
    ``image_size`` pixels square from ``cameras``, made here and closed when the loop ends
    or is abandoned) with ``policy`` for ``steps`` steps from the reset with ``seed``,
    yielding each :class:`Transition`."""
    own = isinstance(env, str)
    sim = make_env(env, image_size, **camera_kwargs(cameras)) if isinstance(env, str) else env
    try:
        obs, info = sim.reset(seed=seed)
        policy.reset(obs, info)
        for _ in range(steps):
            action = np.asarray(policy(obs, info), dtype=np.float32)
            next_obs, _, _, _, next_info = sim.step(action)
            yield Transition(obs, info, action, next_obs, next_info)
            obs, info = next_obs, next_info
    finally:
        if own:
            sim.close()


def camera_kwargs(cameras: tuple[str, ...]) -> dict[str, Any]:
    """``make_env``'s keyword for ``cameras``: none for the one top view (every env's default)."""
    return {} if tuple(cameras) == ("top",) else {"cameras": tuple(cameras)}


def record(transitions: Iterable[Transition], info: Mapping[str, type]) -> dict[str, np.ndarray]:
    """An episode's arrays in the episode store's layout: step t holds the observation
    before action t and the action itself: ``img`` (T, H, W, 3) uint8, ``state`` (T, 4)
    float32 (agent_pos), ``action`` (T, 4) float32 (as commanded), ``target`` (T, 4)
    float32 (the rate-limited setpoints action t executed, what the world model is
    conditioned on), then each key of ``info`` (the info before action t) as that dtype.
    With several cameras (``pixels`` a {camera: frame} mapping) the first is ``img`` and each
    other ``img_<camera>`` (:mod:`iwsim.data.views`)."""
    rows: dict[str, list] = {k: [] for k in ("img", "state", "action", "target", *info)}
    for tr in transitions:
        for key, frame in _view_frames(tr.obs["pixels"]).items():
            rows.setdefault(key, []).append(frame)
        rows["state"].append(tr.obs["agent_pos"])
        rows["action"].append(tr.action)
        rows["target"].append(tr.next_info["target"])
        for k in info:
            rows[k].append(tr.info[k])
    dtypes: dict[str, type] = {"state": np.float32, "action": np.float32, "target": np.float32, **info}
    return {k: np.asarray(v, dtype=dtypes.get(k, np.uint8)) for k, v in rows.items()}


def _view_frames(pixels: np.ndarray | Mapping[str, np.ndarray]) -> dict[str, np.ndarray]:
    """{store array: frame} of an observation's ``pixels``."""
    if not isinstance(pixels, Mapping):
        return {views.IMAGE_KEY: pixels}
    cameras = tuple(pixels)
    return {views.view_key(cameras, c): pixels[c] for c in cameras}
