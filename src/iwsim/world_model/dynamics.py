"""Stage 2 network: the latent dynamics F over a sliding window of latents.

F predicts the next latent from the last K latents (the window, stacked as input
channels, newest last), the action that produces the next frame and the one before it,
and the noise levels of its input. It is a residual CNN at latent resolution with FiLM from
the level embedding and one spatial self-attention layer in the middle (the block moves as
one rigid object however far apart its cells are). With ``down`` = 1 its middle half runs at
half the latent's resolution with twice the channels, between a strided convolution and an
upsampling one whose output is added to what went in (a U-Net of one level, as the paper's
dynamics: a 16 x 16 latent's T spans ~6 cells, at 8 x 8 it is ~3, as in the coarse latent
whose T stays rigid); a quarter of the blocks run before it and a quarter after, at full
resolution. ``down`` = 0 keeps every block at latent resolution.

Actions enter as per-cell input features at latent resolution, for the current and the
previous action (measured here: FiLM from an action MLP was ignored by the trained model
at CPU budgets, while the same network given actions as spatial maps used them):

- generic: a learned linear map from any action vector to an (action_channels, h, w)
  grid, so any ``Box`` action (e.g. ALOHA joint targets) works;
- positional: where the task declares which action entries are (x, y) positions seen by
  a top-down orthographic camera (``point_index``), Gaussian blobs at those positions on
  the latent grid (the current and previous pusher targets). A position in image
  coordinates (x right, y up, in [-1, 1]) is ``normalised action * point_scale +
  point_offset``; the task's workspace and view give these numbers.

FiLM from the action MLP stays available (``action_film``) for comparison.

The robot's own state (``state_dim`` > 0: the store's ``data/state``, e.g. where T-push's
pushers actually are, which differs from their setpoints when contact holds them back)
enters like the actions, as a learned grid plus blobs at its positions where it holds the
same points as the actions (``state_point_scale``); and :meth:`Dynamics.predict_state`, a
small head, predicts the next state from the new latent, the newest context latent, the
actions and the current state, as a correction to the state the current setpoint asks for
where the state is what the actions set (``state_action_scale``), else to the last state.
A rollout feeds each predicted state back as the next step's input (see
:class:`~iwsim.world_model.WorldModel`).

No layer mixes batch items, so a batched rollout equals per-item rollouts.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import nn
from torch.nn import functional as F

from iwsim.core.errors import InputError
from iwsim.models.blocks import ResBlock, group_norm, sinusoidal, zero_init


@dataclass(frozen=True)
class DynamicsConfig:
    latent_channels: int = 4
    latent_size: int = 16  # h = w of a latent
    action_dim: int = 4
    context: int = 3  # K: latents in the window
    channels: int = 64
    blocks: int = 8
    heads: int = 4  # of the spatial attention in the middle (0: none)
    down: int = 0  # 1: the middle blocks at half resolution with 2x channels (a one-level U-Net); 0: none
    emb_dim: int = 128
    num_levels: int = 1000  # noise levels are embedded as t / T * 1000
    spatial_actions: bool = True  # the learned action grid
    action_channels: int = 8  # per action (current, previous)
    action_film: bool = False  # FiLM from an action MLP (the old pathway)
    positional_actions: bool = True  # blobs at the positions the task declares (filled in by training)
    point_index: tuple[tuple[int, int], ...] = ()  # action entries (x, y) that are image positions
    point_scale: tuple[float, ...] = ()  # per action entry: image coordinate = a * scale + offset
    point_offset: tuple[float, ...] = ()
    point_sigma: float = 0.75  # blob std in latent cells
    state_dim: int = 0  # the robot's own state, taken and predicted (0: none; filled in by training)
    state_channels: int = 8  # of the learned state grid
    state_point_scale: tuple[float, ...] = ()  # per state entry, as point_scale (empty: no state blobs)
    state_point_offset: tuple[float, ...] = ()
    state_head_channels: int = 32
    # Where the state is the quantity the actions set (the same size: T-push's pushers and
    # their setpoints), the map from a normalised action to the normalised state it sets,
    # per entry: state = action * scale + offset. The head then predicts the state's offset
    # from the current setpoint (contact holding a pusher back) instead of from the last
    # state. Empty: from the last state.
    state_action_scale: tuple[float, ...] = ()
    state_action_offset: tuple[float, ...] = ()


class SpatialAttention(nn.Module):
    """Self-attention among the positions of each frame."""

    def __init__(self, channels: int, heads: int) -> None:
        super().__init__()
        self.heads = heads
        self.norm = group_norm(channels)
        self.qkv = nn.Conv2d(channels, 3 * channels, 1)
        self.out = nn.Conv2d(channels, channels, 1)
        zero_init(self.out)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """x (N, c, h, w) -> like x."""
        n, c, h, w = x.shape
        q, k, v = self.qkv(self.norm(x)).view(n, 3, self.heads, c // self.heads, h * w).transpose(-1, -2).unbind(1)
        # softmax(q k^T / sqrt(d)) v written out: what F.scaled_dot_product_attention computes,
        # whose CPU flash kernel's backward is far slower on latent grids this small
        # (bench/results/speed).
        weights = torch.softmax((q * q.shape[-1] ** -0.5) @ k.transpose(-1, -2), dim=-1)
        o = weights @ v  # (n, heads, hw, d)
        return x + self.out(o.transpose(-1, -2).reshape(n, c, h, w))


class Dynamics(nn.Module):
    """F(x, context, levels, actions) -> the network output for the new latent (a v- or
    x-prediction, depending on the objective; see :mod:`iwsim.world_model.objectives`)."""

    point_scale: torch.Tensor  # (A,) buffers, with cfg.point_index
    point_offset: torch.Tensor
    state_point_scale: torch.Tensor  # (S,) buffers, with cfg.state_point_scale
    state_point_offset: torch.Tensor
    state_action_scale: torch.Tensor  # (S,) buffers, with cfg.state_action_scale
    state_action_offset: torch.Tensor

    def __init__(self, cfg: DynamicsConfig = DynamicsConfig()) -> None:
        super().__init__()
        self.cfg = cfg
        c, e, s = cfg.channels, cfg.emb_dim, cfg.latent_size
        if cfg.point_index and not (len(cfg.point_scale) == len(cfg.point_offset) == cfg.action_dim):
            raise InputError(f"point_scale and point_offset need {cfg.action_dim} values each (one per action "
                             f"entry), got {len(cfg.point_scale)} and {len(cfg.point_offset)}.")
        self.level_mlp = nn.Sequential(nn.Linear(3 * (e // 2), e), nn.SiLU(), nn.Linear(e, e))
        self.action_mlp = nn.Sequential(nn.Linear(2 * cfg.action_dim, e), nn.SiLU(), nn.Linear(e, e)) \
            if cfg.action_film else None
        self.action_grid = nn.Linear(cfg.action_dim, cfg.action_channels * s * s) if cfg.spatial_actions else None
        if cfg.point_index:
            self.register_buffer("point_scale", torch.tensor(cfg.point_scale, dtype=torch.float32), persistent=False)
            self.register_buffer("point_offset", torch.tensor(cfg.point_offset, dtype=torch.float32),
                                 persistent=False)
        if cfg.state_point_scale and not (cfg.point_index and len(cfg.state_point_scale) ==
                                          len(cfg.state_point_offset) == cfg.state_dim):
            raise InputError(f"state blobs need the action's point_index and {cfg.state_dim} values each in "
                             f"state_point_scale and state_point_offset, got {len(cfg.state_point_scale)} and "
                             f"{len(cfg.state_point_offset)}.")
        if cfg.state_action_scale:
            if not len(cfg.state_action_scale) == len(cfg.state_action_offset) == cfg.state_dim == cfg.action_dim:
                raise InputError(f"state_action_scale and state_action_offset need {cfg.state_dim} values each, one "
                                 "per state entry, and a state of the action's size.")
            self.register_buffer("state_action_scale", torch.tensor(cfg.state_action_scale, dtype=torch.float32),
                                 persistent=False)
            self.register_buffer("state_action_offset", torch.tensor(cfg.state_action_offset, dtype=torch.float32),
                                 persistent=False)
        if cfg.state_point_scale:
            self.register_buffer("state_point_scale", torch.tensor(cfg.state_point_scale, dtype=torch.float32),
                                 persistent=False)
            self.register_buffer("state_point_offset", torch.tensor(cfg.state_point_offset, dtype=torch.float32),
                                 persistent=False)
        cin = (1 + cfg.context) * cfg.latent_channels + 2 + 2 * len(cfg.point_index)
        cin += 2 * cfg.action_channels if cfg.spatial_actions else 0
        self.state_grid = nn.Linear(cfg.state_dim, cfg.state_channels * s * s) if cfg.state_dim else None
        state_in = self.state_features_channels()
        self.conv_in = nn.Conv2d(cin + state_in, c, 3, padding=1)
        if cfg.down not in (0, 1) or (cfg.down and s % 2):
            raise InputError(f"down takes 0 or 1 (1 needs an even latent size), got {cfg.down} with a {s} x {s} "
                             "latent.")
        outer = cfg.blocks // 4 if cfg.down else 0  # blocks at full resolution before and after the middle
        mid, half = c * 2 ** cfg.down, (cfg.blocks - 2 * outer) // 2
        self.blocks_in = nn.ModuleList(ResBlock(c, c, e) for _ in range(outer))
        self.down = nn.Conv2d(c, mid, 3, stride=2, padding=1) if cfg.down else None
        self.blocks_a = nn.ModuleList(ResBlock(mid, mid, e) for _ in range(half))
        self.attn = SpatialAttention(mid, cfg.heads) if cfg.heads else None
        self.blocks_b = nn.ModuleList(ResBlock(mid, mid, e) for _ in range(cfg.blocks - 2 * outer - half))
        self.up = nn.Conv2d(mid, c, 3, padding=1) if cfg.down else None
        self.blocks_out = nn.ModuleList(ResBlock(c, c, e) for _ in range(outer))
        self.norm_out = group_norm(c)
        self.conv_out = nn.Conv2d(c, cfg.latent_channels, 3, padding=1)
        zero_init(self.conv_out)
        self.state_head = StateHead(cfg, cin - cfg.context * cfg.latent_channels + cfg.latent_channels + state_in) \
            if cfg.state_dim else None

    def state_features_channels(self) -> int:
        cfg = self.cfg
        if not cfg.state_dim:
            return 0
        return cfg.state_channels + (len(cfg.point_index) if cfg.state_point_scale else 0)

    def state_features(self, state: torch.Tensor) -> list[torch.Tensor]:
        """Per-cell maps of the normalised state (B, S): the learned grid, and blobs at its
        positions when it holds the action's points."""
        if self.state_grid is None:
            return []
        b, s = state.shape[0], self.cfg.latent_size
        maps = [self.state_grid(state).view(b, -1, s, s)]
        if self.cfg.state_point_scale:
            pos = state[:, None] * self.state_point_scale + self.state_point_offset
            maps.append(blobs(pos, self.cfg.point_index, s, self.cfg.point_sigma).flatten(1, 2))
        return maps

    def predict_state(self, new: torch.Tensor, newest: torch.Tensor, actions: torch.Tensor,
                      state: torch.Tensor) -> torch.Tensor:
        """The normalised state (B, S) at the new latent ``new`` (B, C, h, w), from it, the
        newest context latent ``newest`` (B, C, h, w), the actions (B, 2, A) (as forward's)
        and the state (B, S) at the newest context latent: the state the current action sets
        (``state_action_scale``) or else the last state, plus the head's correction."""
        if self.state_head is None:
            raise InputError("this dynamics network has no state head (it was trained without the robot's state).")
        inp = [new, newest, coordinates(new), *self.action_features(actions), *self.state_features(state)]
        base = self.setpoint_state(actions) if self.cfg.state_action_scale else state
        return base + self.state_head(torch.cat(inp, 1))

    def setpoint_state(self, actions: torch.Tensor) -> torch.Tensor:
        """The normalised state (B, S) the current action of ``actions`` (B, 2, A) sets: where
        the robot stands once it has reached its setpoint (a network whose state holds the
        action's points, ``state_action_scale``)."""
        return actions[:, 1] * self.state_action_scale + self.state_action_offset

    def action_features(self, actions: torch.Tensor) -> list[torch.Tensor]:
        """Per-cell action maps from normalised actions (B, 2, A) (previous, current)."""
        b = actions.shape[0]
        s = self.cfg.latent_size
        maps = []
        if self.action_grid is not None:
            maps.append(self.action_grid(actions).view(b, -1, s, s))
        if self.cfg.point_index:
            maps.append(blobs(actions * self.point_scale + self.point_offset, self.cfg.point_index, s,
                              self.cfg.point_sigma).flatten(1, 2))
        return maps

    def forward(self, x: torch.Tensor, context: torch.Tensor, t: torch.Tensor, s: torch.Tensor,
                context_level: torch.Tensor, actions: torch.Tensor, state: torch.Tensor | None = None
                ) -> torch.Tensor:
        """x (B, C, h, w) the new latent's noisy input; context (B, K, C, h, w) the window,
        newest last; t, s (B,) the input level and the level to jump to (embedding units:
        0 .. 1000); context_level (B,) what the context is labelled with (same units);
        actions (B, 2, A) normalised: the one that produced the newest context latent, then
        the one that produces the new latent; state (B, S) the normalised state at the newest
        context latent (a network with ``state_dim``). Returns (B, C, h, w)."""
        assert x.ndim == 4 and context.ndim == 5, f"got x {tuple(x.shape)}, context {tuple(context.shape)}"
        b = x.shape[0]
        e = self.cfg.emb_dim // 2
        scale = 1000.0 / self.cfg.num_levels
        emb = self.level_mlp(torch.cat([sinusoidal(t * scale, e), sinusoidal(s * scale, e),
                                        sinusoidal(context_level * scale, e)], 1))
        if self.action_mlp is not None:
            emb = emb + self.action_mlp(actions.flatten(1))
        inp = [x, context.flatten(1, 2), coordinates(x), *self.action_features(actions)]
        if self.state_grid is not None:
            if state is None:
                raise InputError("this dynamics network takes the robot's state (B, S); none was given.")
            inp += self.state_features(state)
        h = self.conv_in(torch.cat(inp, 1))
        for block in self.blocks_in:
            h = block(h, emb)
        skip = h
        if self.down is not None:
            h = self.down(h)
        for block in self.blocks_a:
            h = block(h, emb)
        if self.attn is not None:
            h = self.attn(h)
        for block in self.blocks_b:
            h = block(h, emb)
        if self.up is not None:
            h = skip + self.up(F.interpolate(h, scale_factor=2, mode="nearest"))
        for block in self.blocks_out:
            h = block(h, emb)
        return self.conv_out(F.silu(self.norm_out(h))).view(b, *x.shape[1:])


