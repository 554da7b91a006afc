"""Scripted policies behind the learned policies' interface, so that the same loops
(:func:`iwsim.eval.policy.rollout`, MuJoCo's vector env or the world model's) drive both.

    policy = ScriptedBatch("expert", noise=0.01, latency=2)
    policy.reset()
    actions = policy.predict_action({"image": (B, 1, H, W, 3) uint8, "agent_pos": (B, 1, 4)})
    # -> (B, 1, 4)

Each of the B episodes gets its own scripted policy, made on the first call after
``reset()``. They see nothing but the frame and ``agent_pos``: the block pose is
estimated from the pixels (``pose_source="pixels"``), so a scripted policy behaves the
same in MuJoCo and inside a world model. Degradations, for policies of graded skill:
``noise`` adds Gaussian noise (metres, per coordinate) to every command, ``latency``
executes each command that many steps late (holding the pushers' first positions until
then). Noise is seeded per episode index, so results do not depend on the batch size.
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass

import numpy as np

from iwsim.envs.pixels import estimate_block_pose
from iwsim.envs.pusht import WORKSPACE
from iwsim.envs.scripted import ExpertPolicy, PlayPolicy, ScriptedPolicy
from iwsim.errors import InputError

KINDS = ("expert", "play")


@dataclass(frozen=True)
class ScriptedConfig:
    kind: str = "expert"
    noise: float = 0.0  # std of Gaussian noise on each command (m)
    latency: int = 0  # commands execute this many steps late
    seed: int = 0  # episode i draws its noise (and the play policy its choices) from seed + i

    def __post_init__(self) -> None:
        if self.kind not in KINDS:
            raise InputError(f"unknown scripted policy {self.kind!r}; expected one of {', '.join(KINDS)}.")
        if not (np.isfinite(self.noise) and self.noise >= 0):
            raise InputError(f"noise must be a finite number >= 0, got {self.noise}.")
        if self.latency < 0:
            raise InputError(f"latency must be 0 or more steps, got {self.latency}.")

    @property
    def name(self) -> str:
        parts = [self.kind] + ([f"noise{self.noise:g}"] if self.noise else []) + (
            [f"latency{self.latency}"] if self.latency else [])
        return "-".join(parts)


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


class ScriptedBatch:
    """B scripted episodes as one policy with ``obs_horizon = 1`` and one action per call."""

    obs_horizon = 1
    n_action_steps = 1
    kind = "scripted"

    def __init__(self, cfg: ScriptedConfig | str = "expert", **overrides) -> None:
        self.cfg = ScriptedConfig(cfg, **overrides) if isinstance(cfg, str) else cfg
        self.reset()

    def _make(self, i: int) -> ScriptedPolicy:
        if self.cfg.kind == "expert":
            return ExpertPolicy(pose_source="pixels")
        return _PixelPose(PlayPolicy(self.cfg.seed + i))

    def reset(self) -> None:
        self._episodes: list[tuple[ScriptedPolicy, np.random.Generator, deque]] | None = None

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
            for i, o in enumerate(now):
                policy = self._make(i)
                policy.reset(o, {})
                held = deque([o["agent_pos"].copy()] * self.cfg.latency, maxlen=self.cfg.latency + 1)
                self._episodes.append((policy, np.random.default_rng([self.cfg.seed, i]), held))
        actions = []
        for o, (policy, rng, queue) in zip(now, self._episodes):
            a = np.asarray(policy(o, {}), dtype=np.float64)
            if self.cfg.noise:
                a = a + rng.normal(0.0, self.cfg.noise, a.shape)
            queue.append(np.clip(a, -WORKSPACE, WORKSPACE).astype(np.float32))
            actions.append(queue.popleft())
        return np.stack(actions)[:, None]
