"""The world model: a codec (stage 1) + the latent dynamics (stage 2) behind reset / step / rollout.

    wm = WorldModel.load("checkpoints/pusht-64")
    wm.reset(frames)                    # uint8 (B, H, W, 3), or (B, K, H, W, 3) with actions (B, K-1, A)
    frame = wm.step(actions)            # actions (B, A) in the data's units -> uint8 (B, H, W, 3)
    video = wm.rollout(frames, actions) # actions (B, N, A) -> uint8 (B, N, H, W, 3)

The core is functional, on an explicit :class:`StreamState` the model does not keep::

    state = wm.reset_state(frames)               # the same arguments as reset
    state, frame = wm.step_state(state, actions) # the same as step, returning the next state

``reset / step / rollout`` are a thin stateful wrapper around it (the state in ``wm.state``).
With ``latents=True``, reset and step take and give the model's units instead (no decoding)::

    state = wm.reset_state(wm.encode(frames)[:, None], latents=True)  # latents (B, K, C, h, w)
    state, z = wm.step_state(state, wm.normalize_actions(actions), latents=True)  # -> (B, C, h, w)

``wm.reencode = True`` feeds back the encoding of each decoded frame as the newest context
latent instead of the predicted one, in either mode.

A step predicts the next latent from a sliding window of the last K latents (older ones
are dropped), so a step costs the same at step 10 and at step 10,000, and memory stays
flat. The actions are the motion the robot executes: for a task with a speed limit,
the rate-limited targets (``iwsim.envs.tabletop.scene.limit_targets``), which the task-aware
callers (``iwsim/WorldModel-v0``, ``iwsim play``) compute from commands.

The codec is any :class:`~iwsim.world_model.codecs.base.Codec` (frames <-> latents of its
``latent_shape``). A model of several camera views (``cfg.cameras``, as its store names
them) encodes each view with the one codec and stacks the views' latents along the
channels, so one dynamics pass predicts the next state of every view together; its frames
are the views stacked along the channels, uint8 (..., H, W, 3 x views), view v in channels
3v..3v+2 (:func:`iwsim.data.views.stack_views`). The dynamics network is called through a
:class:`~iwsim.world_model.denoiser.Denoiser`. Objectives: a new latent comes from one
consistency jump from noise (ours), or, for the benchmark's baselines, Euler steps of an
EDM denoiser or one pass of a regressor (``cfg.objective``,
:mod:`iwsim.world_model.objectives`).

Randomness: the noise of batch item i comes from its own generator, seeded by
``seed + i`` (or ``seeds[i]``) at reset, so a batched rollout equals per-item rollouts.

Independent rollouts (e.g. the browser sessions of ``iwsim play``) can share forward
passes: ``StreamState.cat`` joins their states for one ``step_state`` and ``.split()``
separates them again, so each rollout keeps its own state between batched steps.
"""

from __future__ import annotations

import math
import os
from collections.abc import Sequence
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any, Literal, overload

import numpy as np
import torch
from torch import nn

from iwsim.core.checkpoint import (
    CheckpointError,
    build_within_memory,
    check_finite_output,
    load_json,
    load_model_dir,
    locate,
    resolve_checkpoint,
    save_model_dir,
)
from iwsim.core.config import from_dict, to_dict
from iwsim.core.errors import InputError
from iwsim.core.normalize import scale, unscale
from iwsim.core.precision import Precision, bf16_available, require_bf16
from iwsim.data.frames import to_model, to_uint8
from iwsim.diffusion.schedule import gaussian
from iwsim.envs.registry import task_from_config
from iwsim.envs.task import Task
from iwsim.world_model.codecs import WM_KIND, build_codec, codec_class, world_model_codec
from iwsim.world_model.codecs.base import DEFAULT_KIND, Codec, decode_views, encode_views
from iwsim.world_model.denoiser import ACTION_STILL, Denoiser
from iwsim.world_model.dynamics import Dynamics
from iwsim.world_model.novelty import Novelty
from iwsim.world_model.presets import OBJECTIVES, DynamicsStageConfig

KIND = WM_KIND


def inference_precision(device: torch.device) -> Precision:
    """The path of ``WorldModel.bf16`` on ``device``: bf16 autocast (the weights stay
    float32) where the hardware has it. The dynamics keeps the standard layout and the
    codec channels-last activations (as in float32): what measured fastest here
    (``bench/results/speed``)."""
    return Precision(bf16=bf16_available(device))


