"""Stage 1 networks: the CNN encoder and the consistency decoder's UNet.

Encoder: image (B, 3, H, W) in [-1, 1] -> latent (B, C, H/d, W/d), d = 2^(levels - 1)
(three levels of channels: d = 4, 16 x 16 latents at 64 px; two: d = 2). Each latent pixel's
C-vector is L2-normalised and scaled by sqrt(C) (as in the public code), so every element
has unit scale on average and stage 2 sees a fixed range.

Decoder UNet: the jump network ``net(x_t, t, s, z) -> v`` of ``iwsim.diffusion.consistency``,
conditioned on the latent by concatenation at the input (z upsampled to H x W) and by an
added 1x1 projection of z at every resolution.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import cast

import torch
from torch import nn
from torch.nn import functional as F

from iwsim.core.errors import InputError
from iwsim.models.blocks import ResBlock, group_norm, sinusoidal, zero_init


@dataclass(frozen=True)
class EncoderConfig:
    image_channels: int = 3
    latent_channels: int = 4
    channels: tuple[int, ...] = (16, 32, 64)  # at H, H/2, H/4: three levels = two halvings
    blocks_per_level: int = 1

    @property
    def downsampling(self) -> int:
        """H / h: the latent's cells are this many pixels wide."""
        return 2 ** (len(self.channels) - 1)


@dataclass(frozen=True)
class DecoderConfig:
    image_channels: int = 3
    latent_channels: int = 4
    channels: tuple[int, ...] = (16, 32, 64)  # at H, H/2, H/4
    blocks_per_level: int = 1
    emb_dim: int = 128
    num_levels: int = 1000  # noise levels are embedded as t / T * 1000


class Encoder(nn.Module):
    def __init__(self, cfg: EncoderConfig = EncoderConfig()) -> None:
        super().__init__()
        if not cfg.channels:
            raise InputError("the encoder needs at least one level of channels.")
        self.cfg = cfg
        self.conv_in = nn.Conv2d(cfg.image_channels, cfg.channels[0], 3, padding=1)
        layers: list[nn.Module] = []
        c = cfg.channels[0]
        for i, ch in enumerate(cfg.channels):
            if i > 0:
                layers.append(nn.Conv2d(c, c, 3, stride=2, padding=1))
            for _ in range(cfg.blocks_per_level):
                layers.append(ResBlock(c, ch))
                c = ch
        self.blocks = nn.ModuleList(layers)
        self.norm_out = group_norm(c)
        self.conv_out = nn.Conv2d(c, cfg.latent_channels, 3, padding=1)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """(B, 3, H, W) in [-1, 1] -> (B, C, H/d, W/d), each pixel's C-vector of norm sqrt(C)."""
        assert x.ndim == 4, f"expected (B, 3, H, W), got {tuple(x.shape)}"
        h = self.conv_in(x)
        for layer in self.blocks:
            h = layer(h)
        z = self.conv_out(F.silu(self.norm_out(h)))
        return F.normalize(z, dim=1, eps=1e-6) * math.sqrt(self.cfg.latent_channels)


class DecoderUNet(nn.Module):
    def __init__(self, cfg: DecoderConfig = DecoderConfig()) -> None:
        super().__init__()
        self.cfg = cfg
        ch, e = cfg.channels, cfg.emb_dim
        self.emb = nn.Sequential(nn.Linear(2 * e, e), nn.SiLU(), nn.Linear(e, e))
        self.conv_in = nn.Conv2d(cfg.image_channels + cfg.latent_channels, ch[0], 3, padding=1)
        # z enters each level at that level's incoming width (the previous level's channels).
        self.z_in = nn.ModuleList(nn.Conv2d(cfg.latent_channels, c, 1) for c in (ch[0], *ch[:-1]))
        self.down = nn.ModuleList()
        self.downsample = nn.ModuleList()
        c, skips = ch[0], []
        for i, co in enumerate(ch):
            blocks = nn.ModuleList()
            for _ in range(cfg.blocks_per_level):
                blocks.append(ResBlock(c, co, e))
                c = co
                skips.append(c)
            self.down.append(blocks)
            self.downsample.append(nn.Conv2d(c, c, 3, stride=2, padding=1) if i < len(ch) - 1 else nn.Identity())
        self.mid = ResBlock(c, c, e)
        self.up = nn.ModuleList()
        for co in reversed(ch):
            blocks = nn.ModuleList()
            for _ in range(cfg.blocks_per_level):
                blocks.append(ResBlock(c + skips.pop(), co, e))
                c = co
            self.up.append(blocks)
        self.norm_out = group_norm(c)
        self.conv_out = nn.Conv2d(c, cfg.image_channels, 3, padding=1)
        zero_init(self.conv_out)

    def forward(self, x: torch.Tensor, t: torch.Tensor, s: torch.Tensor, z: torch.Tensor) -> torch.Tensor:
        """x_t (B, 3, H, W), levels t and s (B,), latent z (B, C, h, w) (any h | H) -> v (B, 3, H, W)."""
        assert x.ndim == 4 and z.ndim == 4, f"expected 4-D x and z, got {tuple(x.shape)}, {tuple(z.shape)}"
        scale = 1000.0 / self.cfg.num_levels
        emb = self.emb(torch.cat([sinusoidal(t * scale, self.cfg.emb_dim), sinusoidal(s * scale, self.cfg.emb_dim)], 1))
        h = self.conv_in(torch.cat([x, F.interpolate(z, size=x.shape[-2:], mode="nearest")], dim=1))
        skips = []
        for i, (blocks, down) in enumerate(zip(self.down, self.downsample)):
            h = h + self.z_in[i](F.interpolate(z, size=h.shape[-2:], mode="nearest"))
            for block in cast(nn.ModuleList, blocks):
                h = block(h, emb)
                skips.append(h)
            h = down(h)
        h = self.mid(h, emb)
        for i, blocks in enumerate(self.up):
            for block in cast(nn.ModuleList, blocks):
                h = block(torch.cat([h, skips.pop()], dim=1), emb)
            if i < len(self.up) - 1:  # nearest upsampling; the next block's convs smooth it
                h = F.interpolate(h, scale_factor=2.0, mode="nearest")
        return self.conv_out(F.silu(self.norm_out(h)))
