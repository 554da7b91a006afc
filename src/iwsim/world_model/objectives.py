"""The dynamics objectives: one table ``{name: Objective(model, loss, sample, steps_knob)}`` that training and
inference both use, so the two can never disagree on what a name means.

Every objective generates a tensor y (B, C, h, w) (the next latent, or its change from
the last one) from a network ``net(x, t, s, **extra_args) -> out`` (the conditioning,
context and actions, in ``extra_args``); ``t`` and ``s`` (B,) are what the network is told
about its input's noise and the level it jumps to, in embedding units (0 .. 1000). The
objective wraps the network once (``Objective.model``) in the samplers' convention
(:mod:`iwsim.diffusion`) and reuses that module's loss and sampler:

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
from typing import Any, Generic, TypeVar

import torch

from iwsim.diffusion import consistency, edm
from iwsim.diffusion.schedule import Schedule

Net = Callable[..., torch.Tensor]
Model = Callable[..., torch.Tensor]
ExtraArgs = dict[str, torch.Tensor]
M = TypeVar("M", bound=Model)  # an objective's model class


@dataclass(frozen=True)
class Levels:
    """Per-sample training noise (B,): consistency levels t > s (integers) and EDM sigmas."""

    t: torch.Tensor
    s: torch.Tensor
    sigma: torch.Tensor


def _consistency_loss(model: consistency.JumpModel, y0: torch.Tensor, levels: Levels, eps: torch.Tensor,
                      extra_args: ExtraArgs) -> tuple[torch.Tensor, torch.Tensor]:
    return model.loss(y0, levels.t, levels.s, eps, **extra_args)


def _consistency_sample(model: consistency.JumpModel, noise: torch.Tensor, steps: int, extra_args: ExtraArgs
                        ) -> torch.Tensor:
    return consistency.sample_jumps(model, noise, consistency.jump_levels(steps, model.schedule.T - 1), extra_args)


def _edm_loss(model: edm.Denoiser, y0: torch.Tensor, levels: Levels, eps: torch.Tensor, extra_args: ExtraArgs
              ) -> tuple[torch.Tensor, torch.Tensor]:
    return model.loss(y0, eps, levels.sigma, **extra_args)


def _edm_sample(model: edm.Denoiser, noise: torch.Tensor, steps: int, extra_args: ExtraArgs) -> torch.Tensor:
    sigmas = edm.karras_sigmas(steps)
    return edm.sample_euler(model, noise * sigmas[0], sigmas, extra_args)


class OnePass:
    """The regression objective's model: the network, told its input is at level T and
    goes to level 0."""

    def __init__(self, net: Net, schedule: Schedule) -> None:
        self.net, self.top = net, float(schedule.T)

    def __call__(self, x: torch.Tensor, t: torch.Tensor, s: torch.Tensor, **extra_args: torch.Tensor
                 ) -> torch.Tensor:
        return self.net(x, t, s, **extra_args)


def _regression_loss(model: OnePass, y0: torch.Tensor, levels: Levels, eps: torch.Tensor, extra_args: ExtraArgs
                     ) -> tuple[torch.Tensor, torch.Tensor]:
    out = _regression_sample(model, y0, 1, extra_args)
    return (out - y0) ** 2, out


def _regression_sample(model: OnePass, noise: torch.Tensor, steps: int, extra_args: ExtraArgs) -> torch.Tensor:
    b = noise.shape[0]
    return model(torch.zeros_like(noise), torch.full((b,), model.top, device=noise.device),
                 torch.zeros(b, device=noise.device), **extra_args)


@dataclass(frozen=True)
class Objective(Generic[M]):
    """``model(net, schedule)`` wraps the network once; ``loss(model, y0, levels, eps,
    extra_args) -> (error (B, C, h, w), estimate of y0)``; ``sample(model, noise, steps,
    extra_args) -> y`` from clipped Gaussian ``noise`` in ``steps`` of the inference knob
    named ``steps_knob`` (``jumps`` or ``euler_steps``; regression ignores it)."""

    model: Callable[[Net, Schedule], M]
    loss: Callable[[M, torch.Tensor, Levels, torch.Tensor, ExtraArgs], tuple[torch.Tensor, torch.Tensor]]
    sample: Callable[[M, torch.Tensor, int, ExtraArgs], torch.Tensor]
    steps_knob: str


def _edm_model(net: Net, schedule: Schedule) -> edm.Denoiser:
    return edm.Denoiser(net)


OBJECTIVES: dict[str, Objective[Any]] = {
    "consistency": Objective(consistency.JumpModel, _consistency_loss, _consistency_sample, "jumps"),
    "edm": Objective(_edm_model, _edm_loss, _edm_sample, "euler_steps"),
    "regression": Objective(OnePass, _regression_loss, _regression_sample, "jumps"),
}
