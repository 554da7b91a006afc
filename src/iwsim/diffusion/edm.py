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

from iwsim.core.errors import InputError

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


def training_sigmas(n: int, generator: torch.Generator | None) -> torch.Tensor:
    """ln sigma ~ N(P_MEAN, P_STD^2)."""
    return (P_MEAN + P_STD * torch.randn(n, generator=generator)).exp()


class Denoiser:
    """A network F in the samplers' convention (:mod:`iwsim.diffusion`): ``model(x, sigma,
    s, **extra_args)`` is D(x; sigma) = c_skip x + c_out F(c_in x, c, c, **extra_args),
    told the level c = c_noise(sigma) in both level slots; ``s`` is not used."""

    def __init__(self, net: Callable[..., torch.Tensor]) -> None:
        self.net = net

    def __call__(self, x: torch.Tensor, sigma: torch.Tensor, s: torch.Tensor | None = None,
                 **extra_args: torch.Tensor) -> torch.Tensor:
        c_skip, c_in, c_out = precondition(sigma, x)
        c = noise_input(sigma)
        return c_skip * x + c_out * self.net(c_in * x, c, c, **extra_args)

    def loss(self, x0: torch.Tensor, eps: torch.Tensor, sigma: torch.Tensor, **extra_args: torch.Tensor
             ) -> tuple[torch.Tensor, torch.Tensor]:
        """The per-element EDM loss (B, ...) of x0 noised by ``eps`` at ``sigma`` (B,):
        lambda(sigma) c_out^2 |F - (x0 - c_skip x) / c_out|^2 = |F - target|^2 with EDM's
        weighting lambda = 1 / c_out^2; and the one-pass denoised estimate D(x; sigma)."""
        x_noisy = x0 + sigma.view((-1,) + (1,) * (x0.ndim - 1)) * eps
        c_skip, c_in, c_out = precondition(sigma, x0)
        c = noise_input(sigma)
        out = self.net(c_in * x_noisy, c, c, **extra_args)
        return (out - (x0 - c_skip * x_noisy) / c_out) ** 2, c_skip * x_noisy + c_out * out


def karras_sigmas(steps: int) -> list[float]:
    """The sampler's sigmas, SIGMA_MAX down to SIGMA_MIN in ``steps`` values, then 0."""
    if steps < 1:
        raise InputError(f"Euler steps must be >= 1, got {steps}.")
    if steps == 1:
        return [SIGMA_MAX, 0.0]
    ramp = torch.linspace(0, 1, steps, dtype=torch.float64)
    lo, hi = SIGMA_MIN ** (1 / RHO), SIGMA_MAX ** (1 / RHO)
    return [float(s) for s in (hi + ramp * (lo - hi)) ** RHO] + [0.0]


def sample_euler(model: Denoiser, x: torch.Tensor, sigmas: list[float], extra_args: dict | None = None
                 ) -> torch.Tensor:
    """Euler steps of the denoiser along ``sigmas`` (:func:`karras_sigmas`; EDM, Algorithm
    1 without the second-order correction), from ``x`` at ``sigmas[0]`` (unit noise times
    ``sigmas[0]``)."""
    extra_args = extra_args or {}
    b = x.shape[0]
    for sigma, nxt in zip(sigmas[:-1], sigmas[1:]):
        denoised = model(x, torch.full((b,), sigma, device=x.device), torch.full((b,), nxt, device=x.device),
                         **extra_args)
        x = denoised if nxt == 0 else x + (nxt - sigma) / sigma * (x - denoised)
    return x
