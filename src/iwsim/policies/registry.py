"""The learned policies by name (LeRobot's ``register_subclass``): each policy's config
class is registered with its name, its network class, the config fields that only change
how it runs, and its training presets. The names are what checkpoints store (``policy`` in
``config.json``), so a registered name never changes.

    @register_policy("dp", model="iwsim.policies.diffusion.model:DiffusionPolicy",
                     execution=("n_action_steps", "inference_steps"), presets={...})
    @dataclass(frozen=True)
    class DiffusionConfig: ...

The network class is named, not imported, so that the command line reads the names and
presets without importing torch; it is imported on first use.
"""

from __future__ import annotations

import dataclasses
import importlib
from collections.abc import Callable
from typing import Any, TypeVar

from iwsim.core.config import TrainConfig
from iwsim.core.errors import InputError

C = TypeVar("C", bound=type)
ACTION_KEYS = ("action", "target")  # what a policy may learn to output (PolicyStageConfig.actions)


@dataclasses.dataclass(frozen=True)
class PolicyStageConfig:
    """A policy type, its config and the training loop's knobs."""

    policy: str = "dp"
    model: dict[str, Any] = dataclasses.field(default_factory=dict)  # the policy's config (to_dict)
    train: TrainConfig = TrainConfig()
    shift: int = 4  # training images move by up to this many pixels (random-shift augmentation)
    # The episode array the policy learns to output: "action", the commands as given, or
    # "target", the setpoints the speed-limited controller executed (smooth where a command jumps).
    actions: str = "action"

    def __post_init__(self) -> None:
        if self.actions not in ACTION_KEYS:
            raise InputError(f"actions must be one of {', '.join(ACTION_KEYS)}, got {self.actions!r}.")


# The training knobs of every policy's tiny preset (for tests): a few steps, checkpoints at 10 and 20.
TINY_TRAIN = TrainConfig(steps=20, batch_size=8, lr=1e-3, warmup_steps=2, eval_every=10, checkpoint_every=10,
                         log_every=5)


@dataclasses.dataclass(frozen=True)
class PolicyType:
    """A registered policy: its config class, its network (``module:Class``) and the config
    fields that only change how a trained network is run, not its weights."""

    name: str
    config_class: type
    model: str
    execution: tuple[str, ...] = ()

    def policy_class(self) -> type:
        """The network class (imported on first use)."""
        module, _, cls = self.model.partition(":")
        return getattr(importlib.import_module(module), cls)


POLICIES: dict[str, PolicyType] = {}  # by name, in registration order
PRESETS: dict[str, PolicyStageConfig] = {}  # every registered policy's training presets, by preset name


def register_policy(name: str, *, model: str, execution: tuple[str, ...] = (),
                    presets: dict[str, PolicyStageConfig] | None = None) -> Callable[[C], C]:
    """Class decorator for a policy's config class: records ``name`` -> the config class,
    its network ``model`` (``"module:Class"``, built as ``Class(cfg, action_norm,
    state_norm)``), its ``execution`` fields and its training ``presets`` (each of policy
    ``name``; the one named ``name`` is the default of ``iwsim train policy``)."""

    def register(cls: C) -> C:
        if name in POLICIES and POLICIES[name].config_class is not cls:
            raise ValueError(f"policy {name!r} is already registered (by {POLICIES[name].config_class.__name__}).")
        for preset, cfg in (presets or {}).items():
            if cfg.policy != name:
                raise ValueError(f"preset {preset!r} is a {cfg.policy!r} policy, registered for {name!r}.")
            if preset in PRESETS and PRESETS[preset] != cfg:
                raise ValueError(f"preset {preset!r} is already registered.")
        POLICIES[name] = PolicyType(name, cls, model, tuple(execution))
        PRESETS.update(presets or {})
        return cls

    return register


def policy_type(policy: str) -> PolicyType:
    """The registered policy ``policy``; an unknown name is the user's error."""
    if policy not in POLICIES:
        raise InputError(f"unknown policy {policy!r}; expected one of {', '.join(POLICIES)}.")
    return POLICIES[policy]


def config_class(policy: str) -> type:
    """The config class of the policy named ``policy``."""
    return policy_type(policy).config_class


def policy_name(cfg: Any) -> str:
    """The registered name of the policy a config (an instance of a registered config class) is for."""
    for name, entry in POLICIES.items():
        if type(cfg) is entry.config_class:
            return name
    raise InputError(f"no registered policy takes a {type(cfg).__name__}.")
