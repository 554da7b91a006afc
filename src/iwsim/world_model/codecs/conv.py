"""A plain convolutional autoencoder (``conv-ae``): the same CNN encoder as the paper's
codec, a mirrored deterministic decoder trained by pixel regression, and any power-of-two
downsampling (``channels``: one level per halving plus one; ``(32, 64)`` gives 32 x 32
latents at 64 px).

Cheaper than the consistency decoder (one pass, no noise), so a representation can be
tried in minutes; its frames are the conditional mean, blurrier where the latent is
ambiguous. See :mod:`iwsim.world_model.codecs.base` for the interface.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import cast

import torch
from torch import nn
from torch.nn import functional as F

from iwsim.core.config import TrainConfig
from iwsim.models.blocks import ResBlock, group_norm
from iwsim.world_model.codecs.base import EncoderCodec
from iwsim.world_model.codecs.consistency_net import EncoderConfig


@dataclass(frozen=True)
class ConvCodecConfig:
    image_size: int  # the frames' (a preset's, or the checkpoint's: every conv-ae checkpoint records it)
    image_channels: int = 3
    latent_channels: int = 4
    channels: tuple[int, ...] = (32, 64)  # at H, H/2, ...: the latent is H / 2^(levels - 1) wide
    blocks_per_level: int = 1
    l1_weight: float = 1.0  # loss: MSE + this x L1 (sharper edges than MSE alone)
    # Extra loss weight on foreground pixels: those whose colour differs from the scene's
    # background (the per-pixel median of training frames, :meth:`ConvCodec.prepare`) by
    # more than ``foreground_threshold`` in some channel ([-1, 1] units). What moves, and
    # so the small things (a pusher is ~20 of 4096 pixels), then counts.
    foreground_weight: float = 0.0
    foreground_threshold: float = 0.2
    # Weight the pixels the decoder paints as foreground too, not only the target's. Weighting
    # the target's alone makes a missed foreground pixel cost 1 + weight times a false one,
    # so where unsure the decoder paints foreground: small things grow (a pile's pieces by
    # ~10% of their area, which a pixel count reads as extra pieces).
    foreground_symmetric: bool = False
    train: TrainConfig = field(default_factory=TrainConfig)
    holdout_every: int = 20
    eval_images: int = 256
    eval_jumps: tuple[int, ...] = (1,)
    freeze_encoder: bool = False
    latent_noise: tuple[float, float] = (0.0, 0.0)  # as AEConfig's (stage 3; the coarse presets in stage 1)
    latent_noise_scale: float = 1.0

    @property
    def encoder(self) -> EncoderConfig:
        return EncoderConfig(self.image_channels, self.latent_channels, self.channels, self.blocks_per_level)


class ConvDecoder(nn.Module):
    """Latents (B, C, h, w) -> images (B, 3, H, W): the encoder mirrored, nearest upsampling."""

    def __init__(self, cfg: ConvCodecConfig) -> None:
        super().__init__()
        ch = tuple(reversed(cfg.channels))
        self.conv_in = nn.Conv2d(cfg.latent_channels, ch[0], 3, padding=1)
        self.levels = nn.ModuleList()
        c = ch[0]
        for co in ch:
            blocks = nn.ModuleList()
            for _ in range(cfg.blocks_per_level):
                blocks.append(ResBlock(c, co))
                c = co
            self.levels.append(blocks)
        self.norm_out = group_norm(c)
        self.conv_out = nn.Conv2d(c, cfg.image_channels, 3, padding=1)

    def forward(self, z: torch.Tensor) -> torch.Tensor:
        h = self.conv_in(z)
        for i, blocks in enumerate(self.levels):
            if i > 0:
                h = F.interpolate(h, scale_factor=2.0, mode="nearest")
            for block in cast(nn.ModuleList, blocks):
                h = block(h)
        return self.conv_out(F.silu(self.norm_out(h)))


class ConvCodec(EncoderCodec):
    kind = "conv-ae"
    config_class = ConvCodecConfig
    stochastic = False

    background: torch.Tensor  # buffer (1, 3, H, W)

    def __init__(self, cfg: ConvCodecConfig) -> None:
        super().__init__(cfg, cfg.encoder)
        self.decoder = ConvDecoder(cfg)
        self.register_buffer("background", torch.zeros(1, cfg.image_channels, cfg.image_size, cfg.image_size))

    def prepare(self, frames: torch.Tensor) -> None:
        """Take the background, the per-pixel median of training ``frames`` (N, 3, H, W),
        when the loss weights the foreground."""
        if self.cfg.foreground_weight > 0:
            self.background.copy_(frames.median(dim=0, keepdim=True).values)

    def decode(self, z: torch.Tensor, noise: torch.Tensor | None = None, jumps: int = 1,
               generator: torch.Generator | None = None) -> torch.Tensor:
        """Deterministic: ``noise``, ``jumps`` and ``generator`` are ignored."""
        return self.decoder(z).clamp(-1, 1)

    def training_noise(self, batch: int, generator: torch.Generator) -> dict[str, torch.Tensor]:
        return {}

    def foreground(self, x: torch.Tensor) -> torch.Tensor:
        """(B, 1, H, W) 1.0 where images ``x`` (B, 3, H, W) differ from the background."""
        return ((x - self.background).abs().amax(dim=1, keepdim=True) > self.cfg.foreground_threshold).to(x.dtype)

    def loss(self, x0: torch.Tensor, z: torch.Tensor, noise: dict[str, torch.Tensor]
             ) -> tuple[torch.Tensor, dict[str, float]]:
        err = self.decoder(z) - x0
        mse, l1 = (err**2).mean(), err.abs().mean()
        if self.cfg.foreground_weight <= 0:
            return mse + self.cfg.l1_weight * l1, {"mse": mse.item(), "l1": l1.item()}
        fg = self.foreground(x0)
        if self.cfg.foreground_symmetric:
            fg = torch.maximum(fg, self.foreground((x0 + err).detach()))
        w = 1.0 + self.cfg.foreground_weight * fg
        loss = (w * (err**2 + self.cfg.l1_weight * err.abs())).mean() / w.mean()
        return loss, {"mse": mse.item(), "l1": l1.item(), "foreground": fg.mean().item()}
