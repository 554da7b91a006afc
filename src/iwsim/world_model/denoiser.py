"""The dynamics network behind one calling convention (like k-diffusion's ``Denoiser``).

Training and inference both call a :class:`Denoiser`, the one place that knows the noise
units (the context-noise std in standardised latent units, told to the network in level
units), the objective's loss and sampler (:mod:`iwsim.world_model.objectives`) and whether
the network generates the next latent or its change from the newest context latent
(``predict_delta``):

    err, estimate = denoiser.loss(target, context, context_sigma, actions, levels, eps)
    next_latent = denoiser.sample(context, context_sigma, actions, noise, steps)

All latents are the dynamics' standardised latents; ``context`` (B, K, C, h, w), newest
last; ``actions`` (B, 2, A) normalised, the one that produced the newest context latent,
then the one that produces the next latent; ``context_sigma`` (B,) the std of the noise on
the context (training) or the std it is labelled with (inference).
"""

from __future__ import annotations

import torch

from iwsim.diffusion.schedule import Schedule
from iwsim.world_model.dynamics import Dynamics
from iwsim.world_model.objectives import OBJECTIVES, Levels, Net
from iwsim.world_model.presets import DynamicsStageConfig

LEVELS_PER_STD = 1000.0  # a context-noise std of 0.1 is told to the network as level 100


class Denoiser:
    """A dynamics network with its objective; holds no weights of its own (the network is
    registered by its owner, the world model or the training module)."""

    def __init__(self, network: Dynamics, cfg: DynamicsStageConfig) -> None:
        self.network, self.cfg = network, cfg
        self.schedule = Schedule(cfg.schedule)
        self.objective = OBJECTIVES[cfg.objective]

    def _net(self, context: torch.Tensor, context_sigma: torch.Tensor, actions: torch.Tensor) -> Net:
        level = context_sigma * LEVELS_PER_STD

        def net(x: torch.Tensor, t: torch.Tensor, s: torch.Tensor) -> torch.Tensor:
            return self.network(x, context, t, s, level, actions)

        return net

    def _base(self, context: torch.Tensor) -> torch.Tensor | None:
        return context[:, -1] if self.cfg.predict_delta else None

    def loss(self, target: torch.Tensor, context: torch.Tensor, context_sigma: torch.Tensor, actions: torch.Tensor,
             levels: Levels, eps: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """The objective's per-element error (B, C, h, w) for the next latent ``target``
        and its one-pass estimate of that latent (what unrolled training feeds back)."""
        base = self._base(context)
        y0 = target if base is None else target - base
        err, estimate = self.objective.loss(self._net(context, context_sigma, actions), self.schedule, y0, levels, eps)
        return err, estimate if base is None else base + estimate

    def sample(self, context: torch.Tensor, context_sigma: torch.Tensor, actions: torch.Tensor, noise: torch.Tensor,
               steps: int | None = None) -> torch.Tensor:
        """The next latent (B, C, h, w) from clipped Gaussian ``noise`` (B, C, h, w) in
        ``steps`` consistency jumps or Euler steps (default: the config's)."""
        if steps is None:
            steps = self.cfg.euler_steps if self.cfg.objective == "edm" else self.cfg.jumps
        y = self.objective.sample(self._net(context, context_sigma, actions), self.schedule, noise, steps)
        base = self._base(context)
        if base is None:
            return y
        if self.cfg.delta_deadband > 0:  # a cell's change under the deadband is no change
            y = y * (y.abs().amax(1, keepdim=True) > self.cfg.delta_deadband)
        return base + y
