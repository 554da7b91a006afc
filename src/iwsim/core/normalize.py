"""Min-max normalisation of (..., D) values to [-1, 1] over per-dimension bounds, as the
world model scales its actions and the imitation policies their actions and states."""

from __future__ import annotations

import numpy as np
import torch
from torch import nn


def widen(low: torch.Tensor, high: torch.Tensor, min_span: float) -> tuple[torch.Tensor, torch.Tensor]:
    """Bounds with the same centre and a span of at least ``min_span``, so that a constant
    dimension still normalises."""
    span = torch.clamp(high - low, min=min_span)
    return (low + high) / 2 - span / 2, (low + high) / 2 + span / 2


def scale(x: torch.Tensor, low: torch.Tensor, high: torch.Tensor) -> torch.Tensor:
    """Values in the data's units -> [-1, 1] over [low, high] (not clipped)."""
    return (x - low) / (high - low) * 2 - 1


def unscale(y: torch.Tensor, low: torch.Tensor, high: torch.Tensor) -> torch.Tensor:
    """The inverse of :func:`scale`."""
    return (y + 1) / 2 * (high - low) + low


class Normalizer(nn.Module):
    """Min-max scaling of (..., D) values to [-1, 1]; its bounds travel with the weights."""

    low: torch.Tensor  # (D,) buffers
    high: torch.Tensor

    def __init__(self, low: np.ndarray | torch.Tensor, high: np.ndarray | torch.Tensor) -> None:
        super().__init__()
        # on the CPU whatever the default device (see iwsim.core.checkpoint.build_within_memory);
        # the module is moved with its weights
        cpu = torch.device("cpu")
        lo, hi = widen(torch.as_tensor(low, dtype=torch.float32, device=cpu),
                       torch.as_tensor(high, dtype=torch.float32, device=cpu), 1e-4)
        self.register_buffer("low", lo)
        self.register_buffer("high", hi)

    def normalize(self, x: torch.Tensor) -> torch.Tensor:
        return scale(x, self.low, self.high)

    def unnormalize(self, y: torch.Tensor) -> torch.Tensor:
        return unscale(y, self.low, self.high)
