"""EDM denoising (Karras et al. 2022), the multi-step diffusion baseline's objective and sampler.

The denoiser D(x; sigma) = c_skip x + c_out F(c_in x; c_noise) of a network F, trained
with log-normal sigmas and sampled by Euler steps along the Karras sigma ladder, as
DIAMOND's world model does (Alonso et al. 2024: P_mean -0.4, P_std 1.2, sigma in
[2e-3, 5], rho 7, 3 Euler steps). Data are the dynamics' standardised latents, so
sigma_data = 1.
"""

from __future__ import annotations

from collections.abc import Callable

import torch

from iwsim.diffusion.schedule import Schedule
from iwsim.errors import InputError

SIGMA_DATA = 1.0
P_MEAN, P_STD = -0.4, 1.2
SIGMA_MIN, SIGMA_MAX, RHO = 2e-3, 5.0, 7.0


def precondition(sigma: torch.Tensor, like: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """(c_skip, c_in, c_out) for sigmas (B,), shaped to broadcast with ``like`` (B, ...)."""
    s = sigma.to(like.dtype).view((-1,) + (1,) * (like.ndim - 1))
    d2 = SIGMA_DATA**2
    norm = (s**2 + d2).sqrt()
    return d2 / (s**2 + d2), 1 / norm, s * SIGMA_DATA / norm


def noise_input(sigma: torch.Tensor) -> torch.Tensor:
    """The level the network is told, c_noise = ln(sigma) / 4 on the scale of the
    consistency levels (x 1000): about -1550 at SIGMA_MIN, 400 at SIGMA_MAX."""
    return 250.0 * sigma.clamp_min(SIGMA_MIN).log()


def level_sigma(schedule: Schedule, levels: torch.Tensor) -> torch.Tensor:
    """The EDM sigma of a DDPM level: x_t / a_t = x0 + (b_t / a_t) eps."""
    flat = levels.flatten()
    a, b = schedule.coefficients(flat, flat.float())
    return (b / a).view(levels.shape)


def training_sigmas(n: int, generator: torch.Generator | None) -> torch.Tensor:
    """ln sigma ~ N(P_MEAN, P_STD^2)."""
    return (P_MEAN + P_STD * torch.randn(n, generator=generator)).exp()


def loss(net_out: torch.Tensor, x0: torch.Tensor, x_noisy: torch.Tensor, sigma: torch.Tensor) -> torch.Tensor:
    """Per-sample EDM loss (B,): lambda(sigma) c_out^2 |F - (x0 - c_skip x) / c_out|^2,
    which is |F - target|^2 with EDM's weighting lambda = 1 / c_out^2."""
    c_skip, _, c_out = precondition(sigma, x0)
    target = (x0 - c_skip * x_noisy) / c_out
    return ((net_out - target) ** 2).mean(tuple(range(1, x0.ndim)))


def karras_sigmas(steps: int) -> list[float]:
    """The sampler's sigmas, SIGMA_MAX down to SIGMA_MIN in ``steps`` values, then 0."""
    if steps < 1:
        raise InputError(f"Euler steps must be >= 1, got {steps}.")
    if steps == 1:
        return [SIGMA_MAX, 0.0]
    ramp = torch.linspace(0, 1, steps, dtype=torch.float64)
    lo, hi = SIGMA_MIN ** (1 / RHO), SIGMA_MAX ** (1 / RHO)
    return [float(s) for s in (hi + ramp * (lo - hi)) ** RHO] + [0.0]


def sample(net: Callable[[torch.Tensor, torch.Tensor, torch.Tensor], torch.Tensor], noise: torch.Tensor,
           steps: int) -> torch.Tensor:
    """Euler steps of the denoiser D(x; sigma) = c_skip x + c_out net(c_in x, c, c) along
    the Karras sigmas (EDM, Algorithm 1 without the second-order correction), from unit
    ``noise`` (B, ...) scaled to SIGMA_MAX."""
    sigmas = karras_sigmas(steps)
    x = noise * sigmas[0]
    b = x.shape[0]
    for sigma, nxt in zip(sigmas[:-1], sigmas[1:]):
        sig = torch.full((b,), sigma, device=x.device)
        c_skip, c_in, c_out = precondition(sig, x)
        c = noise_input(sig)
        denoised = c_skip * x + c_out * net(c_in * x, c, c)
        x = denoised if nxt == 0 else x + (nxt - sigma) / sigma * (x - denoised)
    return x
