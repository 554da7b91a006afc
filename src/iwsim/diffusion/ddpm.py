"""DDPM training noise and the DDIM sampler (Ho et al. 2020; Song et al. 2021), as
Diffusion Policy uses them: an epsilon-predicting network over a discrete schedule.

``net(x, t) -> eps`` takes the noisy sample and the integer timesteps (B,); everything
else it needs (the observation condition) is closed over.
"""

from __future__ import annotations

import math
from collections.abc import Callable

import torch


def squared_cosine_alphas_cumprod(steps: int) -> torch.Tensor:
    """alpha-bar_t of the squared-cosine schedule (Nichol & Dhariwal 2021, Eq. 17), with
    betas clipped at 0.999 as diffusers' "squaredcos_cap_v2"."""
    def f(t: float) -> float:
        return math.cos((t + 0.008) / 1.008 * math.pi / 2) ** 2

    betas = torch.tensor([min(1 - f((i + 1) / steps) / f(i / steps), 0.999) for i in range(steps)], dtype=torch.float64)
    return torch.cumprod(1 - betas, 0).float()


def add_noise(x0: torch.Tensor, eps: torch.Tensor, abar: torch.Tensor) -> torch.Tensor:
    """x_t = sqrt(abar) x0 + sqrt(1 - abar) eps (DDPM, Eq. 4); ``abar`` broadcasts over x0."""
    return abar.sqrt() * x0 + (1 - abar).sqrt() * eps


def ddim_sample(net: Callable[[torch.Tensor, torch.Tensor], torch.Tensor], alphas_cumprod: torch.Tensor,
                noise: torch.Tensor, steps: int) -> torch.Tensor:
    """DDIM (eta = 0, Song et al. 2021, Eq. 12) in ``steps`` evenly spaced timesteps of the
    schedule, from ``noise`` (B, ...) to a sample clipped to [-1, 1] at every step."""
    b = noise.shape[0]
    timesteps = torch.linspace(len(alphas_cumprod) - 1, 0, steps).round().long().tolist()
    x = noise
    for i, t in enumerate(timesteps):
        abar = alphas_cumprod[t]
        eps = net(x, torch.full((b,), t, device=x.device))
        x0 = ((x - (1 - abar).sqrt() * eps) / abar.sqrt()).clamp(-1, 1)
        abar_prev = alphas_cumprod[timesteps[i + 1]] if i + 1 < len(timesteps) else torch.tensor(1.0)
        eps = (x - abar.sqrt() * x0) / (1 - abar).sqrt()  # consistent with the clipped x0
        x = abar_prev.sqrt() * x0 + (1 - abar_prev).sqrt() * eps
    return x