class StateHead(nn.Module):
    """Inputs (B, cin, h, w) -> the correction (B, S) of the normalised state: two
    convolutions at latent resolution and a linear read-out of every cell (where a pusher
    is matters); zero at initialisation, so the state starts at the setpoint (or held)."""

    def __init__(self, cfg: DynamicsConfig, cin: int) -> None:
        super().__init__()
        c, s = cfg.state_head_channels, cfg.latent_size
        out = nn.Linear(c * s * s, cfg.state_dim)
        nn.init.zeros_(out.weight)
        nn.init.zeros_(out.bias)
        self.net = nn.Sequential(nn.Conv2d(cin, c, 3, padding=1), nn.SiLU(), nn.Conv2d(c, c, 3, padding=1),
                                 nn.SiLU(), nn.Flatten(), out)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.net(x)


def widen_window(state: dict[str, torch.Tensor], cfg: DynamicsConfig, context: int) -> dict[str, torch.Tensor]:
    """The weights ``state`` of a :class:`Dynamics` with ``cfg``, for one whose window holds
    ``context`` >= cfg.context latents and that computes the same function: the older
    latents' input weights are zero, so fine-tuning starts from the model unchanged."""
    if context < cfg.context:
        raise InputError(f"a window can only be widened: the model holds {cfg.context} latents, asked for {context}.")
    w, c = state["conv_in.weight"], cfg.latent_channels
    older = w.new_zeros(w.shape[0], (context - cfg.context) * c, *w.shape[2:])
    # Input channels: the new latent's c, then the window's, oldest first (see forward).
    return {**state, "conv_in.weight": torch.cat([w[:, :c], older, w[:, c:]], 1)}


