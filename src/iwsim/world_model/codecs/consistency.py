"""The paper's codec (``consistency-ae``): a CNN encoder and a consistency-model decoder.

    ae = load_codec("runs/ae/checkpoints/last")   # a stage-1 run's checkpoint (iwsim.world_model.codecs.base)
    z = ae.encode(x)                  # (B, 3, 64, 64) in [-1, 1] -> (B, 4, 16, 16) (pusht-64)
    x = ae.decode(z, jumps=1)         # -> (B, 3, 64, 64) in [-1, 1], one consistency jump

The decoder is stochastic: it jumps from clipped Gaussian image noise to a frame, so
``decode`` takes that noise (or a generator to draw it). See :mod:`iwsim.world_model.codecs.base`.
"""

from __future__ import annotations

import torch

from iwsim.diffusion.consistency import JumpModel, jump_levels, sample_jumps, sample_levels, two_jump_loss
from iwsim.diffusion.schedule import Schedule, gaussian
from iwsim.world_model.codecs.base import EncoderCodec
from iwsim.world_model.codecs.consistency_net import DecoderUNet
from iwsim.world_model.presets import AEConfig


class Autoencoder(EncoderCodec):
    """Encoder + consistency decoder (+ its noise schedule): the ``consistency-ae`` codec."""

    kind = "consistency-ae"
    config_class = AEConfig
    stochastic = True

    _anchor: torch.Tensor  # an empty buffer

    def __init__(self, cfg: AEConfig) -> None:
        super().__init__(cfg, cfg.encoder)
        self.decoder: DecoderUNet | torch.jit.ScriptModule = DecoderUNet(cfg.decoder)  # see freeze_for_inference
        self.schedule = Schedule(cfg.schedule)
        self.register_buffer("_anchor", torch.zeros(0), persistent=False)  # tracks the device

    def decode(self, z: torch.Tensor, noise: torch.Tensor | None = None, jumps: int = 1,
               generator: torch.Generator | None = None) -> torch.Tensor:
        """Latents (B, C, h, w) -> images (B, 3, H, W) in [-1, 1] by ``jumps`` consistency
        jumps from ``noise`` (B, 3, H, W) or, when not given, noise drawn from ``generator``."""
        size = self.image_size
        shape = (z.shape[0], self.cfg.decoder.image_channels, size, size)
        x = gaussian(shape, generator, device=z.device, dtype=z.dtype) if noise is None else noise
        return sample_jumps(self.jump_model, x, jump_levels(jumps, self.schedule.T - 1), {"z": z}).clamp(-1, 1)

    @property
    def jump_model(self) -> JumpModel:
        """The decoder in the samplers' convention (:mod:`iwsim.diffusion`), condition ``z``."""
        return JumpModel(self.decoder, self.schedule)

    def training_noise(self, batch: int, generator: torch.Generator) -> dict[str, torch.Tensor]:
        """Jump levels t > s and the image noise of the decoder's two-jump loss."""
        t, s = sample_levels(batch, self.cfg.schedule.num_levels, generator, self.cfg.top_fraction)
        size = self.image_size
        return {"t": t, "s": s, "eps": gaussian((batch, self.cfg.decoder.image_channels, size, size), generator)}

    def loss(self, x0: torch.Tensor, z: torch.Tensor, noise: dict[str, torch.Tensor]
             ) -> tuple[torch.Tensor, dict[str, float]]:
        """The decoder's two-jump consistency loss (:func:`two_jump_loss`) given latents ``z``."""
        return two_jump_loss(self.jump_model, x0, noise["t"], noise["s"], noise["eps"], {"z": z})

    def freeze_for_inference(self) -> Autoencoder:
        """Replace encoder and decoder by frozen TorchScript traces (constants folded,
        convolutions prepacked for oneDNN): the same outputs, less time per call at
        batch 1 on a CPU. The module can no longer be trained or saved; returns self."""
        size = self.image_size
        x = torch.zeros(1, self.cfg.encoder.image_channels, size, size, device=self._device())
        z = torch.zeros(1, *self.latent_shape, device=x.device)
        t = torch.zeros(1, dtype=torch.long, device=x.device)
        self.eval()
        with torch.inference_mode():
            self.encoder = torch.jit.optimize_for_inference(torch.jit.freeze(torch.jit.trace(self.encoder, (x,))))
            self.decoder = torch.jit.optimize_for_inference(
                torch.jit.freeze(torch.jit.trace(self.decoder, (x, t, t, z))))
        return self

    def _device(self) -> torch.device:
        return self._anchor.device
