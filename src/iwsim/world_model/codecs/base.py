"""The codec seam: what the world model needs of a latent representation.

A codec maps frames to latents and back. The dynamics only ever sees latents of
``latent_shape`` (C, h, w); the world model only calls the methods below, so a new latent
representation is one codec module plus a preset (:mod:`iwsim.world_model.presets`):

- ``consistency-ae`` (:mod:`iwsim.world_model.codecs.consistency`): the CNN encoder and the
  consistency-model decoder of the paper; stochastic (its decode takes image noise);
- ``conv-ae`` (:mod:`iwsim.world_model.codecs.conv`): a plain convolutional autoencoder
  with a deterministic decoder and any power-of-two downsampling.

Stage-1 training (:mod:`iwsim.world_model.train_codec`) asks the codec for its loss, so
it trains any codec; checkpoints name the codec's ``kind`` beside its config, and
:mod:`iwsim.world_model.codecs` builds and loads codecs by kind.
"""

from __future__ import annotations

from collections.abc import Iterator, Mapping
from typing import Any, Protocol, Self, runtime_checkable

import torch
from torch import nn

from iwsim.world_model.codecs.consistency_net import Encoder, EncoderConfig

KIND = "autoencoder"  # config.json's kind for a stage-1 run's checkpoints (any codec)
DEFAULT_KIND = "consistency-ae"  # checkpoints written before codecs had names hold this one


@runtime_checkable
class Codec(Protocol):
    """Frames (B, 3, H, W) in [-1, 1] <-> latents (B, *latent_shape)."""

    kind: str  # the name checkpoints store

    @property
    def config_class(self) -> type: ...  # of cfg

    # the config: a dataclass with image_size, train (TrainConfig) and stage 1's fields
    # holdout_every, eval_images, eval_jumps, freeze_encoder, latent_noise, latent_noise_scale
    cfg: Any

    @property
    def image_size(self) -> int: ...

    @property
    def latent_shape(self) -> tuple[int, int, int]:
        """(C, h, w) of one frame's latent."""
        ...

    @property
    def stochastic(self) -> bool:
        """Whether ``decode`` uses its image noise (else it is ignored and may be None)."""
        ...

    def encode(self, x: torch.Tensor) -> torch.Tensor:
        """(B, 3, H, W) in [-1, 1] -> latents (B, C, h, w)."""
        ...

    def decode(self, z: torch.Tensor, noise: torch.Tensor | None = None, jumps: int = 1,
               generator: torch.Generator | None = None) -> torch.Tensor:
        """Latents (B, C, h, w) -> images (B, 3, H, W) in [-1, 1]; a stochastic codec draws
        from clipped Gaussian ``noise`` (B, 3, H, W), or from ``generator`` when not given."""
        ...

    def training_noise(self, batch: int, generator: torch.Generator) -> dict[str, torch.Tensor]:
        """The per-sample randomness of one training step (drawn on the CPU, so every
        DDP rank and every rerun sees the same)."""
        ...

    def loss(self, x0: torch.Tensor, z: torch.Tensor, noise: dict[str, torch.Tensor]
             ) -> tuple[torch.Tensor, dict[str, float]]:
        """The decoder's training loss for rendering ``x0`` from latents ``z`` (the
        encoder's, possibly noised), and its terms for logging."""
        ...

    def encoder_parameters(self) -> list[torch.nn.Parameter]: ...

    def prepare(self, frames: torch.Tensor) -> None:
        """Take what the loss needs from a sample of training frames (N, 3, H, W) in
        [-1, 1] before fresh training (e.g. a background image); most codecs need nothing."""
        ...

    # and what every codec inherits from nn.Module:
    def parameters(self, recurse: bool = True) -> Iterator[nn.Parameter]: ...

    def buffers(self, recurse: bool = True) -> Iterator[torch.Tensor]: ...

    def state_dict(self) -> dict[str, Any]: ...

    def load_state_dict(self, state_dict: Mapping[str, Any], strict: bool = True, assign: bool = False) -> Any: ...

    def to(self, *args: Any, **kwargs: Any) -> Self: ...

    def eval(self) -> Self: ...


class EncoderCodec(nn.Module):
    """What the codecs built on the CNN encoder (:class:`Encoder`) share: its latents are
    ``image_size / downsampling`` cells wide; subclasses add a decoder and its loss."""

    def __init__(self, cfg: Any, encoder: EncoderConfig) -> None:
        super().__init__()
        self.cfg = cfg
        # a TorchScript trace after Autoencoder.freeze_for_inference, without the Encoder's cfg
        self.encoder: Encoder | torch.jit.ScriptModule = Encoder(encoder)
        self._encoder_cfg = encoder

    @property
    def image_size(self) -> int:
        return self.cfg.image_size

    @property
    def latent_shape(self) -> tuple[int, int, int]:
        h = self.cfg.image_size // self._encoder_cfg.downsampling
        return (self._encoder_cfg.latent_channels, h, h)

    def encode(self, x: torch.Tensor) -> torch.Tensor:
        """(B, 3, H, W) in [-1, 1] -> latents (B, C, h, w)."""
        return self.encoder(x)

    def encoder_parameters(self) -> list[nn.Parameter]:
        return list(self.encoder.parameters())

    def prepare(self, frames: torch.Tensor) -> None:
        pass


def encode_views(codec: Codec, x: torch.Tensor, views: int) -> torch.Tensor:
    """Frames of ``views`` views stacked along the channels (B, 3V, H, W) -> their latents
    stacked alike (B, V*C, h, w), every view encoded by the one ``codec`` (in one batch)."""
    if views == 1:
        return codec.encode(x)
    b, _, h, w = x.shape
    z = codec.encode(x.reshape(b * views, 3, h, w))
    return z.reshape(b, views * z.shape[1], *z.shape[2:])


def decode_views(codec: Codec, z: torch.Tensor, views: int, noise: torch.Tensor | None = None, jumps: int = 1,
                 generator: torch.Generator | None = None) -> torch.Tensor:
    """Latents of ``views`` views stacked along the channels (B, V*C, h, w) -> the views'
    images stacked alike (B, 3V, H, W), each view decoded alone (in one batch); ``noise``
    (B, 3V, H, W) for a stochastic codec, as :meth:`Codec.decode` takes it."""
    if views == 1:
        return codec.decode(z, noise, jumps, generator)
    b, c = z.shape[:2]
    zz = z.reshape(b * views, c // views, *z.shape[2:]).contiguous(memory_format=torch.channels_last)
    nn_ = None if noise is None else noise.reshape(b * views, 3, *noise.shape[2:])
    x = codec.decode(zz, nn_, jumps, generator)
    return x.reshape(b, views * 3, *x.shape[2:])


def reconstruct(codec: Codec, x: torch.Tensor, jumps: int = 1, chunk: int = 64) -> torch.Tensor:
    """Encode then decode (B, 3, H, W) images in chunks; chunk i's decoder noise is seeded
    by its first index, so results do not depend on what else is in the batch."""
    parts = []
    for i in range(0, len(x), chunk):
        z = codec.encode(x[i:i + chunk])
        parts.append(codec.decode(z, None, jumps, torch.Generator(x.device).manual_seed(i)))
    return torch.cat(parts)
