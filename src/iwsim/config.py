"""Configs as frozen dataclasses, named presets in Python, and their JSON round trip.

A preset is a complete config; command-line flags override single fields of it
(``dataclasses.replace``). The resolved config is written to the run directory and into
every checkpoint.
"""

from __future__ import annotations

import dataclasses
import typing
from dataclasses import dataclass, field
from typing import Any, TypeVar

from iwsim.diffusion.schedule import ScheduleConfig
from iwsim.models.autoencoder import DecoderConfig, EncoderConfig
from iwsim.models.dynamics import DynamicsConfig

T = TypeVar("T")


@dataclass(frozen=True)
class TrainConfig:
    """The generic loop's knobs (every stage uses this)."""

    steps: int = 10_000
    batch_size: int = 32  # global: split over DDP ranks
    lr: float = 3e-4
    warmup_steps: int = 200  # linear warm-up ...
    lr_decay: str = "cosine"  # ... then "cosine" to 0 at `steps`, or "constant"
    betas: tuple[float, float] = (0.9, 0.99)
    weight_decay: float = 0.0
    grad_clip: float = 1.0
    ema_decay: float = 0.999
    log_every: int = 25
    eval_every: int = 500
    checkpoint_every: int = 500
    seed: int = 0


@dataclass(frozen=True)
class AEConfig:
    """Stage 1: encoder + consistency decoder."""

    image_size: int = 64
    encoder: EncoderConfig = field(default_factory=EncoderConfig)
    decoder: DecoderConfig = field(default_factory=DecoderConfig)
    schedule: ScheduleConfig = field(default_factory=ScheduleConfig)
    train: TrainConfig = field(default_factory=TrainConfig)
    top_fraction: float = 0.5  # share of training jumps that start at pure noise, like decoding
    holdout_every: int = 20  # episode i is held out iff i % 20 == 19
    eval_images: int = 256  # held-out frames scored at each evaluation
    eval_jumps: tuple[int, ...] = (1, 2, 3)
    # Stage 3 (decoder fine-tuning): a frozen encoder, and the decoder's latent condition
    # noised as z + latent_noise_scale * b_t * eps with t uniform in latent_noise [lo, hi).
    freeze_encoder: bool = False
    latent_noise: tuple[int, int] = (0, 0)
    latent_noise_scale: float = 1.0


def _ae(image_size: int, channels: tuple[int, ...], blocks: int, emb: int, **train: Any) -> AEConfig:
    return AEConfig(
        image_size=image_size,
        encoder=EncoderConfig(channels=channels, blocks_per_level=blocks),
        decoder=DecoderConfig(channels=channels, blocks_per_level=blocks, emb_dim=emb),
        train=TrainConfig(**train),
    )


AE_PRESETS: dict[str, AEConfig] = {
    # Seconds on a CPU: for tests.
    "tiny": dataclasses.replace(
        _ae(64, (8, 8, 8), 1, 16, steps=6, batch_size=4, warmup_steps=2, log_every=1, eval_every=3,
            checkpoint_every=3, ema_decay=0.9),
        eval_images=8,
    ),
    # The CPU default: 2200 steps take 45-50 minutes on 2 CPU cores; it passes 32 dB near step 1000.
    "pusht-64": _ae(64, (16, 32, 64), 1, 128, steps=2200, batch_size=32, lr=1e-3, warmup_steps=100,
                    eval_every=250, checkpoint_every=250, ema_decay=0.995),
    # Paper scale (128 px, 64 base channels), for GPUs.
    "pusht-128": _ae(128, (64, 128, 256), 2, 256, steps=200_000, batch_size=64, lr=2e-4, warmup_steps=2000,
                     eval_every=5000, checkpoint_every=5000, ema_decay=0.9999),
}


