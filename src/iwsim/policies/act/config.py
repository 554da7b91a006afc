"""ACT: its config, registered as ``act`` (the name its checkpoints store), and
its training presets. The network is :mod:`iwsim.policies.act.model`."""

from __future__ import annotations

from dataclasses import dataclass

from iwsim.core.config import TrainConfig
from iwsim.core.errors import InputError
from iwsim.data.views import DEFAULT_CAMERA, check_cameras
from iwsim.policies.registry import TINY_TRAIN, PolicyStageConfig, register_policy

# The paper-sized-down defaults, and a tiny one for tests.
PRESETS = {
    # Diffusion Policy's trunk (a first conv of stride 2: the same 8 x 8 cells, a cheaper
    # step) and its learning rate, 3e-4, faster per step than the paper's 1e-4
    # (bench/results/policies/runs.md, "ACT's execution and budget").
    "act": PolicyStageConfig("act", {"encoder_channels": (32, 64, 64), "encoder_stride": 2},
                             TrainConfig(steps=20_000, batch_size=32, lr=3e-4, warmup_steps=500,
                                         weight_decay=1e-4, eval_every=1000, checkpoint_every=1000)),
    "tiny-act": PolicyStageConfig("act", {"chunk_size": 8, "dim": 32, "heads": 2, "enc_layers": 1, "dec_layers": 1,
                                          "ff_dim": 64}, TINY_TRAIN, shift=2),
}


@register_policy("act", model="iwsim.policies.act.model:ACTPolicy",
                 execution=("n_action_steps", "temporal_ensemble"), presets=PRESETS)
@dataclass(frozen=True)
class ACTConfig:
    obs_horizon: int = 1  # ACT observes the current step only
    chunk_size: int = 16  # k: actions predicted per query (the paper: 100 at 50 Hz)
    n_action_steps: int = 1  # actions executed per query (1 with temporal ensembling)
    temporal_ensemble: float | None = 0.01  # m in w_i = exp(-m * i); None: execute n_action_steps per chunk
    encoder_channels: tuple[int, ...] = (32, 64, 64, 64)  # CNN trunk; levels after the first halve H and W
    encoder_stride: int = 1  # of the first conv; 2 with one level fewer gives the same cells at ~1/4 the cost
    # "cells": a token per cell of the trunk's feature map (the paper's); "keypoints": a token per
    # spatial-softmax keypoint of it, made from its (x, y) (Diffusion Policy's pooling)
    image_tokens: str = "cells"
    keypoints: int = 32  # how many, with image_tokens="keypoints"
    dim: int = 128
    heads: int = 4
    enc_layers: int = 2
    dec_layers: int = 2
    vae_layers: int = 2  # the CVAE encoder's transformer layers (the paper: 4)
    ff_dim: int = 256
    dropout: float = 0.1
    latent_dim: int = 32  # as the paper
    kl_weight: float = 10.0  # beta, as the paper
    observe_state: bool = True  # False: act from the image alone (the agent_pos token is blanked)
    relative_actions: bool = False  # predict offsets from the current agent_pos (same size as the action)
    # the camera views it sees, in order (iwsim.data.views), stacked along the channels; set from
    # the training store's views (a checkpoint saved before views existed: one, the top view)
    cameras: tuple[str, ...] = (DEFAULT_CAMERA,)

    @property
    def horizon(self) -> int:
        """Future actions a training window holds (as DiffusionConfig.horizon)."""
        return self.chunk_size

    def __post_init__(self) -> None:
        check_cameras(self.cameras, "the policy's cameras")
        if self.obs_horizon != 1:
            raise InputError(f"ACT observes the current step only: obs_horizon must be 1, got {self.obs_horizon}.")
        if not 1 <= self.n_action_steps <= self.chunk_size:
            raise InputError(f"n_action_steps must be in 1..chunk_size ({self.chunk_size}), got {self.n_action_steps}.")
        if self.temporal_ensemble is not None and self.n_action_steps != 1:
            raise InputError(f"temporal ensembling queries every step, so n_action_steps must be 1, got "
                             f"{self.n_action_steps}; set temporal_ensemble to None to execute several.")
        if self.dim % 4 or self.dim % self.heads:
            raise InputError(f"dim must be divisible by 4 (2D sine embedding) and by heads ({self.heads}), "
                             f"got {self.dim}.")
        if self.image_tokens not in ("cells", "keypoints"):
            raise InputError(f"image_tokens must be 'cells' or 'keypoints', got {self.image_tokens!r}.")
        if self.encoder_stride not in (1, 2):
            raise InputError(f"encoder_stride must be 1 or 2, got {self.encoder_stride}.")
        if not self.encoder_channels or any(c % 8 for c in self.encoder_channels):
            raise InputError(f"encoder_channels must be multiples of 8 (GroupNorm(8)), got {self.encoder_channels}.")
