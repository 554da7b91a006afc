"""The DDPM noise schedule on integer levels t = 0..T (T = 1000 by default).

Level 0 is clean data (alpha_bar = 1); level t > 0 uses the t-th of T sigmoid betas
(Jabri et al. 2022; the public code's choice). All functions broadcast over a batch of
levels ``t`` of shape (B,) and data of shape (B, ...).
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

NOISE_CLIP = 6.0  # Gaussian noise is clipped to +-6 (the public code does the same)


@dataclass(frozen=True)
class ScheduleConfig:
    num_levels: int = 1000  # T
    beta_start: float = 1e-4
    beta_end: float = 2e-2
    sigmoid_range: float = 6.0  # betas follow sigmoid(linspace(-r, r, T))


class Schedule:
    """alpha_bar(t) for integer levels t in [0, T], with x_t = a x0 + b eps, a^2 + b^2 = 1."""

    def __init__(self, cfg: ScheduleConfig = ScheduleConfig()) -> None:
        self.cfg = cfg
        r = cfg.sigmoid_range
        # A table of constants, on the CPU whatever the default device
        # (see iwsim.core.checkpoint.build_within_memory).
        cpu = torch.device("cpu")
        betas = torch.sigmoid(torch.linspace(-r, r, cfg.num_levels, dtype=torch.float64, device=cpu))
        betas = betas * (cfg.beta_end - cfg.beta_start) + cfg.beta_start
        # alpha_bar[0] = 1: level 0 is the clean image.
        self.alpha_bar = torch.cat([torch.ones(1, dtype=torch.float64, device=cpu), torch.cumprod(1 - betas, 0)])

    @property
    def T(self) -> int:  # noqa: N802  (the papers' name)
        return self.cfg.num_levels

    def coefficients(self, t: torch.Tensor, like: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """(a, b) = (sqrt(alpha_bar_t), sqrt(1 - alpha_bar_t)), shaped to broadcast with ``like``."""
        ab = self.alpha_bar.to(t.device)[t.long()].to(like.dtype)
        shape = (-1,) + (1,) * (like.ndim - 1)
        return ab.sqrt().view(shape), (1 - ab).clamp_min(0).sqrt().view(shape)

    def noise(self, x0: torch.Tensor, t: torch.Tensor, eps: torch.Tensor) -> torch.Tensor:
        """x_t = sqrt(ab_t) x0 + sqrt(1 - ab_t) eps (DDPM, Ho et al. 2020, Eq. 4)."""
        a, b = self.coefficients(t, x0)
        return a * x0 + b * eps

    def snr(self, t: torch.Tensor) -> torch.Tensor:
        """Signal-to-noise ratio alpha_bar / (1 - alpha_bar) per level (inf at t = 0)."""
        ab = self.alpha_bar.to(t.device)[t.long()]
        return (ab / (1 - ab)).float()


def gaussian(shape: tuple[int, ...], generator: torch.Generator | None, device: torch.device | str = "cpu",
             dtype: torch.dtype = torch.float32) -> torch.Tensor:
    """Standard normal noise clipped to +-NOISE_CLIP, drawn from ``generator``."""
    return torch.randn(shape, generator=generator, device=device, dtype=dtype).clamp_(-NOISE_CLIP, NOISE_CLIP)