@dataclass(frozen=True)
class DynamicsStageConfig:
    """Stage 2: the latent dynamics on a frozen stage-1 autoencoder."""

    dynamics: DynamicsConfig = field(default_factory=DynamicsConfig)
    schedule: ScheduleConfig = field(default_factory=ScheduleConfig)
    train: TrainConfig = field(default_factory=TrainConfig)
    seq_len: int = 12  # L: a training sequence is L context frames and the L frames they predict
    context_levels: tuple[int, int] = (1, 100)  # training context noise levels, uniform in [lo, hi)
    context_level: int = 15  # the level context frames are labelled with at inference
    jumps: int = 1  # consistency jumps per predicted frame at inference
    # "consistency" (ours); the baselines: "edm" (multi-step diffusion, DIAMOND-style) and
    # "regression" (a deterministic next-latent predictor, DINO-WM-style); see VARIANTS.
    objective: str = "consistency"
    euler_steps: int = 3  # the "edm" objective's Euler steps per predicted frame
    top_fraction: float = 0.5  # share of training jumps from level T - 1, where inference starts
    zero_fraction: float = 0.5  # share of training jumps that land on level 0, as inference does
    start_fraction: float = 0.1  # share of sequences that start at an episode's first frame
    holdout_every: int = 20
    eval_episodes: int = 4  # held-out episodes rolled out open-loop at each evaluation
    eval_steps: int = 64


def _dyn(window: int, channels: tuple[int, int], heads: int, emb: int, seq_len: int, **train: Any
         ) -> DynamicsStageConfig:
    return DynamicsStageConfig(dynamics=DynamicsConfig(window=window, channels=channels, heads=heads, emb_dim=emb),
                               seq_len=seq_len, train=TrainConfig(**train))


DYNAMICS_PRESETS: dict[str, DynamicsStageConfig] = {
    # Seconds on a CPU: for tests.
    "tiny": dataclasses.replace(
        _dyn(4, (8, 16), 2, 16, 5, steps=6, batch_size=4, warmup_steps=2, log_every=1, eval_every=3,
             checkpoint_every=3, ema_decay=0.9),
        eval_episodes=2, eval_steps=6,
    ),
    # The CPU default for 64 px latents (4 x 16 x 16): trains in about 90 minutes on 2 cores.
    "pusht-64": dataclasses.replace(
        _dyn(8, (64, 128), 4, 128, 10, steps=1500, batch_size=12, lr=5e-4, warmup_steps=100, eval_every=250,
             checkpoint_every=250, ema_decay=0.995),
        top_fraction=0.9,  # inference is one jump from pure noise: train mostly that
    ),
}


OBJECTIVES = ("consistency", "edm", "regression")

# The baselines of the benchmark: the same network, data and budget as ours, trained
# differently (``iwsim train dynamics --variant NAME``).
VARIANTS: dict[str, dict[str, Any]] = {
    "ours": {},
    # Ablation: ours without context-noise augmentation (clean context in training and inference).
    "no-context-noise": {"context_levels": (0, 1), "context_level": 0},
    # Next latent by MSE regression from a clean context (like DINO-WM's predictor).
    "deterministic": {"objective": "regression", "context_levels": (0, 1), "context_level": 0},
    # EDM denoiser sampled by 3 Euler steps (like DIAMOND), with our context noise.
    "diffusion": {"objective": "edm"},
}


def variant(cfg: DynamicsStageConfig, name: str) -> DynamicsStageConfig:
    """``cfg`` changed into the named benchmark variant (see VARIANTS)."""
    if name not in VARIANTS:
        raise ValueError(f"unknown variant {name!r}; expected one of {', '.join(VARIANTS)}.")
    return dataclasses.replace(cfg, **VARIANTS[name])


def to_dict(cfg: Any) -> dict[str, Any]:
    """A config dataclass as plain JSON-ready data."""
    return dataclasses.asdict(cfg)


def from_dict(cls: type[T], data: dict[str, Any]) -> T:
    """Rebuild a (nested) config dataclass from ``to_dict`` output; unknown keys are errors."""
    hints = typing.get_type_hints(cls)
    names = {f.name for f in dataclasses.fields(cls)}
    unknown = set(data) - names
    if unknown:
        raise ValueError(f"unknown {cls.__name__} fields {sorted(unknown)}.")
    kwargs = {}
    for name, value in data.items():
        hint = hints[name]
        if dataclasses.is_dataclass(hint):
            value = from_dict(hint, value)
        elif typing.get_origin(hint) is tuple:
            value = tuple(value)
        kwargs[name] = value
    return cls(**kwargs)