@dataclass
class StreamState:
    """The state of B rollouts between two steps: the window ``context`` (B, K, C, h, w)
    of standardised latents, newest last; the normalised action (B, A) that produced the
    newest one and whether it is known (B,) (not right after a reset from one frame,
    where the first action stands in for it); whether ``action`` is the setpoint the robot
    holds at the newest latent (``held`` (B,): known, or given at the reset though the
    network is shown the stand-in; what ``rest_threshold`` compares with); each item's
    noise generator; for a model that predicts the robot's own state, that state (B, S)
    at the newest latent, normalised (``robot``; None otherwise).

    Stepping returns a new state and leaves the old one's tensors as they were; the
    generators are shared and advance, so a state is stepped once."""

    context: torch.Tensor
    action: torch.Tensor
    known: torch.Tensor
    held: torch.Tensor
    generators: list[torch.Generator]
    robot: torch.Tensor | None = None

    @property
    def batch_size(self) -> int:
        return self.context.shape[0]

    @staticmethod
    def cat(states: Sequence[StreamState]) -> StreamState:
        """One state for the rollouts of ``states``."""
        if not states:
            raise InputError("StreamState.cat needs at least one state.")
        robots = [s.robot for s in states if s.robot is not None]
        if robots and len(robots) != len(states):
            raise InputError("StreamState.cat: the states come from models with and without the robot's state.")
        return StreamState(torch.cat([s.context for s in states]), torch.cat([s.action for s in states]),
                           torch.cat([s.known for s in states]), torch.cat([s.held for s in states]),
                           [g for s in states for g in s.generators], torch.cat(robots) if robots else None)

    def previous(self, actions: torch.Tensor) -> torch.Tensor:
        """The action (B, A) that produced the newest context latent: the known one, else
        (right after a reset from one frame) ``actions``, the first action, stands in."""
        return torch.where(self.known[:, None], self.action, actions)

    def split(self) -> list[StreamState]:
        """One state per rollout (views, no copies)."""
        return [StreamState(self.context[i:i + 1], self.action[i:i + 1], self.known[i:i + 1], self.held[i:i + 1],
                            [self.generators[i]], None if self.robot is None else self.robot[i:i + 1])
                for i in range(self.batch_size)]


