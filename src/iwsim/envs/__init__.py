"""Tasks (MuJoCo ground truth), their scripted policies and pixel scorers."""

from __future__ import annotations

import gymnasium as gym
import numpy as np
from gymnasium.envs.registration import register, registry

if "iwsim/BimanualPushT-v0" not in registry:
    register(
        id="iwsim/BimanualPushT-v0",
        entry_point="iwsim.envs.pusht:BimanualPushTEnv",
        max_episode_steps=600,  # the paper's evaluation horizon
    )

if "iwsim/WorldModel-v0" not in registry:
    register(
        id="iwsim/WorldModel-v0",
        entry_point="iwsim.envs.world_model_env:WorldModelEnv",
        max_episode_steps=600,
    )

TASKS = {"pusht": "iwsim/BimanualPushT-v0"}
POLICIES = ("play", "expert")


def check_task(task: str) -> str:
    """Return the Gymnasium id of ``task`` or raise a one-line ValueError."""
    if task not in TASKS:
        raise ValueError(f"unknown task {task!r}; expected one of {sorted(TASKS)}.")
    return TASKS[task]


def make_env(task: str, image_size: int = 64, **kwargs) -> gym.Env:
    """The task's environment without a time limit (episode length is the caller's)."""
    return gym.make(check_task(task), image_size=image_size, max_episode_steps=None, **kwargs)


def record_episode(task: str, policy: str, seed: int, steps: int, image_size: int = 64) -> dict[str, np.ndarray]:
    """Run one seeded episode and return its arrays, in the episode store's layout.

    Step t holds the observation before action t and the action itself:
    ``img`` (T, H, W, 3) uint8, ``state`` (T, 4) float32 (agent_pos), ``action`` (T, 4)
    float32 (as commanded), ``target`` (T, 4) float32 (the rate-limited setpoints action t
    executed, what the world model is conditioned on), ``block_pose`` (T, 3) float32,
    ``iou`` (T,) float32 and ``n_contacts`` (T,) int32, with T = ``steps``. The same
    arguments give the same arrays.
    """
    from iwsim.envs.policies import make_policy

    env = make_env(task, image_size)
    try:
        pol = make_policy(policy, seed)
        obs, info = env.reset(seed=seed)
        pol.reset(obs, info)
        rows: dict[str, list] = {k: [] for k in ("img", "state", "action", "target", "block_pose", "iou",
                                                 "n_contacts")}
        for _ in range(steps):
            action = np.asarray(pol(obs, info), dtype=np.float32)
            rows["img"].append(obs["pixels"])
            rows["state"].append(obs["agent_pos"])
            rows["action"].append(action)
            rows["block_pose"].append(info["block_pose"])
            rows["iou"].append(info["iou"])
            rows["n_contacts"].append(info["n_contacts"])
            obs, _, _, _, info = env.step(action)
            rows["target"].append(info["target"])
    finally:
        env.close()
    dtypes = {"img": np.uint8, "n_contacts": np.int32}
    return {k: np.asarray(v, dtype=dtypes.get(k, np.float32)) for k, v in rows.items()}
