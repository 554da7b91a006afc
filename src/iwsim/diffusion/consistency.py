"""Consistency "jumps" between noise levels, their training loss and the sampler.

A jump network ``net(x_t, t, s, cond) -> v`` predicts the v-target (Salimans & Ho 2022)
of its input; the jump itself is a fixed function around it (CTM, Kim et al. 2024, in
the DDPM parameterisation):

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

from iwsim.diffusion.schedule import Schedule, gaussian
from iwsim.errors import InputError

JumpNet = Callable[[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor], torch.Tensor]
SNR_MIN, SNR_MAX = 1.0, 5.0  # loss weight: the SNR of the input level, clipped to [1, 5]


def jump(net: JumpNet, schedule: Schedule, x_t: torch.Tensor, t: torch.Tensor, s: torch.Tensor,
         cond: torch.Tensor) -> torch.Tensor:
    """G(x_t; t, s): move x_t (B, ...) from levels t (B,) to levels s (B,), s <= t."""
    v = net(x_t, t, s, cond)
    a_t, b_t = schedule.coefficients(t, x_t)
    a_s, b_s = schedule.coefficients(s, x_t)
    x0_hat = a_t * x_t - b_t * v
    eps_hat = b_t * x_t + a_t * v
    return a_s * x0_hat + b_s * eps_hat


def loss_weight(schedule: Schedule, t: torch.Tensor) -> torch.Tensor:
    """min(max(SNR(t), 1), 5): min-SNR-5 (Hang et al. 2023) with a floor of 1 so that
    jumps from pure noise, the 1-jump decode, still learn (truncated SNR, Salimans & Ho)."""
    return schedule.snr(t).clamp(SNR_MIN, SNR_MAX)


def jump_loss(net: JumpNet, schedule: Schedule, x0: torch.Tensor, cond: torch.Tensor, t: torch.Tensor,
              s: torch.Tensor, eps: torch.Tensor) -> torch.Tensor:
    """Per-sample weighted error (B,) of the jump t -> s from x_t onto the same-noise x_s,
    for x0 (B, ...), levels 0 <= s < t <= T (B,) and one noise draw eps shaped like x0."""
    x_t, x_s = schedule.noise(x0, t, eps), schedule.noise(x0, s, eps)
    err = ((jump(net, schedule, x_t, t, s, cond) - x_s) ** 2).mean(tuple(range(1, x0.ndim)))
    return err * loss_weight(schedule, t)


def two_jump_loss(net: JumpNet, schedule: Schedule, x0: torch.Tensor, cond: torch.Tensor,
                  t: torch.Tensor, s: torch.Tensor, eps: torch.Tensor) -> tuple[torch.Tensor, dict[str, float]]:
    """The decoder's objective: the jump t -> s onto the same-noise x_s (:func:`jump_loss`),
    then s -> 0 onto x0.

    Returns the scalar loss and its two terms (floats, for logging).
    """
    x_s = schedule.noise(x0, s, eps)
    first = jump_loss(net, schedule, x0, cond, t, s, eps).mean()
    second = ((jump(net, schedule, x_s, s, torch.zeros_like(s), cond) - x0) ** 2).mean(tuple(range(1, x0.ndim)))
    second = (second * loss_weight(schedule, s)).mean()
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
def sample(net: JumpNet, schedule: Schedule, cond: torch.Tensor, shape: tuple[int, ...], num_jumps: int = 1,
           generator: torch.Generator | None = None, disable: bool = True,
           noise: torch.Tensor | None = None) -> torch.Tensor:
    """Draw x0 (shape, batch first) given ``cond`` by ``num_jumps`` deterministic jumps
    from clipped Gaussian noise at level T - 1 (drawn from ``generator``, or ``noise``
    when given). The same generator state gives the same output."""
    levels = jump_levels(num_jumps, schedule.T - 1)
    x = gaussian(shape, generator, device=cond.device, dtype=cond.dtype) if noise is None else noise
    b = shape[0]
    for t, s in tqdm(list(zip(levels[:-1], levels[1:])), desc="jumps", disable=disable):
        x = jump(net, schedule, x, torch.full((b,), t, device=x.device), torch.full((b,), s, device=x.device), cond)
    return x