class WorldModel(nn.Module):
    """Codec and latent dynamics, with action and latent normalisation.

    The dynamics works on standardised latents ``(z - latent_mean) / latent_scale``: the
    per-element mean over the training frames and one scale, the root-mean-square of the
    frame-to-frame variation. Scene latents barely change from frame to frame (a static
    background, small moving objects), and without this the context noise of stage 2
    (levels up to 100, noise std up to 0.14) would drown the differences that matter.

    A model whose dynamics takes the robot's own state (``cfg.dynamics.state_dim`` > 0)
    min-max normalises it over ``state_low .. state_high`` and predicts it each step
    (:meth:`robot_state` reads it from a state in the data's units).
    """

    action_low: torch.Tensor  # (A,) buffers
    action_high: torch.Tensor
    state_low: torch.Tensor  # (S,) buffers (S = 0 without the robot's state)
    state_high: torch.Tensor
    latent_mean: torch.Tensor  # (C, h, w) or (C, 1, 1)

    def __init__(self, codec: Codec, dynamics: Dynamics, cfg: DynamicsStageConfig,
                 action_low: Sequence[float] | torch.Tensor, action_high: Sequence[float] | torch.Tensor,
                 latent_mean: torch.Tensor | None = None, latent_scale: float = 1.0,
                 state_low: Sequence[float] | torch.Tensor = (), state_high: Sequence[float] | torch.Tensor = ()
                 ) -> None:
        super().__init__()
        if cfg.objective not in OBJECTIVES:
            raise InputError(f"unknown objective {cfg.objective!r}; expected one of {', '.join(OBJECTIVES)}.")
        self.views = len(cfg.cameras)
        c, h, w = codec.latent_shape
        if (c * self.views, h, w) != self.latent_shape_of(cfg):
            views = f" x {self.views} views" if self.views > 1 else ""
            raise InputError(f"the codec's latents are {tuple(codec.latent_shape)}{views} but the dynamics takes "
                             f"{self.latent_shape_of(cfg)}.")
        self.codec, self.dynamics, self.cfg = codec, dynamics, cfg
        codec.to(memory_format=torch.channels_last)  # see decode_latents
        self.denoiser = Denoiser(dynamics, cfg)
        low = torch.as_tensor(action_low, dtype=torch.float32)
        high = torch.as_tensor(action_high, dtype=torch.float32)
        if low.shape != (cfg.dynamics.action_dim,) or high.shape != low.shape or not bool((high > low).all()):
            raise InputError(f"action bounds must be two vectors of {cfg.dynamics.action_dim} values with "
                             f"high > low, got {low.tolist()} and {high.tolist()}.")
        self.register_buffer("action_low", low)
        self.register_buffer("action_high", high)
        slow = torch.as_tensor(state_low, dtype=torch.float32)
        shigh = torch.as_tensor(state_high, dtype=torch.float32)
        sdim = cfg.dynamics.state_dim
        if slow.shape != (sdim,) or shigh.shape != slow.shape or not bool((shigh > slow).all()):
            raise InputError(f"state bounds must be two vectors of {sdim} values (the dynamics' state_dim) with "
                             f"high > low, got {slow.tolist()} and {shigh.tolist()}.")
        self.register_buffer("state_low", slow)
        self.register_buffer("state_high", shigh)
        c = cfg.dynamics.latent_channels
        mean = torch.zeros(c, 1, 1) if latent_mean is None else torch.as_tensor(latent_mean, dtype=torch.float32)
        if mean.ndim != 3 or mean.shape[0] != c or not latent_scale > 0:
            raise InputError(f"latent mean must be ({c}, h, w) or ({c}, 1, 1) and the scale positive, got "
                             f"{tuple(mean.shape)} and {latent_scale}.")
        self.register_buffer("latent_mean", mean)
        self.latent_scale = float(latent_scale)
        # Inference knobs, from the config and settable: consistency jumps (or Euler steps
        # of the "edm" objective) per new frame and the context-noise std the context is
        # labelled with (standardised latent units).
        self.jumps, self.euler_steps, self.context_label = cfg.jumps, cfg.euler_steps, cfg.context_label
        self.reencode = False
        # float32 unless bf16 is asked for (the config's inference_bf16, or the bf16 setting)
        # and the hardware has it (a checkpoint that asks for it runs in float32 elsewhere)
        self._precision = inference_precision(self.action_low.device) if cfg.inference_bf16 else Precision()
        # The trust signal (iwsim.world_model.novelty): the Gaussian of the training data's
        # step inputs, when the checkpoint carries one (iwsim export-model --novelty-data).
        self.novelty: Novelty | None = None
        self._state: StreamState | None = None
        # The robot task (iwsim.envs.task.Task) the checkpoint records, set by load; None
        # for a model built in code (its callers then take iwsim.envs.registry.task_of's default).
        self.task: Task | None = None
        self.name = "the world model"  # what errors call it (load: "world model PATH")

    @property
    def bf16(self) -> bool:
        """Whether inference runs under bf16 autocast (:func:`inference_precision`): about
        twice the frames per second of a batch of 64 on a CPU with AMX, no faster for one
        stream, frames within a few grey levels of float32's (``bench/results/speed``). Off
        unless the checkpoint asks for it (``iwsim export-model --bf16``); setting it on is
        refused on a device without bf16 instructions."""
        return self._precision.bf16

    @bf16.setter
    def bf16(self, value: bool) -> None:
        if value:
            require_bf16(self.device, "WorldModel.bf16")
        self._precision = inference_precision(self.device) if value else Precision()

    @property
    def context_label(self) -> float:
        """The context-noise std (standardised latent units) the context is labelled with."""
        return self._context_label

    @context_label.setter
    def context_label(self, value: float) -> None:
        if not (isinstance(value, int | float) and np.isfinite(value) and value >= 0):
            raise InputError(f"context_label must be a finite std >= 0, got {value!r}.")
        self._context_label = float(value)

    # -- properties -------------------------------------------------------------------------
    @staticmethod
    def latent_shape_of(cfg: DynamicsStageConfig) -> tuple[int, int, int]:
        d = cfg.dynamics
        return (d.latent_channels, d.latent_size, d.latent_size)

    @property
    def image_size(self) -> int:
        return self.codec.image_size

    @property
    def latent_shape(self) -> tuple[int, int, int]:
        """(C, h, w) of one frame's latent (its views' latents stacked along the channels)."""
        c, h, w = self.codec.latent_shape  # three, as __init__ checked
        return (c * self.views, h, w)

    @property
    def cameras(self) -> tuple[str, ...]:
        """The views of a frame, in order: a frame is (H, W, 3 x views), view v in channels
        3v..3v+2 (:func:`iwsim.data.views.unstack_views`)."""
        return tuple(self.cfg.cameras)

    @property
    def action_dim(self) -> int:
        return self.cfg.dynamics.action_dim

    @property
    def state_dim(self) -> int:
        """Size of the robot's own state the model predicts (0: none)."""
        return self.cfg.dynamics.state_dim

    @property
    def device(self) -> torch.device:
        return self.action_low.device

    @property
    def batch_size(self) -> int:
        """The batch of the current rollout (0 before ``reset``)."""
        return 0 if self._state is None else self._state.batch_size

    @property
    def state(self) -> StreamState:
        """The rollouts' state: take it after ``reset`` or ``step``, set it to continue them."""
        if self._state is None:
            raise RuntimeError("call reset() before step().")
        return self._state

    @state.setter
    def state(self, value: StreamState) -> None:
        self._state = value

    # -- frames and actions -----------------------------------------------------------------
    def check_frames(self, frames: np.ndarray | torch.Tensor, ndim: int) -> torch.Tensor:
        """uint8 frames of rank ``ndim`` ending in (H, W, 3) at this model's size (3 x views
        channels for a model of several views), as a tensor."""
        x = torch.as_tensor(frames)
        s, c = self.image_size, 3 * self.views
        if x.dtype != torch.uint8:
            raise InputError(f"frames must be uint8, got {x.dtype}.")
        if x.ndim != ndim or tuple(x.shape[-3:]) != (s, s, c):
            want = f"(B, H, W, {c})" if ndim == 4 else f"(B, T, H, W, {c})"
            views = f" ({self.views} views stacked along the channels)" if self.views > 1 else ""
            raise InputError(f"expected frames {want} with H = W = {s}{views}, got shape {tuple(x.shape)}.")
        return x

    def normalize_actions(self, actions: np.ndarray | torch.Tensor, batch: int | None = None) -> torch.Tensor:
        """Actions (..., A) in the data's units -> [-1, 1] (clipped, as the task clips its
        targets to the workspace). Non-finite values and wrong shapes are a ValueError."""
        a = torch.as_tensor(actions, dtype=torch.float32, device=self.device)
        if a.ndim < 1 or a.shape[-1] != self.action_dim or (batch is not None and a.shape[0] != batch):
            lead = "B" if batch is None else str(batch)
            raise InputError(f"expected actions of shape ({lead}, ..., {self.action_dim}), got {tuple(a.shape)}.")
        bad = ~torch.isfinite(a)
        if bad.any():
            raise InputError(f"actions must be finite, got {a[bad][0].item()} at index "
                             f"{tuple(i.item() for i in bad.nonzero()[0])}.")
        return scale(a, self.action_low, self.action_high).clamp(-1, 1)

    @torch.inference_mode()
    def encode(self, frames: np.ndarray | torch.Tensor) -> torch.Tensor:
        """uint8 frames (B, H, W, 3 x views) -> latents (B, *latent_shape)."""
        x = self.check_frames(frames, 4)
        with self._precision.autocast(self.device):
            z = encode_views(self.codec, to_model(x, self.views).to(self.device), self.views).float()
        check_finite_output(z, self.name, "its encoder's latents")
        return z

    @torch.inference_mode()
    def decode(self, latents: np.ndarray | torch.Tensor, seed: int = 0) -> np.ndarray:
        """Latents (B, C, h, w) (as ``encode`` returns them, numpy or tensor) -> uint8 frames
        (B, H, W, 3 x views) (a stochastic codec's noise drawn from ``seed``)."""
        z = torch.as_tensor(latents, dtype=torch.float32, device=self.device)
        if z.ndim != 4 or tuple(z.shape[1:]) != self.latent_shape:
            raise InputError(f"expected latents (B, {', '.join(map(str, self.latent_shape))}), "
                             f"got shape {tuple(z.shape)}.")
        if not bool(torch.isfinite(z).all()):
            raise InputError("the latents to decode hold NaN or infinite values.")
        g = torch.Generator(self.device).manual_seed(seed)
        with self._precision.autocast(self.device):
            images = decode_views(self.codec, z, self.views, None, 1, g).float()
        check_finite_output(images, self.name, "its decoder's frames")
        return to_uint8(images)

    # -- the dynamics' latent units -----------------------------------------------------------
    def standardize(self, z: torch.Tensor) -> torch.Tensor:
        """Autoencoder latents (..., C, h, w) -> the dynamics' standardised latents."""
        return (z - self.latent_mean) / self.latent_scale

    def unstandardize(self, z: torch.Tensor) -> torch.Tensor:
        return z * self.latent_scale + self.latent_mean

    # -- functional core: explicit states ------------------------------------------------------
    @torch.inference_mode()
    def reset_state(self, context: np.ndarray | torch.Tensor, actions: np.ndarray | torch.Tensor | None = None,
                    seed: int | Sequence[int] = 0, held: np.ndarray | torch.Tensor | None = None, *,
                    latents: bool = False, state: np.ndarray | torch.Tensor | None = None) -> StreamState:
        """The state of B rollouts from one context frame each, uint8 (B, H, W, 3), or from
        K frames (B, K, H, W, 3) with the K - 1 actions (B, K-1, A) taken between them, in
        the data's units; ``held``: the setpoints (B, A) the robot holds at the newest
        frame, when the caller knows them (a still robot then keeps a still scene from the
        first step). Item i's noise comes from a generator seeded ``seed + i`` (or ``seed[i]``).
        ``state``: the robot's own state (B, S) at the newest frame, for a model that
        predicts it (ignored otherwise); without it, where the state has the action's size
        (the tabletop tasks' pushers), the held setpoints (or the newest action) stand in,
        else the middle of the state's range.

        ``latents=True``: everything in the model's units: context latents (B, K, C, h, w)
        as ``encode`` gives them, ``actions``, ``held`` and ``state`` normalised
        (``normalize_actions``, ``normalize_state``)."""
        if latents:
            z = torch.as_tensor(context, dtype=torch.float32, device=self.device)
            if z.ndim != 5 or tuple(z.shape[2:]) != self.latent_shape:
                raise InputError(f"expected context latents (B, K, {', '.join(map(str, self.latent_shape))}), "
                                 f"got shape {tuple(z.shape)}.")
            a, h, r = (None if v is None else torch.as_tensor(v, dtype=torch.float32, device=self.device)
                       for v in (actions, held, state))
        else:
            x = torch.as_tensor(context)
            x = self.check_frames(x[:, None] if x.ndim == 4 else x, 5)
            b, k = x.shape[:2]
            a = self.normalize_actions(actions, b) if k > 1 and actions is not None else None
            h = None if held is None else self.normalize_actions(held, b)
            r = None if state is None or not self.state_dim else self.normalize_state(state, b)
            z = self.encode(x.flatten(0, 1)).unflatten(0, (b, k))
        return self._reset(z, a, seed, h, r)

    @overload
    def step_state(self, state: StreamState, actions: np.ndarray | torch.Tensor, *,
                   latents: Literal[False] = False) -> tuple[StreamState, np.ndarray]: ...

    @overload
    def step_state(self, state: StreamState, actions: np.ndarray | torch.Tensor, *,
                   latents: Literal[True]) -> tuple[StreamState, torch.Tensor]: ...

    @overload
    def step_state(self, state: StreamState, actions: np.ndarray | torch.Tensor, *,
                   latents: bool) -> tuple[StreamState, np.ndarray | torch.Tensor]: ...

    @torch.inference_mode()
    def step_state(self, state: StreamState, actions: np.ndarray | torch.Tensor, *,
                   latents: bool = False) -> tuple[StreamState, np.ndarray | torch.Tensor]:
        """Actions (B, A) in the data's units -> the next state and frames, uint8 (B, H, W, 3).

        ``latents=True``: normalised actions (B, A) -> the next state and the predicted
        latents (B, C, h, w), as ``encode`` gives them; nothing is decoded unless ``reencode``
        (which makes the state's newest latent the encoding of their decoded frame)."""
        if latents:
            state, z, _ = self._step(state, torch.as_tensor(actions, dtype=torch.float32, device=self.device))
            return state, z
        state, _, images = self._step(state, self.normalize_actions(actions, state.batch_size), decode=True)
        assert images is not None  # decode=True
        return state, to_uint8(images)

    def _reset(self, latents: torch.Tensor, actions: torch.Tensor | None, seed: int | Sequence[int],
               held: torch.Tensor | None, robot: torch.Tensor | None = None) -> StreamState:
        """The state from context latents (B, K0, C, h, w) (as ``encode`` gives them), the
        normalised actions (B, K0-1, A) between them, held setpoints (B, A) and the robot's
        normalised state (B, S) (see :meth:`reset_state` for its stand-ins). The window
        keeps the last K; fewer are padded by repeating the first, as in training at an
        episode's start."""
        b, k0 = latents.shape[:2]
        z = self.standardize(latents)
        if k0 > 1:
            if actions is None:
                raise InputError(f"{k0} context frames need the {k0 - 1} actions (B, {k0 - 1}, A) between them.")
            if tuple(actions.shape) != (b, k0 - 1, self.action_dim):
                raise InputError(f"expected actions ({b}, {k0 - 1}, {self.action_dim}), got {tuple(actions.shape)}.")
        k = self.cfg.dynamics.context
        if k0 < k:
            z = torch.cat([z[:, :1].expand(b, k - k0, *z.shape[2:]), z], 1)
        seeds = [seed + i for i in range(b)] if isinstance(seed, int) else list(seed)
        if len(seeds) != b:
            raise InputError(f"got {len(seeds)} seeds for a batch of {b}.")
        if held is not None and tuple(held.shape) != (b, self.action_dim):
            raise InputError(f"expected held setpoints ({b}, {self.action_dim}), got {tuple(held.shape)}.")
        if k0 > 1:
            assert actions is not None  # checked above
            action = actions[:, -1]
        else:
            action = held if held is not None else torch.zeros(b, self.action_dim)
        known = torch.full((b,), k0 > 1, device=self.device)
        if self.state_dim:
            robot = self._robot_at_reset(robot, action if k0 > 1 or held is not None else None, b)
        else:
            robot = None
        return StreamState(z[:, -k:].contiguous(), action.to(self.device), known, known | (held is not None),
                           [torch.Generator(self.device).manual_seed(int(s)) for s in seeds], robot)

    def _robot_at_reset(self, robot: torch.Tensor | None, setpoint: torch.Tensor | None, b: int) -> torch.Tensor:
        """The normalised state (B, S) a rollout starts from: ``robot`` if given, else the
        setpoint (B, A) in the state's units where they have one size, else the middle."""
        if robot is not None:
            if tuple(robot.shape) != (b, self.state_dim):
                raise InputError(f"expected the robot's state ({b}, {self.state_dim}), got {tuple(robot.shape)}.")
            return robot.to(self.device)
        if setpoint is not None and self.state_dim == self.action_dim:
            data = unscale(setpoint.to(self.device), self.action_low, self.action_high)
            return scale(data, self.state_low, self.state_high)
        return torch.zeros(b, self.state_dim, device=self.device)

    def normalize_state(self, state: np.ndarray | torch.Tensor, batch: int | None = None) -> torch.Tensor:
        """The robot's state (B, S) in the data's units -> the model's units (not clipped)."""
        r = torch.as_tensor(state, dtype=torch.float32, device=self.device)
        if r.ndim != 2 or r.shape[-1] != self.state_dim or (batch is not None and r.shape[0] != batch):
            raise InputError(f"expected the robot's state ({batch or 'B'}, {self.state_dim}), got {tuple(r.shape)}.")
        if not bool(torch.isfinite(r).all()):
            raise InputError("the robot's state must be finite.")
        return scale(r, self.state_low, self.state_high)

    def robot_state(self, state: StreamState | None = None) -> np.ndarray | None:
        """The robot's own state (B, S) in the data's units that the model predicts at the
        newest frame of ``state`` (default: the current rollouts'); None for a model that
        does not predict it."""
        state = self.state if state is None else state
        if state.robot is None:
            return None
        return unscale(state.robot, self.state_low, self.state_high).cpu().numpy()

    def _step(self, state: StreamState, actions: torch.Tensor,
              decode: bool = False) -> tuple[StreamState, torch.Tensor, torch.Tensor | None]:
        """The one step: normalised actions (B, A) -> the next state, the next latents
        (B, C, h, w) as ``encode`` gives them and, with ``decode`` or ``reencode``, their
        images (B, 3, H, W) in [-1, 1] (else None). With ``reencode``, the newest context
        latent becomes the encoding of the decoded frame (the decoder renders a clean frame
        and the encoder projects it back onto the data) instead of the predicted latent."""
        b = state.batch_size
        if actions.shape != (b, self.action_dim):
            raise InputError(f"expected actions of shape ({b}, {self.action_dim}), got {tuple(actions.shape)}.")
        prev = state.previous(actions)
        noise = self._noise(state.generators, tuple(state.context.shape[2:]))
        still = state.held & ((actions - state.action).abs().amax(1) <= ACTION_STILL)
        acts = torch.stack([prev, actions], 1)
        new = self._predict(state.context, acts, noise, still, state.robot)
        check_finite_output(new, self.name, "its dynamics' next latent")
        robot = None
        if state.robot is not None:
            with self._precision.autocast(self.device):
                robot = self.dynamics.predict_state(new, state.context[:, -1], acts, state.robot).float()
            check_finite_output(robot, self.name, "its dynamics' robot state")
        z = self.unstandardize(new)
        images = None
        if decode or self.reencode:  # the decoder draws after the dynamics, from the same generators
            images = self.decode_latents(z, state.generators)
            if self.reencode:
                new = self.standardize(encode_views(self.codec, images.clamp(-1, 1), self.views))
        done = torch.ones_like(state.known)
        return (StreamState(torch.cat([state.context[:, 1:], new[:, None]], 1), actions, done, done, state.generators,
                            robot), z, images)

    def _noise(self, generators: Sequence[torch.Generator], shape: tuple[int, ...]) -> torch.Tensor:
        """Clipped Gaussian noise (B, *shape), item i from generator i."""
        return torch.cat([gaussian((1, *shape), g, self.device) for g in generators])

    def _predict(self, context: torch.Tensor, actions: torch.Tensor, noise: torch.Tensor,
                 still: torch.Tensor | None = None, robot: torch.Tensor | None = None) -> torch.Tensor:
        """The next standardised latent (B, C, h, w) from the window (B, K, C, h, w), the
        previous and current normalised actions (B, 2, A) and the noise (B, C, h, w): what
        the objective generates, plus the newest context latent when it generates the
        change (``predict_delta``). ``still`` (B,): whether the setpoint holds still
        (:meth:`Denoiser.sample`; default: the two actions are the same); ``robot`` (B, S):
        the robot's normalised state, for a model that takes it."""
        sigma = torch.full((context.shape[0],), self.context_label, device=context.device)
        with self._precision.autocast(self.device):
            new = self.denoiser.sample(context, sigma, actions, noise, self.jumps, self.euler_steps, still, robot)
        return new.float()

    @torch.inference_mode()
    def novelty_of(self, state: StreamState, actions: np.ndarray | torch.Tensor) -> np.ndarray | None:
        """How unlike the training data the step that ``actions`` (B, A), in the data's
        units, takes from ``state`` is (:mod:`iwsim.world_model.novelty`): (B,), or None
        for a model without novelty statistics."""
        if self.novelty is None:
            return None
        a = self.normalize_actions(actions, state.batch_size)
        return self.novelty(state.context[:, -1], state.previous(a), a).cpu().numpy()

    @torch.inference_mode()
    def decode_latents(self, z: torch.Tensor, generators: Sequence[torch.Generator] | None = None) -> torch.Tensor:
        """Latents (B, ..., C, h, w) -> images (B, ..., 3 x views, H, W) in [-1, 1], item
        i's noise (for a stochastic codec) from ``generators[i]`` (default: the current
        rollouts' generators)."""
        lead = tuple(z.shape[1:-3])
        size = self.image_size
        shape = (3 * self.views, size, size)
        noise = None
        if self.codec.stochastic:
            gens = self.state.generators if generators is None else generators
            noise = self._noise(gens, (*lead, *shape)).flatten(0, len(lead))
            noise = noise.contiguous(memory_format=torch.channels_last)
        # channels-last activations: the decoder's convolutions run faster on CPU (bench/speed.py)
        with self._precision.autocast(self.device):
            images = decode_views(self.codec, z.flatten(0, len(lead)).contiguous(memory_format=torch.channels_last),
                                  self.views, noise)
        check_finite_output(images, self.name, "its decoder's frames")
        return images.float().contiguous().view(*z.shape[:-3], *shape)

    def rollout(self, context_frames: np.ndarray | torch.Tensor, actions: np.ndarray | torch.Tensor,
                context_actions: np.ndarray | torch.Tensor | None = None, seed: int | Sequence[int] = 0,
                progress: bool = False) -> np.ndarray:
        """Open-loop rollout: context frames (B, [K,] H, W, 3), actions (B, N, A) ->
        predicted frames uint8 (B, N, H, W, 3)."""
        from tqdm import tqdm

        a = self.normalize_actions(actions)
        if a.ndim != 3:
            raise InputError(f"expected actions (B, N, {self.action_dim}), got {tuple(a.shape)}.")
        state = self._state = self.reset_state(context_frames, context_actions, seed)
        if a.shape[0] != state.batch_size:
            raise InputError(f"{state.batch_size} context frames but actions for {a.shape[0]} rollouts.")
        out = []
        with torch.inference_mode():
            for i in tqdm(range(a.shape[1]), desc="rollout", disable=not progress):
                state, _, images = self._step(state, a[:, i], decode=True)
                self._state = state
                assert images is not None  # decode=True
                out.append(to_uint8(images))
        return np.stack(out, 1) if out else np.zeros((state.batch_size, 0, self.image_size, self.image_size, 3),
                                                     np.uint8)

    # -- the stateful wrapper: the rollouts' state kept in ``self.state`` ----------------------
    def reset(self, context: np.ndarray | torch.Tensor, actions: np.ndarray | torch.Tensor | None = None,
              seed: int | Sequence[int] = 0, held: np.ndarray | torch.Tensor | None = None, *,
              latents: bool = False, state: np.ndarray | torch.Tensor | None = None) -> None:
        """Start B rollouts from one context frame each, uint8 (B, H, W, 3), or from K
        frames (B, K, H, W, 3) with the K - 1 actions (B, K-1, A) taken between them
        (``held``, ``latents`` and ``state``: see :meth:`reset_state`)."""
        self._state = self.reset_state(context, actions, seed, held, latents=latents, state=state)

    @overload
    def step(self, actions: np.ndarray | torch.Tensor, *, latents: Literal[False] = False) -> np.ndarray: ...

    @overload
    def step(self, actions: np.ndarray | torch.Tensor, *, latents: Literal[True]) -> torch.Tensor: ...

    @overload
    def step(self, actions: np.ndarray | torch.Tensor, *, latents: bool) -> np.ndarray | torch.Tensor: ...

    def step(self, actions: np.ndarray | torch.Tensor, *, latents: bool = False) -> np.ndarray | torch.Tensor:
        """Actions (B, A) in the data's units -> the next frames, uint8 (B, H, W, 3)
        (``latents``: see :meth:`step_state`)."""
        self._state, out = self.step_state(self.state, actions, latents=latents)
        return out

    # -- checkpoints ----------------------------------------------------------------------------
    def export(self) -> dict[str, torch.Tensor]:
        """The tensors of a world-model ``model.safetensors``."""
        return {**{f"codec.{k}": v for k, v in self.codec.state_dict().items()},
                **{f"dynamics.{k}": v for k, v in self.dynamics.state_dict().items()},
                **({} if self.novelty is None else {f"novelty.{k}": v for k, v in self.novelty.state_dict().items()}),
                "latent_mean": self.latent_mean}

    def describe(self) -> dict:
        """The parts of ``config.json`` that ``load`` reads."""
        return {"kind": KIND, "codec": {"kind": self.codec.kind, "config": to_dict(self.codec.cfg)},
                "stage2": to_dict(self.cfg),
                "action_norm": {"low": self.action_low.tolist(), "high": self.action_high.tolist()},
                **({"state_norm": {"low": self.state_low.tolist(), "high": self.state_high.tolist()}}
                   if self.state_dim else {}),
                "latent_norm": {"scale": self.latent_scale},
                **({} if self.task is None else {"task": self.task.describe()})}

    def save(self, path: str | Path, extra: dict | None = None, force: bool = False) -> Path:
        """Write a self-contained checkpoint directory atomically; ``extra`` entries
        (provenance) are added to ``config.json``."""
        return save_model_dir(Path(path), self.export(), {**(extra or {}), **self.describe()}, force)

    @classmethod
    def load(cls, path: str | os.PathLike[str], device: str | torch.device = "cpu") -> WorldModel:
        """From a checkpoint directory (``model.safetensors`` + ``config.json``), e.g. one
        written by ``iwsim train dynamics`` or ``iwsim export-model``. Checkpoints from
        before the codec seam (an ``ae`` config and ``ae.*`` weights: the consistency
        autoencoder) load as they are."""
        path = locate(path)
        config, tensors = load_model_dir(path, KIND)
        prefix, codec_kind, codec_cfg = world_model_codec(config)
        for part, value in (("codec", codec_cfg), *((p, config.get(p)) for p in ("stage2", "action_norm",
                                                                                   "latent_norm"))):
            if value is None:
                raise CheckpointError(f"{path / 'config.json'} is missing the {part!r} part of the world model.")
        try:
            cfg = from_dict(DynamicsStageConfig, config["stage2"])
            from_dict(codec_class(codec_kind).config_class, codec_cfg)
        except (TypeError, ValueError, KeyError, AttributeError) as e:
            raise CheckpointError(f"{path / 'config.json'} does not describe a world model: {e}") from None
        codec = build_within_memory(lambda: build_codec(codec_kind, codec_cfg), f"the codec of {path}")
        parts = {}
        for part, name in ((prefix, "codec"), ("dynamics", "dynamics")):
            parts[name] = {k[len(part) + 1:]: v for k, v in tensors.items() if k.startswith(part + ".")}
            if not parts[name]:
                raise CheckpointError(f"{path / 'model.safetensors'} has no {name} weights ({part}.*).")
        if "latent_mean" not in tensors:
            raise CheckpointError(f"{path / 'model.safetensors'} has no latent normalisation (latent_mean).")
        dyn = build_within_memory(lambda: Dynamics(cfg.dynamics), f"the dynamics of {path}")
        try:
            codec.load_state_dict(parts["codec"])
            dyn.load_state_dict(parts["dynamics"])
        except RuntimeError as e:
            raise CheckpointError(f"{path / 'model.safetensors'} does not match its config: "
                                  f"{' '.join(str(e).split())[:200]}") from None
        norm, snorm = config["action_norm"], config.get("state_norm") or {"low": [], "high": []}
        wm = cls(codec, dyn, cfg, norm["low"], norm["high"], tensors["latent_mean"], config["latent_norm"]["scale"],
                 snorm["low"], snorm["high"])
        if "novelty.mean" in tensors:
            wm.novelty = Novelty(tensors["novelty.mean"].shape[0])
            wm.novelty.load_state_dict({k[len("novelty."):]: v for k, v in tensors.items() if k.startswith("novelty.")})
        wm.task = task_from_config(config, path / "config.json")
        wm.name = f"world model {path}"
        if wm.task.action_dim != wm.action_dim:
            raise CheckpointError(f"{path / 'config.json'}: its task {wm.task.name!r} takes {wm.task.action_dim}-D "
                                  f"actions but the model {wm.action_dim}-D ones.")
        return wm.to(device).eval()


