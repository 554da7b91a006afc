"""Imitation policies on image + agent_pos, one folder per policy (its config and its
network side by side), each registered by name (:mod:`iwsim.policies.registry`):
Diffusion Policy (``dp``, :mod:`iwsim.policies.diffusion`) and ACT (``act``,
:mod:`iwsim.policies.act`). A folder here holding a registered config is a policy: the
command line, the studies and bench/ read the names and presets from the registry.

    from iwsim.policies.factory import load_policy
    policy = load_policy("runs/pol/dp")          # a run (its last checkpoint) or a checkpoint
    policy.reset()
    actions = policy.predict_action({"image": (B, To, H, W, 3) uint8, "agent_pos": (B, To, 4)})
    # -> (B, Ta, 4): execute in order, then ask again

A checkpoint is a directory with ``model.safetensors`` (weights and normalisation
bounds) and ``config.json`` (``kind: policy``, the policy's name and its config).
Importing this package registers the policies without importing torch.
"""

from __future__ import annotations

import importlib
import pkgutil

from iwsim.policies.registry import (
    POLICIES,
    PRESETS,
    PolicyStageConfig,
    PolicyType,
    config_class,
    policy_name,
    policy_type,
    register_policy,
)

__all__ = ["POLICIES", "PRESETS", "PolicyStageConfig", "PolicyType", "config_class", "policy_name", "policy_type",
           "register_policy"]

for _folder in pkgutil.iter_modules(__path__):  # every policy folder registers its config on import
    if _folder.ispkg:
        importlib.import_module(f"{__name__}.{_folder.name}")
