"""Scripted policies for the T-pushing task: ``play`` (data) and ``expert`` (goal-directed).

A policy is called as ``policy(obs, info) -> action`` after ``policy.reset(obs, info)``.
"""

from __future__ import annotations

import numpy as np

from iwsim.envs import POLICIES


class RandomPolicy:
    """Placeholder: uniform random targets (replaced by play/expert)."""

    def __init__(self, env, seed: int) -> None:
        self.space = env.action_space
        self.rng = np.random.default_rng(seed)

    def reset(self, obs: dict, info: dict) -> None:
        pass

    def __call__(self, obs: dict, info: dict) -> np.ndarray:
        return self.rng.uniform(self.space.low, self.space.high).astype(np.float32)


def make_policy(name: str, env, seed: int):
    if name not in POLICIES:
        raise ValueError(f"unknown policy {name!r}; expected one of {list(POLICIES)}.")
    return RandomPolicy(env, seed)