def complete_run_config(config: dict[str, Any]) -> dict[str, Any]:
    """A stored world-model run's config (a codec run's, a dynamics or decoder fine-tune
    run's) with the codec and stage-2 fields added to iwsim since filled with their
    defaults, as loading reads them, so that a run started before a new field resumes. A
    config it cannot read is returned as it is (the comparison then says what differs)."""
    try:
        if isinstance(config.get("model"), dict):  # stage 1: {"codec": kind, "model": its config}
            cls = codec_class(config.get("codec", DEFAULT_KIND)).config_class
            return {**config, "model": to_dict(from_dict(cls, config["model"]))}
        done = dict(config)
        if isinstance(config.get("stage2"), dict):
            done["stage2"] = to_dict(from_dict(DynamicsStageConfig, config["stage2"]))
        _, kind, codec_cfg = world_model_codec(config)
        if isinstance(config.get("codec"), dict) and isinstance(codec_cfg, dict):
            done["codec"] = {**config["codec"], "config": to_dict(from_dict(codec_class(kind).config_class,
                                                                             codec_cfg))}
        return done
    except (InputError, TypeError, ValueError):
        return config


# Stage-2 settings that act only at inference: a checkpoint can carry other values than its run's.
INFERENCE_SETTINGS = ("rest_threshold", "delta_deadband", "inference_bf16")


