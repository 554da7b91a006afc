"""Diffusion Policy (Chi et al. 2023), the CNN variant, small enough to train on a CPU.

An image encoder (trained from scratch) and the agent positions of the last ``To`` steps
condition a 1D temporal UNet, through FiLM in every residual block, that denoises a chunk
of ``Tp`` actions; with several camera views, an encoder per view, their features side by
side in the condition (the paper's code's default, ``share_rgb_model=False``). Training:
DDPM noise prediction (100 steps, squared-cosine betas, as the paper's code). Inference:
DDIM, a few deterministic steps. Execution: receding horizon, the ``Ta`` actions starting
at the current step, then replan (the paper's To = 2, Tp = 16, Ta = 8). The trainer keeps
EMA weights, which are what gets exported.
"""

from __future__ import annotations

from collections.abc import Iterable
from typing import cast

import numpy as np
import torch
from torch import nn

from iwsim.core.errors import InputError
from iwsim.diffusion.ddpm import EpsDenoiser, ddim_timesteps, sample_ddim, squared_cosine_alphas_cumprod
from iwsim.models.blocks import sinusoidal
from iwsim.policies.common import (
    ImageEncoder,
    Normalizer,
    Policy,
    PolicyBatch,
    prepare_obs,
)
from iwsim.policies.diffusion.config import DiffusionConfig


