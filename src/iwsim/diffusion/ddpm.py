"""DDPM training noise and the DDIM sampler (Ho et al. 2020; Song et al. 2021), as
Diffusion Policy uses them: an epsilon-predicting network over a discrete schedule.

``net(x, t, **extra_args) -> eps`` takes the noisy sample, the integer timesteps (B,) and
the condition; :class:`EpsDenoiser` wraps it in the samplers' convention
(:mod:`iwsim.diffusion`).
"""

from __future__ import annotations

import math
from collections.abc import Callable

import numpy as np
import torch
from torch.nn import functional as F


def squared_cosine_alphas_cumprod(steps: int) -> torch.Tensor:
    """alpha-bar_t of the squared-cosine schedule (Nichol & Dhariwal 2021, Eq. 17), with
    betas clipped at 0.999 as diffusers' "squaredcos_cap_v2"."""
    def f(t: float) -> float:
        return math.cos((t + 0.008) / 1.008 * math.pi / 2) ** 2

    abar = np.cumprod([1 - min(1 - f((i + 1) / steps) / f(i / steps), 0.999) for i in range(steps)])
    # NumPy's arithmetic, not torch's on the meta device (see iwsim.core.checkpoint.build_within_memory)
    return torch.tensor(abar, dtype=torch.float32)


def add_noise(x0: torch.Tensor, eps: torch.Tensor, abar: torch.Tensor) -> torch.Tensor:
    """x_t = sqrt(abar) x0 + sqrt(1 - abar) eps (DDPM, Eq. 4); ``abar`` broadcasts over x0."""
    return abar.sqrt() * x0 + (1 - abar).sqrt() * eps


class EpsDenoiser:
    """An epsilon-predicting network over the schedule ``alphas_cumprod`` in the samplers'
    convention: ``model(x, t, s, **extra_args)`` is the estimate of x0 (not clipped) from
    the network's noise at timesteps t (B,); ``s`` is not used."""

    def __init__(self, net: Callable[..., torch.Tensor], alphas_cumprod: torch.Tensor) -> None:
        self.net, self.alphas_cumprod = net, alphas_cumprod

    def _abar(self, t: torch.Tensor, like: torch.Tensor) -> torch.Tensor:
        return self.alphas_cumprod[t].view((-1,) + (1,) * (like.ndim - 1))

    def __call__(self, x: torch.Tensor, t: torch.Tensor, s: torch.Tensor | None = None,
                 **extra_args: torch.Tensor) -> torch.Tensor:
        abar = self._abar(t, x)
        eps = self.net(x, t, **extra_args)
        return (x - (1 - abar).sqrt() * eps) / abar.sqrt()

    def loss(self, x0: torch.Tensor, eps: torch.Tensor, t: torch.Tensor, **extra_args: torch.Tensor
             ) -> torch.Tensor:
        """DDPM's simple loss: the mean squared error of the noise ``eps`` predicted from x0
        noised at timesteps t (B,)."""
        return F.mse_loss(self.net(add_noise(x0, eps, self._abar(t, x0)), t, **extra_args), eps)


def ddim_timesteps(train_steps: int, steps: int) -> list[int]:
    """``steps`` evenly spaced timesteps of a ``train_steps`` schedule, the last first."""
    return torch.linspace(train_steps - 1, 0, steps).round().long().tolist()


def sample_ddim(model: EpsDenoiser, x: torch.Tensor, timesteps: list[int], extra_args: dict | None = None
                ) -> torch.Tensor:
    """DDIM (eta = 0, Song et al. 2021, Eq. 12) through ``timesteps`` (:func:`ddim_timesteps`)
    from noise ``x`` (B, ...) to a sample, its x0 estimate clipped to [-1, 1] at every step."""
    extra_args = extra_args or {}
    alphas_cumprod = model.alphas_cumprod
    b = x.shape[0]
    for i, t in enumerate(timesteps):
        last = i + 1 == len(timesteps)
        nxt = 0 if last else timesteps[i + 1]
        abar = alphas_cumprod[t]
        x0 = model(x, torch.full((b,), t, device=x.device), torch.full((b,), nxt, device=x.device),
                   **extra_args).clamp(-1, 1)
        abar_prev = torch.tensor(1.0) if last else alphas_cumprod[nxt]
        eps = (x - abar.sqrt() * x0) / (1 - abar).sqrt()  # consistent with the clipped x0
        x = abar_prev.sqrt() * x0 + (1 - abar_prev).sqrt() * eps
    return x