def check_inference(settings: dict[str, float]) -> dict[str, float]:
    """``settings`` if each is an inference setting (:data:`INFERENCE_SETTINGS`): the
    thresholds finite and >= 0, inference_bf16 a bool; else InputError."""
    for k, v in settings.items():
        if k not in INFERENCE_SETTINGS:
            raise InputError(f"{k!r} is not an inference setting; expected one of {', '.join(INFERENCE_SETTINGS)}.")
        if k == "inference_bf16":
            if not isinstance(v, bool):
                raise InputError(f"inference_bf16 must be true or false, got {v!r}.")
        elif not (math.isfinite(v) and v >= 0):  # inf would freeze every frame (no change passes)
            raise InputError(f"{k} must be a finite number >= 0, got {v}.")
    return settings


def export_model(run: str | Path, out: str | Path, force: bool = False, decoder: str | Path | None = None,
                 novelty: Novelty | None = None, inference: dict[str, float] | None = None) -> Path:
    """A standalone world-model checkpoint (``model.safetensors`` + ``config.json``) from a
    run of ``train dynamics`` or ``train decoder-finetune`` (its last checkpoint) or from
    one of its checkpoints (``iwsim export-model``).

    With ``decoder`` (another world model whose codec has the same encoder weights, e.g. a
    ``train decoder-finetune`` run), the checkpoint takes that model's codec: its latents
    are the ones the dynamics was trained on, only their rendering differs. With ``novelty``
    (:func:`iwsim.world_model.dynamics_data.fit_store_novelty` of the training data) the
    checkpoint carries that trust signal instead of the run's. ``inference`` sets stage-2
    settings that act only at inference (:data:`INFERENCE_SETTINGS`, each >= 0)."""
    inference = check_inference(inference or {})
    src = resolve_checkpoint(run)
    config = load_json(src / "config.json")
    provenance: dict[str, Any] = {k: config[k] for k in ("data", "ae_checkpoint", "finetuned_from") if k in config}
    if "provenance" in config:  # a checkpoint exported before: its own record is kept
        provenance["exported_from"] = config["provenance"]
    wm = WorldModel.load(src)
    if decoder is not None:
        dec_src = resolve_checkpoint(decoder)
        codec = WorldModel.load(dec_src).codec
        theirs, mine = codec.encoder_parameters(), wm.codec.encoder_parameters()
        same = type(codec) is type(wm.codec) and len(theirs) == len(mine) and all(
            a.shape == b.shape and torch.equal(a, b) for a, b in zip(theirs, mine))
        if not same:
            raise InputError(f"{dec_src}'s codec encodes differently from {src}'s (other encoder weights); "
                             "its decoder renders other latents.")
        task, novelty = wm.task, wm.novelty
        wm = WorldModel(codec, wm.dynamics, wm.cfg, wm.action_low, wm.action_high, wm.latent_mean, wm.latent_scale,
                        wm.state_low, wm.state_high)
        wm.task, wm.novelty = task, novelty
        provenance["decoder"] = str(dec_src)
    if novelty is not None:
        wm.novelty = novelty
    if inference:
        provenance["inference"] = {k: [getattr(wm.cfg, k), v] for k, v in inference.items()}  # [the run's, now]
        changes: dict[str, Any] = dict(inference)
        wm.cfg = replace(wm.cfg, **changes)
    return wm.save(out, {"provenance": {"source": str(src), **provenance}}, force)
