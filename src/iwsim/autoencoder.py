"""The stage-1 autoencoder as one object: encode frames to latents, decode latents to frames.

    ae = Autoencoder.load("runs/ae/checkpoints/last")
    z = ae.encode(frames)                    # uint8 (B, H, W, 3) -> (B, C, H/4, W/4)
    frames = ae.decode(z, jumps=1)           # -> uint8 (B, H, W, 3)
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch
from torch import nn

from iwsim.checkpoint import CheckpointError, load_model_dir
from iwsim.config import AEConfig, from_dict
from iwsim.data.frames import to_model, to_uint8
from iwsim.diffusion.consistency import sample
from iwsim.diffusion.schedule import Schedule
from iwsim.errors import InputError
from iwsim.models.autoencoder import DecoderUNet, Encoder

KIND = "autoencoder"  # config.json's kind


class Autoencoder(nn.Module):
    """Encoder + consistency decoder (+ its noise schedule)."""

    def __init__(self, cfg: AEConfig) -> None:
        super().__init__()
        self.cfg = cfg
        self.encoder = Encoder(cfg.encoder)
        self.decoder = DecoderUNet(cfg.decoder)
        self.schedule = Schedule(cfg.schedule)
        self.register_buffer("_anchor", torch.zeros(0), persistent=False)  # tracks the device

    @property
    def image_size(self) -> int:
        return self.cfg.image_size

    def encode_tensor(self, x: torch.Tensor) -> torch.Tensor:
        """(B, 3, H, W) in [-1, 1] -> latents (B, C, H/4, W/4)."""
        return self.encoder(x)

    def decode_tensor(self, z: torch.Tensor, jumps: int = 1, generator: torch.Generator | None = None,
                      noise: torch.Tensor | None = None) -> torch.Tensor:
        """Latents (B, C, h, w) -> images (B, 3, 4h, 4w) in [-1, 1] by ``jumps`` consistency
        jumps from ``noise`` (B, 3, 4h, 4w) or, when not given, noise drawn from ``generator``."""
        b, _, h, w = z.shape
        shape = (b, self.cfg.decoder.image_channels, 4 * h, 4 * w)
        return sample(self.decoder, self.schedule, z, shape, num_jumps=jumps, generator=generator,
                      noise=noise).clamp(-1, 1)

    def reconstruct_tensor(self, x: torch.Tensor, jumps: int = 1, chunk: int = 64) -> torch.Tensor:
        """Encode then decode (B, 3, H, W) images in chunks; chunk i's noise is seeded by
        its first index, so results do not depend on what else is in the batch."""
        parts = []
        for i in range(0, len(x), chunk):
            z = self.encode_tensor(x[i:i + chunk])
            parts.append(self.decode_tensor(z, jumps, torch.Generator(x.device).manual_seed(i)))
        return torch.cat(parts)

    @torch.inference_mode()
    def encode(self, frames: np.ndarray | torch.Tensor) -> torch.Tensor:
        """uint8 frames (B, H, W, 3) -> latents (B, C, H/4, W/4)."""
        x = to_model(frames).to(self._device())
        if x.ndim != 4 or x.shape[-1] != self.image_size or x.shape[-2] != self.image_size:
            s = self.image_size
            raise InputError(f"expected frames (B, {s}, {s}, 3), got {tuple(frames.shape)}.")
        return self.encode_tensor(x)

    @torch.inference_mode()
    def decode(self, z: torch.Tensor, jumps: int = 1, generator: torch.Generator | None = None) -> np.ndarray:
        """Latents (B, C, h, w) -> uint8 frames (B, 4h, 4w, 3)."""
        return to_uint8(self.decode_tensor(z.to(self._device()), jumps, generator))

    def freeze_for_inference(self) -> Autoencoder:
        """Replace encoder and decoder by frozen TorchScript traces (constants folded,
        convolutions prepacked for oneDNN): the same outputs, ~25% less time per call at
        batch 1 on a CPU. The module can no longer be trained or saved; returns self."""
        size, c = self.image_size, self.cfg.encoder.latent_channels
        x = torch.zeros(1, self.cfg.encoder.image_channels, size, size, device=self._device())
        z = torch.zeros(1, c, size // 4, size // 4, device=x.device)
        t = torch.zeros(1, dtype=torch.long, device=x.device)
        self.eval()
        with torch.inference_mode():
            self.encoder = torch.jit.optimize_for_inference(torch.jit.freeze(torch.jit.trace(self.encoder, (x,))))
            self.decoder = torch.jit.optimize_for_inference(
                torch.jit.freeze(torch.jit.trace(self.decoder, (x, t, t, z))))
        return self

    def _device(self) -> torch.device:
        return self._anchor.device

    @classmethod
    def load(cls, path: str | Path, device: str | torch.device = "cpu") -> Autoencoder:
        """From a checkpoint directory holding ``model.safetensors`` and ``config.json``."""
        path = Path(path)
        config, tensors = load_model_dir(path, KIND)
        try:
            cfg = from_dict(AEConfig, config["model"])
        except (TypeError, ValueError, KeyError) as e:
            raise CheckpointError(f"{path / 'config.json'} is not an autoencoder config: {e}") from None
        model = cls(cfg)
        try:
            model.load_state_dict(tensors)
        except RuntimeError as e:
            raise CheckpointError(f"{path / 'model.safetensors'} does not match its config: {e}") from None
        return model.to(device).eval()
