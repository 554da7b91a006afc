"""Consistency "jumps" between noise levels, their training loss and the sampler.

A jump network ``net(x_t, t, s, **extra_args) -> v`` predicts the v-target (Salimans &
Ho 2022) of its input; the jump itself, :class:`JumpModel`, is a fixed function around it
(CTM, Kim et al. 2024, in the DDPM parameterisation):

    x0_hat  = a_t x_t - b_t v                    (v = a_t eps - b_t x0)
    eps_hat = b_t x_t + a_t v
    G(x_t; t, s) = a_s x0_hat + b_s eps_hat      (a DDIM step from t straight to s)

so G(x; t, t) = x and G(x; 0, s) = x whatever the network says. Training uses one noise
draw for both ends of a jump ("same noise"): x_t and x_s share eps, and G must land on x_s.
"""

from __future__ import annotations

from collections.abc import Callable

import torch
from tqdm import tqdm

from iwsim.core.errors import InputError
from iwsim.diffusion.schedule import Schedule

JumpNet = Callable[..., torch.Tensor]  # net(x_t, t, s, **extra_args) -> v
SNR_MIN, SNR_MAX = 1.0, 5.0  # loss weight: the SNR of the input level, clipped to [1, 5]


def _per_sample(w: torch.Tensor, like: torch.Tensor) -> torch.Tensor:
    return w.view((-1,) + (1,) * (like.ndim - 1))


def loss_weight(schedule: Schedule, t: torch.Tensor) -> torch.Tensor:
    """min(max(SNR(t), 1), 5): min-SNR-5 (Hang et al. 2023) with a floor of 1 so that
    jumps from pure noise, the 1-jump decode, still learn (truncated SNR, Salimans & Ho)."""
    return schedule.snr(t).clamp(SNR_MIN, SNR_MAX)


class JumpModel:
    """A v-predicting jump network in the samplers' convention (:mod:`iwsim.diffusion`):
    ``model(x_t, t, s, **extra_args)`` is the jump G(x_t; t, s) from levels t (B,) to
    levels s (B,), s <= t; the network holds the weights, the model none."""

    def __init__(self, net: JumpNet, schedule: Schedule) -> None:
        self.net, self.schedule = net, schedule

    def __call__(self, x_t: torch.Tensor, t: torch.Tensor, s: torch.Tensor, **extra_args: torch.Tensor | None
                 ) -> torch.Tensor:
        return self.jump(self.net(x_t, t, s, **extra_args), x_t, t, s)

    def jump(self, v: torch.Tensor, x_t: torch.Tensor, t: torch.Tensor, s: torch.Tensor) -> torch.Tensor:
        """G(x_t; t, s) around the network's output ``v``."""
        a_t, b_t = self.schedule.coefficients(t, x_t)
        a_s, b_s = self.schedule.coefficients(s, x_t)
        x0_hat = a_t * x_t - b_t * v
        eps_hat = b_t * x_t + a_t * v
        return a_s * x0_hat + b_s * eps_hat

    def loss(self, x0: torch.Tensor, t: torch.Tensor, s: torch.Tensor, eps: torch.Tensor,
             **extra_args: torch.Tensor | None) -> tuple[torch.Tensor, torch.Tensor]:
        """The weighted per-element error (B, ...) of the jump t -> s from x_t onto the
        same-noise x_s, and the same network pass's jump to 0 (the estimate of x0)."""
        x_t, x_s = self.schedule.noise(x0, t, eps), self.schedule.noise(x0, s, eps)
        v = self.net(x_t, t, s, **extra_args)
        out, estimate = self.jump(v, x_t, t, s), self.jump(v, x_t, t, torch.zeros_like(t))
        return (out - x_s) ** 2 * _per_sample(loss_weight(self.schedule, t), x0), estimate


def jump_loss(model: JumpModel, x0: torch.Tensor, t: torch.Tensor, s: torch.Tensor, eps: torch.Tensor,
              extra_args: dict | None = None) -> torch.Tensor:
    """Per-sample weighted error (B,) of the jump t -> s from x_t onto the same-noise x_s,
    for x0 (B, ...), levels 0 <= s < t <= T (B,) and one noise draw eps shaped like x0
    (the error is averaged over each sample before it is weighted)."""
    extra_args = extra_args or {}
    x_t, x_s = model.schedule.noise(x0, t, eps), model.schedule.noise(x0, s, eps)
    err = ((model(x_t, t, s, **extra_args) - x_s) ** 2).mean(tuple(range(1, x0.ndim)))
    return err * loss_weight(model.schedule, t)


def two_jump_loss(model: JumpModel, x0: torch.Tensor, t: torch.Tensor, s: torch.Tensor, eps: torch.Tensor,
                  extra_args: dict | None = None) -> tuple[torch.Tensor, dict[str, float]]:
    """The decoder's objective: the jump t -> s onto the same-noise x_s (:func:`jump_loss`),
    then s -> 0 onto x0.

    Returns the scalar loss and its two terms (floats, for logging).
    """
    extra_args = extra_args or {}
    x_s = model.schedule.noise(x0, s, eps)
    first = jump_loss(model, x0, t, s, eps, extra_args).mean()
    second = ((model(x_s, s, torch.zeros_like(s), **extra_args) - x0) ** 2).mean(tuple(range(1, x0.ndim)))
    second = (second * loss_weight(model.schedule, s)).mean()
    return first + second, {"loss_jump": first.item(), "loss_to_zero": second.item()}


def sample_levels(batch: int, num_levels: int, generator: torch.Generator | None, top_fraction: float = 0.0,
                  device: torch.device | str = "cpu", zero_fraction: float = 0.0) -> tuple[torch.Tensor, torch.Tensor]:
    """Training levels: t uniform in [1, T], except that a ``top_fraction`` of the batch
    starts from T - 1, where sampling starts; s uniform in [0, t), except that a
    ``zero_fraction`` jumps straight to s = 0."""
    t = torch.randint(1, num_levels + 1, (batch,), generator=generator, device=device)
    top = torch.rand(batch, generator=generator, device=device) < top_fraction
    t = torch.where(top, torch.full_like(t, num_levels - 1), t)
    s = (torch.rand(batch, generator=generator, device=device) * t).long()
    if zero_fraction > 0:
        zero = torch.rand(batch, generator=generator, device=device) < zero_fraction
        s = torch.where(zero, torch.zeros_like(s), s)
    return t, s


def jump_levels(num_jumps: int, start: int) -> list[int]:
    """Levels visited by a K-jump decode from ``start``: K = 3 from 999 gives
    999, 666, 333, 0 (the public code's schedule)."""
    if num_jumps < 1:
        raise InputError(f"num_jumps must be >= 1, got {num_jumps}.")
    return [round(start * (num_jumps - k) / num_jumps) for k in range(num_jumps + 1)]


@torch.no_grad()
def sample_jumps(model: JumpModel, x: torch.Tensor, levels: list[int], extra_args: dict | None = None,
                 disable: bool = True) -> torch.Tensor:
    """Deterministic jumps of ``x`` (B, ...) from ``levels[0]`` through each of ``levels``
    (:func:`jump_levels`) to the last."""
    extra_args = extra_args or {}
    b = x.shape[0]
    for t, s in tqdm(list(zip(levels[:-1], levels[1:])), desc="jumps", disable=disable):
        x = model(x, torch.full((b,), t, device=x.device), torch.full((b,), s, device=x.device), **extra_args)
    return x
