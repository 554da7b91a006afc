"""Building, describing and loading the registered policies (:mod:`iwsim.policies.registry`)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import torch

from iwsim.core.checkpoint import CheckpointError, build_within_memory, load_json, load_model_dir, locate
from iwsim.core.config import TrainConfig, from_dict, to_dict
from iwsim.core.errors import InputError
from iwsim.envs.registry import DEFAULT_TASK, task_from_config
from iwsim.envs.task import Task
from iwsim.policies.common import Normalizer, Policy
from iwsim.policies.registry import POLICIES, config_class, policy_type

KIND = "policy"


def make_policy(policy: str, model: dict[str, Any], action_norm: Normalizer, state_norm: Normalizer) -> Policy:
    """A policy of type ``policy`` with config fields ``model`` (defaults for the rest)."""
    entry = policy_type(policy)
    return entry.policy_class()(from_dict(entry.config_class, model), action_norm, state_norm)


def describe(policy: Policy) -> dict[str, Any]:
    """The parts of ``config.json`` that :func:`load_policy` reads."""
    return {"kind": KIND, "policy": policy.kind, "model": to_dict(policy.cfg),
            "action_dim": policy.action_dim, "state_dim": policy.state_dim}


def complete_config(config: dict[str, Any]) -> dict[str, Any]:
    """A stored run's config with the model and training fields added to iwsim since filled
    with their defaults, as they are read back (a run started before a new field resumes)."""
    if config.get("policy") not in POLICIES or not isinstance(config.get("model"), dict):
        return config
    config = {**config, "model": to_dict(from_dict(config_class(config["policy"]), config["model"]))}
    if isinstance(config.get("train"), dict):
        config["train"] = to_dict(from_dict(TrainConfig, config["train"]))
    return config


def checkpoint_dir(path: str | Path) -> Path:
    """The checkpoint directory of a policy run (its last checkpoint) or of a checkpoint
    (a shipped one, ``checkpoints/NAME``, from any working directory: :func:`locate`)."""
    path = locate(path)
    last = path / "checkpoints" / "last"
    return last.resolve() if last.exists() else path


def recorded_task(path: str | Path) -> Task | None:
    """The task whose episodes the policy at ``path`` (a run or a checkpoint) was trained on,
    as its ``config.json`` records it; None when it records none (trained before policies
    recorded their task) or there is no such file (loading the policy says what is wrong)."""
    config_path = checkpoint_dir(path) / "config.json"
    if not config_path.is_file():
        return None
    config = load_json(config_path)
    return task_from_config(config, config_path) if isinstance(config, dict) and "task" in config else None


def load_policy(path: str | Path, device: str | torch.device = "cpu", n_action_steps: int | None = None,
                **execution: Any) -> Policy:
    """A trained policy from a checkpoint directory, or from a run (its last checkpoint).

    ``n_action_steps`` overrides how many actions of each predicted chunk are executed
    before the policy is queried again (Diffusion Policy's Ta; None: as trained). It only
    changes execution: the chunk the network predicts is the same. ``execution`` overrides
    the policy's other registered execution fields the same way (DP's ``inference_steps``;
    ACT's ``temporal_ensemble``, None to execute ``n_action_steps`` of each chunk)."""
    path = checkpoint_dir(path)
    if not (path / "config.json").is_file() or not (path / "model.safetensors").is_file():
        raise CheckpointError(f"{path} is not a policy checkpoint (model.safetensors + config.json) or a run of "
                              "iwsim train policy.")
    config, tensors = load_model_dir(path, KIND)
    if n_action_steps is not None:
        execution = {**execution, "n_action_steps": n_action_steps}
    if execution:
        entry = POLICIES.get(config.get("policy", ""))
        allowed = entry.execution if entry else ()
        unknown = sorted(set(execution) - set(allowed))
        if unknown:
            raise InputError(f"{', '.join(unknown)} cannot be changed when running a {config.get('policy')!r} policy; "
                             f"these can: {', '.join(allowed)}.")
        config["model"] = {**config.get("model", {}), **execution}
        from_dict(config_class(config.get("policy", "")), config["model"])  # a bad value: its one-line InputError
    try:
        a, s = int(config["action_dim"]), int(config["state_dim"])
        policy = build_within_memory(lambda: make_policy(config["policy"], config["model"], Normalizer(
            np.zeros(a), np.ones(a)), Normalizer(np.zeros(s), np.ones(s))), f"the policy of {path}")
        policy.load_state_dict(tensors)
        # the frames it was trained on; a policy saved before they were recorded was trained on T-push's
        policy.image_size = int(config.get("image_size", DEFAULT_TASK.image_size))
    except (KeyError, TypeError, ValueError, RuntimeError) as e:
        raise CheckpointError(f"{path} does not hold a loadable policy ({' '.join(str(e).split())[:200]}).") from None
    policy.task = task_from_config(config, path / "config.json") if "task" in config else None
    policy.name = f"policy {path}"
    return policy.to(device).eval()
