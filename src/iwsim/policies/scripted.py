"""Scripted policies behind the learned policies' interface, so that the same loops
(:func:`iwsim.eval.policy.rollout`, MuJoCo's vector env or the world model's) drive both.

    policy = ScriptedBatch("expert", noise=0.01, latency=2)  # or "expert-wide", "play", "still"
    policy.reset()
    actions = policy.predict_action({"image": (B, 1, H, W, 3) uint8, "agent_pos": (B, 1, 4)})
    # -> (B, 1, 4)

Each of the B episodes gets its own scripted policy, made on the first call after
``reset()``. They see nothing but the frame and ``agent_pos``: the block pose is
estimated from the pixels (``pose_source="pixels"``), so a scripted policy behaves the
same in MuJoCo and inside a world model. Degradations, for policies of graded skill:
``noise`` adds Gaussian noise (metres, per coordinate) to every command, ``latency``
executes each command that many steps late (holding the pushers' first positions until
then). A human-like hand (:class:`iwsim.envs.scripting.Hand`) between the policy and the robot: ``lag`` (a
slow hand that follows the policy's commands with that time constant, in steps),
``pause`` (the chance per step of holding the command still for 5-20 steps),
``jitter`` (a tremor: smooth noise of that std, correlated over ~5 steps) and
``overshoot`` (a hand that leads its motion by that many steps, so every stop overshoots
and comes back); ``miss`` aims the expert at a block displaced by that many metres in a
direction (and turned by an angle) drawn per episode: expert-like motions that miss.
The experts are those of :data:`iwsim.envs.scripted.EXPERTS` (``expert``, the precise pinch;
``expert-wide``, the forgiving one); the ``still`` policy holds the pushers where they start.
All draws are seeded per episode index, so results do not depend on the batch size.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from iwsim.envs.pixels import estimate_block_pose
from iwsim.envs.scripted import EXPERTS, ExpertPolicy, Pinch, PlayPolicy
from iwsim.envs.scripting import Degraded, ScriptedPolicy
from iwsim.errors import InputError

KINDS = (*EXPERTS, "play", "still")


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
        if self.miss and self.kind not in EXPERTS:
            raise InputError(f"miss displaces an expert's aim; the {self.kind!r} policy has none.")

    @property
    def name(self) -> str:
        parts = [self.kind] + [f"{k}{getattr(self, k):g}" for k in ("noise", "latency", "lag", "pause", "jitter",
                                                                    "overshoot", "miss") if getattr(self, k)]
        return "-".join(parts)


class _MissingExpert(ExpertPolicy):
    """A pixel expert (its ``pinch``) aiming at a block displaced by ``offset`` (x, y, yaw)
    from where it sees it: the expert's kind of motion, not aimed at where the block is."""

    def __init__(self, pinch: Pinch, offset: np.ndarray) -> None:
        super().__init__(pose_source="pixels", pinch=pinch)
        self.offset = offset

    def block_pose(self, obs: dict, info: dict) -> np.ndarray | None:
        pose = super().block_pose(obs, info)
        return None if pose is None else pose + self.offset


class _PixelPose:
    """A scripted policy that takes its block pose from the frame (for the play policy,
    which otherwise reads ``info["block_pose"]`` from the simulator)."""

    def __init__(self, policy: ScriptedPolicy) -> None:
        self.policy = policy
        self._pose = np.zeros(3)

    def _info(self, obs: dict) -> dict:
        est = estimate_block_pose(obs["pixels"])
        if est.found:  # when the block is hidden, keep the last pose seen
            self._pose = est.pose
        return {"block_pose": self._pose}

    def reset(self, obs: dict, info: dict) -> None:
        self.policy.reset(obs, self._info(obs))

    def __call__(self, obs: dict, info: dict) -> np.ndarray:
        return self.policy(obs, self._info(obs))


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

    def __init__(self, cfg: ScriptedConfig | str = "expert", **overrides) -> None:
        self.cfg = ScriptedConfig(cfg, **overrides) if isinstance(cfg, str) else cfg
        self.reset()

    def _make(self, i: int, rng: np.random.Generator) -> ScriptedPolicy:
        if self.cfg.kind == "still":
            return _Still()
        if self.cfg.kind not in EXPERTS:
            return _PixelPose(PlayPolicy(self.cfg.seed + i))
        pinch = EXPERTS[self.cfg.kind]()
        if self.cfg.miss:
            angle = rng.uniform(-np.pi, np.pi)
            return _MissingExpert(pinch, np.array([self.cfg.miss * np.cos(angle), self.cfg.miss * np.sin(angle),
                                                   rng.uniform(-np.pi / 2, np.pi / 2)]))
        return ExpertPolicy(pose_source="pixels", pinch=pinch)

    def reset(self) -> None:
        self._episodes: list[Degraded] | None = None

    def predict_action(self, obs: dict) -> np.ndarray:
        """obs: image (B, 1, H, W, 3) uint8 and agent_pos (B, 1, 4) -> actions (B, 1, 4) float32."""
        image, pos = np.asarray(obs["image"]), np.asarray(obs["agent_pos"], dtype=np.float32)
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
