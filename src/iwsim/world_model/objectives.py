"""The dynamics objectives: one table ``{name: Objective(loss, sample)}`` that training and
inference both use, so the two can never disagree on what a name means.

Every objective generates a tensor y (B, C, h, w) (the next latent, or its change from
the last one) from a network ``net(x, t, s) -> out`` whose conditioning (context,
actions) is closed over; ``t`` and ``s`` (B,) are what the network is told about its
input's noise and the level it jumps to, in embedding units (0 .. 1000).

- ``consistency`` (ours): a consistency jump network (:mod:`iwsim.diffusion.consistency`)
  trained on jumps t -> s onto the same-noise target; sampled by jumps from pure noise.
- ``edm``: an EDM denoiser (:mod:`iwsim.diffusion.edm`) sampled by Euler steps, as
  DIAMOND's world model.
- ``regression``: one pass from zeros, trained by MSE (a deterministic predictor, as
  DINO-WM's).

``loss`` returns the per-element weighted error (B, C, h, w) (the caller weights cells and
reduces) and the objective's one-pass estimate of y (B, C, h, w), which unrolled training
feeds back as context.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import torch

from iwsim.diffusion import consistency, edm
from iwsim.diffusion.schedule import Schedule

Net = Callable[[torch.Tensor, torch.Tensor, torch.Tensor], torch.Tensor]


@dataclass(frozen=True)
class Levels:
    """Per-sample training noise (B,): consistency levels t > s (integers) and EDM sigmas."""

    t: torch.Tensor
    s: torch.Tensor
    sigma: torch.Tensor


def _consistency_loss(net: Net, schedule: Schedule, y0: torch.Tensor, levels: Levels, eps: torch.Tensor
                      ) -> tuple[torch.Tensor, torch.Tensor]:
    t, s = levels.t, levels.s
    x_t, x_s = schedule.noise(y0, t, eps), schedule.noise(y0, s, eps)
    v = net(x_t, t.float(), s.float())
    fixed = lambda *_: v  # noqa: E731  (one network pass serves both jumps)
    out = consistency.jump(fixed, schedule, x_t, t, s, None)
    estimate = consistency.jump(fixed, schedule, x_t, t, torch.zeros_like(t), None)  # x0_hat
    w = consistency.loss_weight(schedule, t).view(-1, 1, 1, 1)
    return (out - x_s) ** 2 * w, estimate


def _consistency_sample(net: Net, schedule: Schedule, noise: torch.Tensor, steps: int) -> torch.Tensor:
    return consistency.sample(lambda x, t, s, _: net(x, t.float(), s.float()), schedule, None,
                              tuple(noise.shape), steps, noise=noise)


def _edm_loss(net: Net, schedule: Schedule, y0: torch.Tensor, levels: Levels, eps: torch.Tensor
              ) -> tuple[torch.Tensor, torch.Tensor]:
    sigma = levels.sigma
    x_noisy = y0 + sigma.view(-1, 1, 1, 1) * eps
    c_skip, c_in, c_out = edm.precondition(sigma, y0)
    c = edm.noise_input(sigma)
    out = net(c_in * x_noisy, c, c)
    return (out - (y0 - c_skip * x_noisy) / c_out) ** 2, c_skip * x_noisy + c_out * out


def _edm_sample(net: Net, schedule: Schedule, noise: torch.Tensor, steps: int) -> torch.Tensor:
    return edm.sample(net, noise, steps)


def _regression_loss(net: Net, schedule: Schedule, y0: torch.Tensor, levels: Levels, eps: torch.Tensor
                     ) -> tuple[torch.Tensor, torch.Tensor]:
    out = _regression_sample(net, schedule, y0, 1)
    return (out - y0) ** 2, out


def _regression_sample(net: Net, schedule: Schedule, noise: torch.Tensor, steps: int) -> torch.Tensor:
    b = noise.shape[0]
    return net(torch.zeros_like(noise), torch.full((b,), float(schedule.T), device=noise.device),
               torch.zeros(b, device=noise.device))


@dataclass(frozen=True)
class Objective:
    """``loss(net, schedule, y0, levels, eps) -> (error (B, C, h, w), estimate of y0)``;
    ``sample(net, schedule, noise, steps) -> y`` from clipped Gaussian ``noise`` in
    ``steps`` jumps (consistency) or Euler steps (edm); regression ignores both."""

    loss: Callable[[Net, Schedule, torch.Tensor, Levels, torch.Tensor], tuple[torch.Tensor, torch.Tensor]]
    sample: Callable[[Net, Schedule, torch.Tensor, int], torch.Tensor]


OBJECTIVES: dict[str, Objective] = {
    "consistency": Objective(_consistency_loss, _consistency_sample),
    "edm": Objective(_edm_loss, _edm_sample),
    "regression": Objective(_regression_loss, _regression_sample),
}
