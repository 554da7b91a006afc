"""Stage 2 network: the latent dynamics F, a jump network over a sliding window of latents.

Frames of two kinds flow through F, each a latent (C, h, w) with its own noise level and
the action that produced it (a_{k-1} for frame k):

- context frames: past latents, lightly noised (training) or labelled with a small level
  (inference); a context frame at time k attends to the context frames k-N+1 .. k;
- target frames: the noisy latent of a frame to predict at time k; it attends to the
  context frames k-N+1 .. k-1 and to itself, and nothing attends to it.

So every window holds N frames: N - 1 context frames and the frame being predicted. All
layers but the temporal attention act on each frame alone (3D convolutions with per-frame
(1, 3, 3) kernels, i.e. 2D convolutions over B*T frames; per-frame GroupNorm; FiLM from
the frame's level and action; spatial attention within the frame), and temporal attention
is causal with a band of N. Hence a context frame's activations never change once
computed: inference keeps, per temporal-attention layer, the keys and values of the last
N - 1 context frames (a key/value cache, as in a causal transformer) and each step
computes only the new target frame and the context frame that just joined.

Training runs one sequence of L context frames and the L targets they predict in one
pass (the attention mask above), so every position of a sequence is a training target;
the same code with a cache is the streaming step (see :class:`Cache`).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import torch
from torch import nn
from torch.nn import functional as F

from iwsim.models.blocks import ResBlock, group_norm, sinusoidal


@dataclass(frozen=True)
class DynamicsConfig:
    latent_channels: int = 4
    action_dim: int = 4
    window: int = 8  # N: frames per window, N - 1 context frames + the predicted frame
    channels: tuple[int, int] = (64, 128)  # at latent resolution h and h/2
    heads: int = 4
    emb_dim: int = 128
    num_levels: int = 1000  # noise levels are embedded as t / T * 1000


@dataclass
class Cache:
    """Per temporal-attention layer, keys and values (B*h*w, heads, M, d) of the last
    M <= N - 1 context frames, and their times (M,)."""

    keys: list[torch.Tensor] = field(default_factory=list)
    values: list[torch.Tensor] = field(default_factory=list)
    times: torch.Tensor | None = None

    def __len__(self) -> int:
        return 0 if self.times is None else len(self.times)


class TemporalAttention(nn.Module):
    """Causal attention over time at each spatial position, with a learned bias per head
    and time offset (0 .. N-1), and a band of N frames (see the module docstring)."""

    def __init__(self, channels: int, heads: int, window: int) -> None:
        super().__init__()
        self.heads, self.window = heads, window
        self.norm = group_norm(channels)
        self.qkv = nn.Linear(channels, 3 * channels)
        self.out = nn.Linear(channels, channels)
        self.bias = nn.Parameter(torch.zeros(heads, window))
        nn.init.zeros_(self.out.weight)
        nn.init.zeros_(self.out.bias)

    def forward(self, x: torch.Tensor, layout: tuple[torch.Tensor, torch.Tensor, torch.Tensor],
                past_k: torch.Tensor | None, past_v: torch.Tensor | None
                ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """x (B, F, c, h, w) for F frames; ``layout`` from :func:`attention_layout`; past
        keys/values (B*h*w, heads, M, d) of M earlier context frames. Returns the output
        like x and this call's context keys and values (to cache)."""
        b, f, c, h, w = x.shape
        is_ctx, offset, allowed = layout
        hd = c // self.heads
        y = self.norm(x.flatten(0, 1)).view(b, f, c, h * w).permute(0, 3, 1, 2).reshape(b * h * w, f, c)
        q, k, v = self.qkv(y).view(b * h * w, f, 3, self.heads, hd).permute(2, 0, 3, 1, 4)
        new_k, new_v = k[:, :, is_ctx], v[:, :, is_ctx]
        if past_k is not None:
            k, v = torch.cat([past_k, k], 2), torch.cat([past_v, v], 2)
        bias = self.bias[:, offset.clamp(0, self.window - 1)]  # (heads, F, M + F)
        mask = bias.masked_fill(~allowed, float("-inf")).to(q.dtype)
        o = F.scaled_dot_product_attention(q, k, v, attn_mask=mask[None])
        o = o.permute(0, 2, 1, 3).reshape(b, h * w, f, c).permute(0, 2, 3, 1).reshape(b, f, c, h, w)
        return x + self.out(o.movedim(2, -1)).movedim(-1, 2), new_k, new_v


