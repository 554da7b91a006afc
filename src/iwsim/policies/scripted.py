"""Scripted policies behind the learned policies' interface, so that the same loops
(:func:`iwsim.eval.policy.rollout`, MuJoCo's vector env or the world model's) drive both.

    policy = ScriptedBatch("expert", noise=0.01, latency=2)  # or "expert-wide", "play", "still"
    policy = ScriptedBatch("expert", task="pilesweep")       # a task's own (default: T-push's)
    policy.reset()
    actions = policy.predict_action({"image": (B, 1, H, W, 3) uint8, "agent_pos": (B, 1, 4)})
    # -> (B, 1, 4)

Each of the B episodes gets its own scripted policy, made on the first call after
``reset()``: the task's (:meth:`iwsim.envs.task.Task.pixel_policy`), which sees nothing but
the frame and ``agent_pos`` (T-push's experts estimate the block pose from the pixels), so
a scripted policy behaves the same in MuJoCo and inside a world model. Degradations, for
policies of graded skill:
``noise`` adds Gaussian noise (metres, per coordinate) to every command, ``latency``
executes each command that many steps late (holding the pushers' first positions until
then). A human-like hand (:class:`iwsim.envs.tabletop.scripting.Hand`) between the policy and the robot: ``lag`` (a
slow hand that follows the policy's commands with that time constant, in steps),
``pause`` (the chance per step of holding the command still for 5-20 steps),
``jitter`` (a tremor: smooth noise of that std, correlated over ~5 steps) and
``overshoot`` (a hand that leads its motion by that many steps, so every stop overshoots
and comes back); ``miss`` aims the expert at a block displaced by that many metres in a
direction (and turned by an angle) drawn per episode: expert-like motions that miss.
T-push's experts are ``expert``, the precise pinch, and ``expert-wide``, the forgiving one;
the ``still`` policy (any task's) holds the pushers where they start.
All draws are seeded per episode index, so results do not depend on the batch size.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from iwsim.core.errors import InputError
from iwsim.envs.registry import DEFAULT_TASK, REGISTRY, get_task
from iwsim.envs.tabletop.scripting import Degraded, ScriptedPolicy
from iwsim.envs.task import Task

STILL = "still"  # holds the pushers where they start: a policy of every task
# Every scripted policy of a registered task, and the still one.
KINDS = (*dict.fromkeys(k for make in REGISTRY.values() for k in make().pixel_policies), STILL)


@dataclass(frozen=True)
class ScriptedConfig:
    kind: str = "expert"
    noise: float = 0.0  # std of Gaussian noise on each command (m)
    latency: int = 0  # commands execute this many steps late
    seed: int = 0  # episode i draws its noise (and the play policy its choices) from seed + i
    lag: float = 0.0  # a slow hand: time constant (steps) of the low-pass its commands go through; <= 1: none
    pause: float = 0.0  # chance per step that the hand holds its command for 5-20 steps
    jitter: float = 0.0  # tremor: std (m) of smooth AR(1) noise on every command
    overshoot: float = 0.0  # the hand leads its motion by this many steps (each stop overshoots)
    miss: float = 0.0  # an expert aims at a block displaced by this much (m) and turned (per episode)

    def __post_init__(self) -> None:
        if self.kind not in KINDS:
            raise InputError(f"unknown scripted policy {self.kind!r}; expected one of {', '.join(KINDS)}.")
        for name in ("noise", "lag", "jitter", "overshoot", "miss"):
            v = getattr(self, name)
            if not (np.isfinite(v) and v >= 0):
                raise InputError(f"{name} must be a finite number >= 0, got {v}.")
        if not 0 <= self.pause < 1:
            raise InputError(f"pause must be a chance per step in [0, 1), got {self.pause}.")
        if self.latency < 0:
            raise InputError(f"latency must be 0 or more steps, got {self.latency}.")
        if self.miss and self.kind in ("play", STILL):
            raise InputError(f"miss displaces an expert's aim; the {self.kind!r} policy has none.")

    @property
    def name(self) -> str:
        parts = [self.kind] + [f"{k}{getattr(self, k):g}" for k in ("noise", "latency", "lag", "pause", "jitter",
                                                                    "overshoot", "miss") if getattr(self, k)]
        return "-".join(parts)


class _Still:
    """Holds the pushers where they start."""

    def reset(self, obs: dict, info: dict) -> None:
        self.start = np.asarray(obs["agent_pos"], dtype=np.float32).copy()

    def __call__(self, obs: dict, info: dict) -> np.ndarray:
        return self.start


class ScriptedBatch:
    """B scripted episodes as one policy with ``obs_horizon = 1`` and one action per call."""

    obs_horizon = 1
    n_action_steps = 1
    kind = "scripted"

    def __init__(self, cfg: ScriptedConfig | str = "expert", task: Task | str | None = None,
                 cameras: tuple[str, ...] | None = None, **overrides) -> None:
        """``task``: whose scripted policies (a Task or a built-in task's name; None: T-push's).
        ``cameras``: the views it is given (stacked along the channels, so that a rollout
        records every view); it reads the first, as the task's pixel scorer (None: one view)."""
        self.cameras = cameras
        self.cfg = ScriptedConfig(cfg, **overrides) if isinstance(cfg, str) else cfg
        self.task = DEFAULT_TASK() if task is None else get_task(task) if isinstance(task, str) else task
        if self.cfg.kind not in (*self.task.pixel_policies, STILL):
            raise InputError(f"task {self.task.name!r} has no scripted policy {self.cfg.kind!r}; expected one of "
                             f"{', '.join((*self.task.pixel_policies, STILL))}.")
        self.reset()

    def _make(self, i: int, rng: np.random.Generator) -> ScriptedPolicy:
        if self.cfg.kind == STILL:
            return _Still()
        return self.task.pixel_policy(self.cfg.kind, self.cfg.seed + i, rng, self.cfg.miss)

    def reset(self) -> None:
        self._episodes: list[Degraded] | None = None

    def predict_action(self, obs: dict) -> np.ndarray:
        """obs: image (B, 1, H, W, 3) uint8 and agent_pos (B, 1, 4) -> actions (B, 1, 4) float32."""
        image, pos = np.asarray(obs["image"]), np.asarray(obs["agent_pos"], dtype=np.float32)
        if self.cameras is not None and image.ndim == 5 and image.shape[-1] == 3 * len(self.cameras):
            image = image[..., :3]  # the first view
        if image.ndim != 5 or image.shape[-1] != 3 or image.dtype != np.uint8 or pos.ndim != 3 or pos.shape[-1] != 4:
            raise InputError(f"scripted policies take image (B, T, H, W, 3) uint8 and agent_pos (B, T, 4), got "
                             f"{image.shape} {image.dtype} and {pos.shape}.")
        if self._episodes is not None and len(self._episodes) != len(image):
            raise InputError(f"this batch has {len(image)} episodes; reset() before starting {len(self._episodes)}.")
        now = [{"pixels": image[i, -1], "agent_pos": pos[i, -1]} for i in range(len(image))]
        if self._episodes is None:
            self._episodes = []
            c = self.cfg
            for i, o in enumerate(now):
                rng = np.random.default_rng([c.seed, i])
                hand_rng = np.random.default_rng([c.seed, i, 1])  # the noise's draws stay as they were
                policy = Degraded(self._make(i, hand_rng), rng, hand_rng, noise=c.noise, latency=c.latency,
                                  lag=c.lag, pause=c.pause, jitter=c.jitter, overshoot=c.overshoot)
                policy.reset(o, {})
                self._episodes.append(policy)
        return np.stack([policy(o, {}) for o, policy in zip(now, self._episodes)])[:, None]
