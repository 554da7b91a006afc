"""The dynamics network behind one calling convention (like k-diffusion's ``Denoiser``).

Training and inference both call a :class:`Denoiser`, the one place that knows the noise
units (the context-noise std in standardised latent units, told to the network in level
units), the objective's loss and sampler (:mod:`iwsim.world_model.objectives`) and whether
the network generates the next latent or its change from the newest context latent
(``predict_delta``). It wraps the dynamics network once (``self.model``) in the
samplers' convention (:mod:`iwsim.diffusion`), the conditioning as ``extra_args``:

    err, estimate = denoiser.loss(target, context, context_sigma, actions, levels, eps)
    next_latent = denoiser.sample(context, context_sigma, actions, noise, jumps, euler_steps)

All latents are the dynamics' standardised latents; ``context`` (B, K, C, h, w), newest
last; ``actions`` (B, 2, A) normalised, the one that produced the newest context latent,
then the one that produces the next latent; ``context_sigma`` (B,) the std of the noise on
the context (training) or the std it is labelled with (inference); ``state`` (B, S) the
robot's normalised state at the newest context latent, for a network that takes it.
"""

from __future__ import annotations

import torch

from iwsim.diffusion.schedule import Schedule
from iwsim.world_model.dynamics import Dynamics
from iwsim.world_model.objectives import OBJECTIVES, ExtraArgs, Levels
from iwsim.world_model.presets import DynamicsStageConfig

LEVELS_PER_STD = 1000.0  # a context-noise std of 0.1 is told to the network as level 100
ACTION_STILL = 1e-6  # normalised actions this close are the same setpoint (rest_threshold)


class Denoiser:
    """A dynamics network with its objective; holds no weights of its own (the network is
    registered by its owner, the world model or the training module)."""

    def __init__(self, network: Dynamics, cfg: DynamicsStageConfig) -> None:
        self.network, self.cfg = network, cfg
        self.schedule = Schedule(cfg.schedule)
        self.objective = OBJECTIVES[cfg.objective]
        self.model = self.objective.model(self._net, self.schedule)

    def _net(self, x: torch.Tensor, t: torch.Tensor, s: torch.Tensor, *, context: torch.Tensor,
             context_level: torch.Tensor, actions: torch.Tensor, state: torch.Tensor | None = None) -> torch.Tensor:
        """The dynamics network as the objectives call it: ``net(x, t, s, **extra_args)``."""
        return self.network(x, context, t.float(), s.float(), context_level, actions, state)

    @staticmethod
    def _extra_args(context: torch.Tensor, context_sigma: torch.Tensor, actions: torch.Tensor,
                    state: torch.Tensor | None) -> ExtraArgs:
        out = {"context": context, "context_level": context_sigma * LEVELS_PER_STD, "actions": actions}
        return out if state is None else {**out, "state": state}

    def _base(self, context: torch.Tensor) -> torch.Tensor | None:
        return context[:, -1] if self.cfg.predict_delta else None

    def loss(self, target: torch.Tensor, context: torch.Tensor, context_sigma: torch.Tensor, actions: torch.Tensor,
             levels: Levels, eps: torch.Tensor, state: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor]:
        """The objective's per-element error (B, C, h, w) for the next latent ``target``
        and its one-pass estimate of that latent (what unrolled training feeds back)."""
        base = self._base(context)
        y0 = target if base is None else target - base
        extra_args = self._extra_args(context, context_sigma, actions, state)
        err, estimate = self.objective.loss(self.model, y0, levels, eps, extra_args)
        return err, estimate if base is None else base + estimate

    def sample(self, context: torch.Tensor, context_sigma: torch.Tensor, actions: torch.Tensor, noise: torch.Tensor,
               jumps: int | None = None, euler_steps: int | None = None,
               still: torch.Tensor | None = None, state: torch.Tensor | None = None) -> torch.Tensor:
        """The next latent (B, C, h, w) from clipped Gaussian ``noise`` (B, C, h, w) in
        ``jumps`` consistency jumps or ``euler_steps`` Euler steps, whichever the objective
        takes (default: the config's). ``still`` (B,) bool: whether the executed setpoint
        holds still (``rest_threshold``; default: the two actions are the same)."""
        knob = self.objective.steps_knob
        steps = {"jumps": jumps, "euler_steps": euler_steps}[knob]
        y = self.objective.sample(self.model, noise, getattr(self.cfg, knob) if steps is None else steps,
                                  self._extra_args(context, context_sigma, actions, state))
        base = self._base(context)
        if base is None:
            return y
        if self.cfg.delta_deadband > 0:  # a cell's change under the deadband is no change
            y = y * (y.abs().amax(1, keepdim=True) > self.cfg.delta_deadband)
        if self.cfg.rest_threshold > 0 and context.shape[1] > 1:  # a scene at rest stays at rest
            if still is None:
                still = (actions[:, 1] - actions[:, 0]).abs().amax(1) <= ACTION_STILL
            resting = (context[:, -1] - context[:, -2]).abs().flatten(1).amax(1) < self.cfg.rest_threshold
            y = y * ~(still & resting)[:, None, None, None]
        return base + y