def attention_layout(times: torch.Tensor, is_ctx: torch.Tensor, past_times: torch.Tensor | None,
                     window: int) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Who attends to whom, shared by all temporal-attention layers of a pass: F query
    frames at ``times`` (F,) of kinds ``is_ctx`` (F,), keys = the M cached context frames
    at ``past_times`` then the F frames. Returns is_ctx, the time offsets (F, M + F) and
    the allowed pairs (F, M + F): a context query at k sees context keys k-N+1 .. k; a
    target query at k sees context keys k-N+1 .. k-1, and itself."""
    f = len(times)
    key_times, key_ctx = times, is_ctx
    if past_times is not None:
        key_times = torch.cat([past_times, times])
        key_ctx = torch.cat([torch.ones_like(past_times, dtype=torch.bool), is_ctx])
    offset = times[:, None] - key_times[None, :]
    is_self = torch.zeros_like(offset, dtype=torch.bool)
    is_self[:, -f:] = torch.eye(f, dtype=torch.bool, device=times.device)
    ctx_q = is_ctx[:, None]
    allowed = key_ctx[None, :] & (offset >= 0) & (offset <= window - 1) & (ctx_q | (offset >= 1))
    return is_ctx, offset, allowed | (is_self & ~ctx_q)


class SpatialAttention(nn.Module):
    """Self-attention among the positions of each frame."""

    def __init__(self, channels: int, heads: int) -> None:
        super().__init__()
        self.heads = heads
        self.norm = group_norm(channels)
        self.qkv = nn.Conv2d(channels, 3 * channels, 1)
        self.out = nn.Conv2d(channels, channels, 1)
        nn.init.zeros_(self.out.weight)
        nn.init.zeros_(self.out.bias)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """x (N, c, h, w) -> like x."""
        n, c, h, w = x.shape
        q, k, v = self.qkv(self.norm(x)).view(n, 3, self.heads, c // self.heads, h * w).transpose(-1, -2).unbind(1)
        o = F.scaled_dot_product_attention(q, k, v)  # (n, heads, hw, d)
        return x + self.out(o.transpose(-1, -2).reshape(n, c, h, w))


class Dynamics(nn.Module):
    """F(frames, levels, actions) -> v-prediction per frame; see the module docstring."""

    def __init__(self, cfg: DynamicsConfig = DynamicsConfig()) -> None:
        super().__init__()
        self.cfg = cfg
        c1, c2 = cfg.channels
        e = cfg.emb_dim
        self.level_mlp = nn.Sequential(nn.Linear(e, e), nn.SiLU(), nn.Linear(e, e))
        # action + "known" flag (the first frame of an episode has no producing action)
        self.action_mlp = nn.Sequential(nn.Linear(cfg.action_dim + 1, e), nn.SiLU(), nn.Linear(e, e))
        # + 2 coordinate channels (CoordConv, Liu et al. 2018): actions are absolute pusher
        # targets, and FiLM's per-channel modulation can only place them with positions at hand.
        self.conv_in = nn.Conv2d(cfg.latent_channels + 2, c1, 3, padding=1)
        self.block1 = ResBlock(c1, c1, e)
        self.tattn1 = TemporalAttention(c1, cfg.heads, cfg.window)
        self.down = nn.Conv2d(c1, c2, 3, stride=2, padding=1)
        self.block2 = ResBlock(c2, c2, e)
        self.sattn = SpatialAttention(c2, cfg.heads)
        self.tattn2 = TemporalAttention(c2, cfg.heads, cfg.window)
        self.block3 = ResBlock(c2, c2, e)
        self.tattn3 = TemporalAttention(c2, cfg.heads, cfg.window)
        self.block4 = ResBlock(c2 + c2, c1, e)
        self.block5 = ResBlock(c1 + c1, c1, e)
        self.norm_out = group_norm(c1)
        self.conv_out = nn.Conv2d(c1, cfg.latent_channels, 3, padding=1)
        nn.init.zeros_(self.conv_out.weight)
        nn.init.zeros_(self.conv_out.bias)

    def embed(self, levels: torch.Tensor, jump_to: torch.Tensor, actions: torch.Tensor,
              known: torch.Tensor) -> torch.Tensor:
        """Per-frame embedding (N, E) from levels t and s (N,), actions (N, A), known (N,)."""
        scale = 1000.0 / self.cfg.num_levels
        lv = torch.cat([sinusoidal(levels * scale, self.cfg.emb_dim // 2),
                        sinusoidal(jump_to * scale, self.cfg.emb_dim // 2)], 1)
        a = torch.cat([actions * known[:, None], known[:, None]], 1).to(lv.dtype)
        return self.level_mlp(lv) + self.action_mlp(a)

    def forward(self, x: torch.Tensor, levels: torch.Tensor, jump_to: torch.Tensor, actions: torch.Tensor,
                known: torch.Tensor, times: torch.Tensor, is_ctx: torch.Tensor, cache: Cache | None = None
                ) -> tuple[torch.Tensor, Cache]:
        """One pass over F frames per batch item.

        x (B, F, C, h, w) latents (noisy for targets); levels, jump_to (B, F) (a context
        frame's jump_to is its own level); actions (B, F, A) normalised, known (B, F) 0/1;
        times (F,) and is_ctx (F,) describe the frames (shared by the batch). ``cache``
        holds earlier context frames. Returns v (B, F, C, h, w) (meaningful for targets)
        and the cache extended by this call's context frames, trimmed to N - 1 frames.
        """
        assert x.ndim == 5, f"expected (B, F, C, h, w), got {tuple(x.shape)}"
        b, f = x.shape[:2]
        emb = self.embed(levels.flatten(), jump_to.flatten(), actions.flatten(0, 1), known.flatten().to(x.dtype))
        cache = cache or Cache()
        past_times = cache.times
        layout = attention_layout(times, is_ctx, past_times, self.cfg.window)
        new_keys, new_values = [], []

        def temporal(layer: TemporalAttention, i: int, h: torch.Tensor) -> torch.Tensor:
            pk = cache.keys[i] if cache.keys else None
            pv = cache.values[i] if cache.values else None
            out, k, v = layer(h.unflatten(0, (b, f)), layout, pk, pv)
            new_keys.append(k if pk is None else torch.cat([pk, k], 2))
            new_values.append(v if pv is None else torch.cat([pv, v], 2))
            return out.flatten(0, 1)

        flat = x.flatten(0, 1)
        h = self.conv_in(torch.cat([flat, coordinates(flat)], 1))
        h1 = temporal(self.tattn1, 0, self.block1(h, emb))
        h = self.down(h1)
        h = self.sattn(self.block2(h, emb))
        h2 = temporal(self.tattn2, 1, h)
        h = temporal(self.tattn3, 2, self.block3(h2, emb))
        h = self.block4(torch.cat([h, h2], 1), emb)
        h = F.interpolate(h, scale_factor=2.0, mode="nearest")
        h = self.block5(torch.cat([h, h1], 1), emb)
        v = self.conv_out(F.silu(self.norm_out(h))).unflatten(0, (b, f))

        keep = self.cfg.window - 1
        ctx_times = times[is_ctx]
        all_times = ctx_times if past_times is None else torch.cat([past_times, ctx_times])
        new = Cache([k[:, :, -keep:] for k in new_keys], [v_[:, :, -keep:] for v_ in new_values], all_times[-keep:])
        return v, new


def coordinates(x: torch.Tensor) -> torch.Tensor:
    """(N, 2, h, w) maps of the pixel-centre x (left to right) and y (bottom to top) in (-1, 1)."""
    n, _, h, w = x.shape
    xs = (torch.arange(w, device=x.device, dtype=x.dtype) + 0.5) / w * 2 - 1
    ys = 1 - (torch.arange(h, device=x.device, dtype=x.dtype) + 0.5) / h * 2
    grid = torch.stack([xs[None, :].expand(h, w), ys[:, None].expand(h, w)])
    return grid[None].expand(n, 2, h, w)


def sequence_layout(length: int, device: torch.device | str = "cpu") -> tuple[torch.Tensor, torch.Tensor]:
    """Times and kinds of a training sequence: context frames 0..L-1, then the L targets
    at times 1..L (target k+1 is predicted from the context up to k)."""
    times = torch.cat([torch.arange(length), torch.arange(1, length + 1)]).to(device)
    is_ctx = torch.cat([torch.ones(length, dtype=torch.bool), torch.zeros(length, dtype=torch.bool)]).to(device)
    return times, is_ctx