def add_state(state: dict[str, torch.Tensor], cfg: DynamicsConfig, new: Dynamics) -> dict[str, torch.Tensor]:
    """The weights ``state`` of a :class:`Dynamics` with ``cfg`` (no robot state), for
    ``new``, the same network with a state: the state's input weights are zero, so the
    latent prediction starts unchanged, and the state head is ``new``'s own (it starts by
    holding the state still)."""
    if cfg.state_dim:
        raise InputError("the network takes the robot's state already.")
    w = state["conv_in.weight"]
    extra = w.new_zeros(w.shape[0], new.state_features_channels(), *w.shape[2:])
    own = {k: v for k, v in new.state_dict().items() if k.startswith(("state_grid.", "state_head."))}
    return {**state, **own, "conv_in.weight": torch.cat([w, extra], 1)}


def blobs(positions: torch.Tensor, index: tuple[tuple[int, int], ...], size: int, sigma: float) -> torch.Tensor:
    """Gaussian blobs (B, T, P, size, size), peak 1, at P image positions taken from
    ``positions`` (B, T, A) (entries ``index``: (x, y) in [-1, 1], x right, y up), with
    std ``sigma`` in cells."""
    ix = torch.tensor([i for i, _ in index], device=positions.device)
    iy = torch.tensor([j for _, j in index], device=positions.device)
    px = (positions[..., ix] + 1) / 2 * size  # (B, T, P) in cells, from the left edge
    py = (1 - positions[..., iy]) / 2 * size  # from the top row
    grid = torch.arange(size, device=positions.device, dtype=positions.dtype) + 0.5
    gx = torch.exp(-((grid - px[..., None]) ** 2) / (2 * sigma**2))  # (B, T, P, size)
    gy = torch.exp(-((grid - py[..., None]) ** 2) / (2 * sigma**2))
    return gy[..., :, None] * gx[..., None, :]


def coordinates(x: torch.Tensor) -> torch.Tensor:
    """(N, 2, h, w) maps of the pixel-centre x (left to right) and y (bottom to top) in (-1, 1)."""
    n, _, h, w = x.shape
    xs = (torch.arange(w, device=x.device, dtype=x.dtype) + 0.5) / w * 2 - 1
    ys = 1 - (torch.arange(h, device=x.device, dtype=x.dtype) + 0.5) / h * 2
    grid = torch.stack([xs[None, :].expand(h, w), ys[:, None].expand(h, w)])
    return grid[None].expand(n, 2, h, w)
