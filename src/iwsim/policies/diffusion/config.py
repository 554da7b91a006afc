"""Diffusion Policy: its config, registered as ``dp`` (the name its checkpoints store), and
its training presets. The network is :mod:`iwsim.policies.diffusion.model`."""

from __future__ import annotations

from dataclasses import dataclass

from iwsim.core.config import TrainConfig
from iwsim.core.errors import InputError
from iwsim.data.views import DEFAULT_CAMERA, check_cameras
from iwsim.policies.registry import TINY_TRAIN, PolicyStageConfig, register_policy

# The paper-sized-down defaults, and a tiny one for tests.
PRESETS = {
    "dp": PolicyStageConfig("dp", {}, TrainConfig(steps=20_000, batch_size=64, lr=3e-4, warmup_steps=500,
                                                  weight_decay=1e-6, eval_every=1000, checkpoint_every=1000)),
    "tiny-dp": PolicyStageConfig("dp", {"image_features": 16, "encoder_channels": (8, 16, 16),
                                        "down_dims": (16, 32), "horizon": 8, "n_action_steps": 4,
                                        "inference_steps": 4}, TINY_TRAIN, shift=2),
}


@register_policy("dp", model="iwsim.policies.diffusion.model:DiffusionPolicy",
                 execution=("n_action_steps", "inference_steps"), presets=PRESETS)
@dataclass(frozen=True)
class DiffusionConfig:
    obs_horizon: int = 2  # To
    horizon: int = 16  # Tp: actions per denoised chunk, from the first observed step
    n_action_steps: int = 8  # Ta: executed per query, from the current step
    image_features: int = 64
    encoder_channels: tuple[int, ...] = (32, 64, 64)
    encoder_stride: int = 2  # of the first conv: 64 px -> 8x8 keypoint maps; full-resolution convs cost 4x more
    down_dims: tuple[int, ...] = (64, 128, 256)
    kernel_size: int = 5
    step_embed_dim: int = 64
    train_steps: int = 100  # DDPM timesteps
    inference_steps: int = 10  # DDIM steps
    relative_actions: bool = False  # predict offsets from the current agent_pos (same size as the action)
    # the camera views it sees, in order (iwsim.data.views), stacked along the channels; set from
    # the training store's views (a checkpoint saved before views existed: one, the top view)
    cameras: tuple[str, ...] = (DEFAULT_CAMERA,)

    def __post_init__(self) -> None:
        check_cameras(self.cameras, "the policy's cameras")
        if not 1 <= self.n_action_steps <= self.horizon - self.obs_horizon + 1:
            raise InputError(f"n_action_steps must be in 1..{self.horizon - self.obs_horizon + 1} "
                             f"(horizon {self.horizon}, obs_horizon {self.obs_horizon}), got {self.n_action_steps}.")
        if self.horizon % 2 ** (len(self.down_dims) - 1):
            raise InputError(f"horizon {self.horizon} must be divisible by {2 ** (len(self.down_dims) - 1)} "
                             f"for {len(self.down_dims)} UNet levels.")
