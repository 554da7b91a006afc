"""Configs as frozen dataclasses, named presets in Python, and their JSON round trip.

The training loop's config lives here; the world model's configs and presets in
:mod:`iwsim.world_model.presets`, the policies' in :mod:`iwsim.policies`.

A preset is a complete config; command-line flags override single fields of it
(``dataclasses.replace``). The resolved config is written to the run directory and into
every checkpoint.
"""

from __future__ import annotations

import dataclasses
import typing
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, TypeVar

from iwsim.core.errors import InputError

if TYPE_CHECKING:
    from _typeshed import DataclassInstance

T = TypeVar("T", bound="DataclassInstance")


@dataclass(frozen=True)
class TrainConfig:
    """The generic loop's knobs (every stage uses this)."""

    steps: int = 10_000
    batch_size: int = 32  # global: split over DDP ranks
    lr: float = 3e-4
    warmup_steps: int = 200  # linear warm-up ...
    lr_decay: str = "cosine"  # ... then "cosine" to 0 at `steps`, or "constant"
    betas: tuple[float, float] = (0.9, 0.99)
    weight_decay: float = 0.0
    grad_clip: float = 1.0
    ema_decay: float = 0.999
    log_every: int = 25
    eval_every: int = 500
    checkpoint_every: int = 500
    seed: int = 0
    cpu_bf16: bool = False  # bf16 autocast on the CPU as well (CUDA always uses it)


def to_dict(cfg: Any) -> dict[str, Any]:
    """A config dataclass as plain JSON-ready data."""
    return dataclasses.asdict(cfg)


def from_dict(cls: type[T], data: dict[str, Any]) -> T:
    """Rebuild a (nested) config dataclass from ``to_dict`` output; unknown keys are errors."""
    hints = typing.get_type_hints(cls)
    names = {f.name for f in dataclasses.fields(cls)}
    unknown = set(data) - names
    if unknown:
        raise InputError(f"unknown {cls.__name__} fields {sorted(unknown)}.")
    kwargs = {}
    for name, value in data.items():
        hint = hints[name]
        if isinstance(hint, type) and dataclasses.is_dataclass(hint):  # a nested config
            value = from_dict(hint, value)
        elif typing.get_origin(hint) is tuple:
            value = _tuples(value)
        kwargs[name] = value
    return cls(**kwargs)


def _tuples(value: Any) -> Any:
    """JSON lists (nested too) back into the tuples a config holds."""
    return tuple(_tuples(v) for v in value) if isinstance(value, list | tuple) else value
