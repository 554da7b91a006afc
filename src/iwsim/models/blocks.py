"""Building blocks shared by the networks: residual blocks with FiLM, level embeddings."""

from __future__ import annotations

import math

import torch
from torch import nn
from torch.nn import functional as F


def group_norm(channels: int) -> nn.GroupNorm:
    return nn.GroupNorm(min(8, channels), channels)


def zero_init(conv: nn.Conv2d) -> None:
    """Zero the weights and bias of ``conv``: a residual branch (or an output) that starts at 0."""
    assert conv.bias is not None, "zero_init takes a convolution with a bias"
    nn.init.zeros_(conv.weight)
    nn.init.zeros_(conv.bias)


class ResBlock(nn.Module):
    """GroupNorm-SiLU-conv twice with a skip; ``emb`` (B, E), if given, modulates the
    second normalisation by FiLM (Perez et al. 2018): h * (1 + scale) + shift."""

    def __init__(self, cin: int, cout: int, emb_dim: int | None = None) -> None:
        super().__init__()
        self.norm1, self.conv1 = group_norm(cin), nn.Conv2d(cin, cout, 3, padding=1)
        self.norm2, self.conv2 = group_norm(cout), nn.Conv2d(cout, cout, 3, padding=1)
        self.film = nn.Linear(emb_dim, 2 * cout) if emb_dim else None
        self.skip = nn.Conv2d(cin, cout, 1) if cin != cout else nn.Identity()
        zero_init(self.conv2)

    def forward(self, x: torch.Tensor, emb: torch.Tensor | None = None) -> torch.Tensor:
        h = self.conv1(F.silu(self.norm1(x)))
        h = self.norm2(h)
        if self.film is not None:
            scale, shift = self.film(emb)[:, :, None, None].chunk(2, dim=1)
            h = h * (1 + scale) + shift
        return self.skip(x) + self.conv2(F.silu(h))


def sinusoidal(x: torch.Tensor, dim: int, max_period: float = 10_000.0, *, sin_first: bool = False,
               include_max: bool = False) -> torch.Tensor:
    """(B,) values -> (B, dim) sinusoidal features (Vaswani et al. 2017): cosines then
    sines of frequencies from 1 down to 1 / max_period (exclusive). ``sin_first`` and
    ``include_max`` (the last frequency exactly 1 / max_period) give Diffusion Policy's layout."""
    half = dim // 2
    steps = half - 1 if include_max else half
    freqs = torch.exp(-math.log(max_period) * torch.arange(half, device=x.device, dtype=torch.float32) / steps)
    angles = x.float()[:, None] * freqs[None]
    return torch.cat([angles.sin(), angles.cos()] if sin_first else [angles.cos(), angles.sin()], dim=1)
