"""Imitation policies on image + agent_pos: Diffusion Policy (``dp``) and ACT (``act``).

    policy = load_policy("runs/pol/dp")          # a run (its last checkpoint) or a checkpoint
    policy.reset()
    actions = policy.predict_action({"image": (B, To, H, W, 3) uint8, "agent_pos": (B, To, 4)})
    # -> (B, Ta, 4): execute in order, then ask again

A checkpoint is a directory with ``model.safetensors`` (weights and normalisation
bounds) and ``config.json`` (``kind: policy``, the policy type and its config).
"""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Any

import torch
from torch import nn

from iwsim.checkpoint import CheckpointError, build_within_memory, load_model_dir
from iwsim.config import TrainConfig, from_dict, to_dict
from iwsim.errors import InputError
from iwsim.policies.act import ACTConfig, ACTPolicy
from iwsim.policies.common import Normalizer
from iwsim.policies.diffusion import DiffusionConfig, DiffusionPolicy

KIND = "policy"
POLICIES = ("dp", "act")


@dataclasses.dataclass(frozen=True)
class PolicyStageConfig:
    """A policy type, its config and the training loop's knobs."""

    policy: str = "dp"
    model: dict[str, Any] = dataclasses.field(default_factory=dict)  # the policy's config (to_dict)
    train: TrainConfig = TrainConfig()
    shift: int = 4  # training images move by up to this many pixels (random-shift augmentation)


def config_class(policy: str) -> type:
    if policy == "dp":
        return DiffusionConfig
    if policy == "act":
        return ACTConfig
    raise InputError(f"unknown policy {policy!r}; expected one of {', '.join(POLICIES)}.")


def make_policy(policy: str, model: dict[str, Any], action_norm: Normalizer, state_norm: Normalizer) -> nn.Module:
    """A policy of type ``policy`` with config fields ``model`` (defaults for the rest)."""
    cfg = from_dict(config_class(policy), model)
    if policy == "dp":
        return DiffusionPolicy(cfg, action_norm, state_norm)
    return ACTPolicy(cfg, action_norm, state_norm)


# Presets: the defaults of the paper-sized-down policies, and tiny ones for tests.
PRESETS: dict[str, PolicyStageConfig] = {
    "dp": PolicyStageConfig("dp", {}, TrainConfig(steps=20_000, batch_size=64, lr=3e-4, warmup_steps=500,
                                                  weight_decay=1e-6, eval_every=1000, checkpoint_every=1000)),
    "act": PolicyStageConfig("act", {}, TrainConfig(steps=20_000, batch_size=32, lr=1e-4, warmup_steps=500,
                                                    weight_decay=1e-4, eval_every=1000, checkpoint_every=1000)),
    "tiny-dp": PolicyStageConfig("dp", {"image_features": 16, "encoder_channels": (8, 16, 16),
                                        "down_dims": (16, 32), "horizon": 8, "n_action_steps": 4,
                                        "inference_steps": 4},
                                 TrainConfig(steps=20, batch_size=8, lr=1e-3, warmup_steps=2, eval_every=10,
                                             checkpoint_every=10, log_every=5), shift=2),
    "tiny-act": PolicyStageConfig("act", {"chunk_size": 8, "dim": 32, "heads": 2, "enc_layers": 1, "dec_layers": 1,
                                          "ff_dim": 64},
                                  TrainConfig(steps=20, batch_size=8, lr=1e-3, warmup_steps=2, eval_every=10,
                                              checkpoint_every=10, log_every=5), shift=2),
}


def describe(policy: nn.Module) -> dict[str, Any]:
    """The parts of ``config.json`` that :func:`load_policy` reads."""
    return {"kind": KIND, "policy": policy.kind, "model": to_dict(policy.cfg),
            "action_dim": policy.action_dim, "state_dim": policy.state_dim}


# Config fields that only change how a trained network is run, not its weights.
EXECUTION_FIELDS = {"dp": ("n_action_steps", "inference_steps"), "act": ("n_action_steps", "temporal_ensemble")}


def load_policy(path: str | Path, device: str | torch.device = "cpu", n_action_steps: int | None = None,
                **execution: Any) -> nn.Module:
    """A trained policy from a checkpoint directory, or from a run (its last checkpoint).

    ``n_action_steps`` overrides how many actions of each predicted chunk are executed
    before the policy is queried again (Diffusion Policy's Ta; None: as trained). It only
    changes execution: the chunk the network predicts is the same. ``execution`` overrides
    the policy's other :data:`EXECUTION_FIELDS` the same way (DP's ``inference_steps``;
    ACT's ``temporal_ensemble``, None to execute ``n_action_steps`` of each chunk)."""
    path = Path(path)
    if (path / "checkpoints" / "last").exists():
        path = (path / "checkpoints" / "last").resolve()
    if not (path / "config.json").is_file() or not (path / "model.safetensors").is_file():
        raise CheckpointError(f"{path} is not a policy checkpoint (model.safetensors + config.json) or a run of "
                              "iwsim train policy.")
    config, tensors = load_model_dir(path, KIND)
    if n_action_steps is not None:
        execution = {**execution, "n_action_steps": n_action_steps}
    if execution:
        allowed = EXECUTION_FIELDS.get(config.get("policy", ""), ())
        unknown = sorted(set(execution) - set(allowed))
        if unknown:
            raise InputError(f"{', '.join(unknown)} cannot be changed when running a {config.get('policy')!r} policy; "
                             f"these can: {', '.join(allowed)}.")
        config["model"] = {**config.get("model", {}), **execution}
        from_dict(config_class(config.get("policy", "")), config["model"])  # a bad value: its one-line InputError
    try:
        a, s = int(config["action_dim"]), int(config["state_dim"])
        policy = build_within_memory(lambda: make_policy(config["policy"], config["model"], Normalizer(
            torch.zeros(a), torch.ones(a)), Normalizer(torch.zeros(s), torch.ones(s))), f"the policy of {path}")
        policy.load_state_dict(tensors)
        policy.image_size = int(config.get("image_size", 64))  # the frames it was trained on
    except (KeyError, TypeError, ValueError, RuntimeError) as e:
        raise CheckpointError(f"{path} does not hold a loadable policy ({' '.join(str(e).split())[:200]}).") from None
    return policy.to(device).eval()