class Conv1dBlock(nn.Sequential):
    def __init__(self, c_in: int, c_out: int, kernel: int) -> None:
        super().__init__(nn.Conv1d(c_in, c_out, kernel, padding=kernel // 2), nn.GroupNorm(8, c_out), nn.Mish())


class FiLMResBlock(nn.Module):
    """Two conv blocks; the condition scales and shifts the first one's output per channel."""

    def __init__(self, c_in: int, c_out: int, cond_dim: int, kernel: int) -> None:
        super().__init__()
        self.block1, self.block2 = Conv1dBlock(c_in, c_out, kernel), Conv1dBlock(c_out, c_out, kernel)
        self.film = nn.Sequential(nn.Mish(), nn.Linear(cond_dim, 2 * c_out))
        self.skip = nn.Conv1d(c_in, c_out, 1) if c_in != c_out else nn.Identity()

    def forward(self, x: torch.Tensor, cond: torch.Tensor) -> torch.Tensor:
        scale, shift = self.film(cond)[..., None].chunk(2, 1)
        return self.block2(self.block1(x) * scale + shift) + self.skip(x)


class ConditionalUnet1D(nn.Module):
    """(B, A, Tp) noisy actions, timesteps (B,), condition (B, C) -> predicted noise."""

    def __init__(self, action_dim: int, cond_dim: int, cfg: DiffusionConfig) -> None:
        super().__init__()
        e = cfg.step_embed_dim
        self.step_dim = e
        self.step_mlp = nn.Sequential(nn.Linear(e, 4 * e), nn.Mish(), nn.Linear(4 * e, e))
        c = e + cond_dim
        dims = [action_dim, *cfg.down_dims]
        k = cfg.kernel_size
        self.down = nn.ModuleList()
        for i, (a, b) in enumerate(zip(dims[:-1], dims[1:])):
            last = i == len(dims) - 2
            self.down.append(nn.ModuleList([FiLMResBlock(a, b, c, k), FiLMResBlock(b, b, c, k),
                                            nn.Identity() if last else nn.Conv1d(b, b, 3, 2, 1)]))
        mid = dims[-1]
        self.mid = nn.ModuleList([FiLMResBlock(mid, mid, c, k), FiLMResBlock(mid, mid, c, k)])
        self.up = nn.ModuleList()
        for a, b in zip(reversed(dims[2:]), reversed(dims[1:-1])):
            self.up.append(nn.ModuleList([FiLMResBlock(2 * a, b, c, k), FiLMResBlock(b, b, c, k),
                                          nn.ConvTranspose1d(b, b, 4, 2, 1)]))
        self.out = nn.Sequential(Conv1dBlock(dims[1], dims[1], k), nn.Conv1d(dims[1], action_dim, 1))

    def forward(self, x: torch.Tensor, t: torch.Tensor, cond: torch.Tensor) -> torch.Tensor:
        g = torch.cat([self.step_mlp(sinusoidal(t, self.step_dim, sin_first=True, include_max=True)), cond], -1)
        skips = []
        for res1, res2, down in cast(Iterable[nn.ModuleList], self.down):
            x = res2(res1(x, g), g)
            skips.append(x)
            x = down(x)
        for res in self.mid:
            x = res(x, g)
        for res1, res2, up in cast(Iterable[nn.ModuleList], self.up):
            x = up(res2(res1(torch.cat([x, skips.pop()], 1), g), g))
        return self.out(x)


class DiffusionPolicy(Policy):
    """See the module docstring; the execution contract is in :mod:`iwsim.policies.common`."""

    alphas_cumprod: torch.Tensor  # buffer (train_steps,)

    def __init__(self, cfg: DiffusionConfig, action_norm: Normalizer, state_norm: Normalizer) -> None:
        super().__init__(cfg, action_norm, state_norm)
        def encoder() -> ImageEncoder:
            return ImageEncoder(cfg.image_features, cfg.encoder_channels, first_stride=cfg.encoder_stride)

        # One encoder per view, none shared (Diffusion Policy's share_rgb_model=False; LeRobot's
        # use_separate_rgb_encoder_per_camera); one view keeps the weights' names of before views.
        views = len(cfg.cameras)
        self.encoder: nn.Module = encoder() if views == 1 else nn.ModuleList(encoder() for _ in range(views))
        cond_dim = cfg.obs_horizon * (views * cfg.image_features + self.state_dim)
        self.unet = ConditionalUnet1D(self.action_dim, cond_dim, cfg)
        self.register_buffer("alphas_cumprod", squared_cosine_alphas_cumprod(cfg.train_steps))

    @property
    def denoiser(self) -> EpsDenoiser:
        """The noise predictor in the samplers' convention (:mod:`iwsim.diffusion`)."""
        return EpsDenoiser(self.unet, self.alphas_cumprod)

    @property
    def encoders(self) -> list[ImageEncoder]:
        """The image encoder of each view, in the views' order."""
        return cast(list[ImageEncoder], [self.encoder] if self.views == 1 else list(self.encoder.children()))

    def condition(self, image: torch.Tensor, agent_pos: torch.Tensor) -> torch.Tensor:
        """image (B, To, 3V, H, W), normalised agent_pos (B, To, S) -> the global condition
        (B, To * (V * F + S)): per step, each view's features in the views' order, then agent_pos."""
        if image.ndim != 5 or image.shape[2] != 3 * self.views:
            raise InputError(f"this policy sees {self.views} camera view(s) ({', '.join(self.cameras)}): expected "
                             f"images (B, To, {3 * self.views}, H, W), got {tuple(image.shape)}.")
        b, to = image.shape[:2]
        views = image.flatten(0, 1).chunk(self.views, 1)  # V x (B * To, 3, H, W)
        feats = torch.cat([enc(x) for enc, x in zip(self.encoders, views, strict=True)], -1).view(b, to, -1)
        return torch.cat([feats, agent_pos], -1).flatten(1)

    def forward(self, batch: PolicyBatch) -> tuple[torch.Tensor, dict[str, float]]:
        """DDPM's simple loss: predict the noise added to the action chunk at a random step."""
        x0 = batch.action.transpose(1, 2)  # (B, A, Tp)
        b = x0.shape[0]
        t = torch.randint(0, self.cfg.train_steps, (b,), device=x0.device)
        eps = torch.randn_like(x0)
        return self.denoiser.loss(x0, eps, t, cond=self.condition(batch.image, batch.agent_pos)), {}

    @torch.no_grad()
    def sample(self, cond: torch.Tensor, generator: torch.Generator | None = None) -> torch.Tensor:
        """DDIM (eta = 0) from noise: condition (B, C) -> normalised chunk (B, Tp, A)."""
        noise = torch.randn(cond.shape[0], self.action_dim, self.cfg.horizon, generator=generator, device=cond.device)
        timesteps = ddim_timesteps(self.cfg.train_steps, self.cfg.inference_steps)
        x = sample_ddim(self.denoiser, noise, timesteps, {"cond": cond})
        return x.transpose(1, 2)

    def reset(self) -> None:
        """Nothing to forget: each query replans from its observations."""

    @torch.no_grad()
    def predict_action(self, obs: dict, generator: torch.Generator | None = None) -> np.ndarray:
        """The next ``Ta`` actions (B, Ta, A) in the data's units, from the current step."""
        image, pos = prepare_obs(obs, self.state_norm, self.cfg.obs_horizon, self.cameras)
        chunk = self.sample(self.condition(image, pos), generator)
        start = self.cfg.obs_horizon - 1
        act = self.action_norm.unnormalize(chunk[:, start:start + self.cfg.n_action_steps])
        return self.to_absolute(act, obs).cpu().numpy()
