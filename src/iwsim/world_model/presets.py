"""The world model's configs and named presets: the codec (stage 1) and the dynamics (stage 2).

A preset is a complete config; command-line flags override single fields of it
(``dataclasses.replace``). A new latent representation is a codec file plus a preset here.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from typing import Any

from iwsim.core.config import TrainConfig
from iwsim.core.errors import InputError
from iwsim.diffusion.schedule import ScheduleConfig
from iwsim.world_model import objectives
from iwsim.world_model.codecs.consistency_net import DecoderConfig, EncoderConfig
from iwsim.world_model.codecs.conv import ConvCodecConfig
from iwsim.world_model.dynamics import DynamicsConfig


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
    # noised as z + latent_noise_scale * sigma * eps with sigma uniform in latent_noise [lo, hi).
    freeze_encoder: bool = False
    latent_noise: tuple[float, float] = (0.0, 0.0)
    latent_noise_scale: float = 1.0


def _ae(image_size: int, channels: tuple[int, ...], blocks: int, emb: int, **train: Any) -> AEConfig:
    return AEConfig(
        image_size=image_size,
        encoder=EncoderConfig(channels=channels, blocks_per_level=blocks),
        decoder=DecoderConfig(channels=channels, blocks_per_level=blocks, emb_dim=emb),
        train=TrainConfig(**train),
    )


AE_PRESETS: dict[str, AEConfig | ConvCodecConfig] = {
    # Seconds on a CPU: for tests.
    "tiny": dataclasses.replace(
        _ae(64, (8, 8, 8), 1, 16, steps=6, batch_size=4, warmup_steps=2, log_every=1, eval_every=3,
            checkpoint_every=3, ema_decay=0.9),
        eval_images=8,
    ),
    # The CPU default, sized to train on 2 CPU cores in under an hour (bench/results/ae.md).
    "pusht-64": _ae(64, (16, 32, 64), 1, 128, steps=2200, batch_size=32, lr=1e-3, warmup_steps=100,
                    eval_every=250, checkpoint_every=250, ema_decay=0.995),
    # Paper scale (128 px, 64 base channels), for GPUs.
    "pusht-128": _ae(128, (64, 128, 256), 2, 256, steps=200_000, batch_size=64, lr=2e-4, warmup_steps=2000,
                     eval_every=5000, checkpoint_every=5000, ema_decay=0.9999),
    # The deterministic conv-ae codec (iwsim.world_model.codecs.conv), x2 downsampling: 4 x 32 x 32
    # latents at 64 px. "tiny-conv" is for tests.
    "tiny-conv": ConvCodecConfig(64, channels=(8, 8), eval_images=8, train=TrainConfig(
        steps=6, batch_size=4, warmup_steps=2, log_every=1, eval_every=3, checkpoint_every=3, ema_decay=0.9)),
    "conv-x2-64": ConvCodecConfig(64, channels=(32, 64), blocks_per_level=2, train=TrainConfig(
        steps=1500, batch_size=32, lr=1e-3, warmup_steps=100, eval_every=250, checkpoint_every=250,
        ema_decay=0.995)),
    # Coarse codecs: a decoder that holds the objects' shapes in its weights, fed by few
    # latent cells (x8: 8 x 8 x 8 latents; x16: 16 x 4 x 4), trained on latents noised like
    # stage 2's context (std up to 0.3) and with the small things weighted up, so that the
    # dynamics runs on far fewer cells (what that costs and gains: bench/results/ablations.md).
    "conv-x8-64": ConvCodecConfig(
        64, latent_channels=8, channels=(16, 32, 64, 128), blocks_per_level=2, foreground_weight=10.0,
        latent_noise=(0.0, 0.3), train=TrainConfig(steps=1000, batch_size=32, lr=1e-3, warmup_steps=100,
                                                    eval_every=250, checkpoint_every=250, ema_decay=0.995)),
    # x4 cells (4 x 4 px) for scenes whose objects are smaller than an x8 cell, such as a
    # pile of 3 px pieces (bench/pile_codec.py measures how many pieces each codec keeps).
    "conv-x4-64": ConvCodecConfig(
        64, latent_channels=8, channels=(16, 32, 64), blocks_per_level=2, foreground_weight=10.0,
        latent_noise=(0.0, 0.3), train=TrainConfig(steps=1000, batch_size=32, lr=1e-3, warmup_steps=100,
                                                    eval_every=250, checkpoint_every=250, ema_decay=0.995)),
    # x4's latent size (2048 numbers) in x8's 8 x 8 cells, 32 channels each, so that
    # the dynamics keeps x8's cost (its convolutions and attention run on the cells).
    "conv-x8c32-64": ConvCodecConfig(
        64, latent_channels=32, channels=(16, 32, 64, 128), blocks_per_level=2, foreground_weight=10.0,
        latent_noise=(0.0, 0.3), train=TrainConfig(steps=1000, batch_size=32, lr=1e-3, warmup_steps=100,
                                                    eval_every=250, checkpoint_every=250, ema_decay=0.995)),
    "conv-x16-64": ConvCodecConfig(
        64, latent_channels=16, channels=(16, 32, 64, 128, 128), blocks_per_level=2, foreground_weight=10.0,
        latent_noise=(0.0, 0.3), train=TrainConfig(steps=1000, batch_size=32, lr=1e-3, warmup_steps=100,
                                                    eval_every=250, checkpoint_every=250, ema_decay=0.995)),
}


@dataclass(frozen=True)
class DynamicsStageConfig:
    """Stage 2: the latent dynamics on a frozen stage-1 autoencoder."""

    dynamics: DynamicsConfig = field(default_factory=DynamicsConfig)
    schedule: ScheduleConfig = field(default_factory=ScheduleConfig)
    train: TrainConfig = field(default_factory=TrainConfig)
    # "consistency" (ours); the baselines: "edm" (multi-step diffusion, DIAMOND-style) and
    # "regression" (a deterministic next-latent predictor, DINO-WM-style); see VARIANTS
    # and iwsim.diffusion.objectives.
    objective: str = "consistency"
    predict_delta: bool = True  # generate the change from the newest context latent, not the latent
    # Context noise in the units the network sees (standardised latents): the context of a
    # training prediction gets Gaussian noise of a std drawn uniformly from this range, and
    # is told that std; at inference the context is labelled with ``context_label``.
    context_sigma: tuple[float, float] = (0.0, 0.3)
    context_label: float = 0.1
    jumps: int = 1  # consistency jumps per predicted frame at inference
    euler_steps: int = 3  # the "edm" objective's Euler steps per predicted frame
    top_fraction: float = 1.0  # share of training jumps from level T - 1, where inference starts
    zero_fraction: float = 1.0  # share of training jumps that land on level 0, as inference does
    # Training on the model's own predictions (a curriculum): from training step k on,
    # each sequence unrolls n predictions, each from a context holding the earlier ones.
    unroll: tuple[tuple[int, int], ...] = ((0, 2), (200, 4), (500, 8))
    unroll_grad: bool = True  # the gradient flows through fed-back predictions (else they are detached)
    unroll_grad_every: int = 0  # with unroll_grad, cut it every this many predictions (0: never; TBPTT)
    changed_weight: float = 4.0  # extra loss weight on latent cells that change (1 + this)
    changed_threshold: float = 0.1  # a cell changes when a channel moves by more (standardised)
    # Inference (predict_delta): a predicted change whose largest channel in a cell stays
    # under this (standardised units) is taken as no change, so that what nothing touches
    # cannot creep by a small systematic change each step (the idle drift). 0: off.
    delta_deadband: float = 0.0
    # Inference (predict_delta): a scene at rest stays at rest. When the executed setpoint
    # holds still and the newest latent changed by less than this (a cell's largest channel,
    # standardised), the next latent is the newest: in the training data such steps are
    # almost always followed by no change (bench/rest_stats.py counts them); without it, a
    # still scene creeps (the idle drift). 0: off.
    rest_threshold: float = 0.0
    # Inference: bf16 autocast (WorldModel.bf16) where the hardware has it, else float32:
    # it pays for large batches, not for one stream (bench/results/speed).
    inference_bf16: bool = False
    start_fraction: float = 0.1  # share of sequences that start at an episode's first frame
    # The camera views the model sees, as the store names them (iwsim.data.views; the data
    # decides): each view is encoded by the one codec and the views' latents are stacked
    # along the channels, so the dynamics predicts the joint next state of every view in
    # one pass, and each view is decoded alone.
    cameras: tuple[str, ...] = ("top",)
    # The robot's own state (the store's data/state, e.g. where T-push's pushers are): the
    # network takes it and predicts it each step (Dynamics.predict_state), each prediction
    # fed back, supervised by an MSE on the normalised state weighted by state_weight.
    predict_state: bool = False
    state_weight: float = 1.0
    # Contact in the state's loss: where the recorded state stands more than
    # state_contact_gap (normalised units, any coordinate) from the one its setpoint sets
    # (Dynamics.setpoint_state: a pusher held back by the block), that step's state error
    # counts 1 + state_contact_weight times. In T-push's broad data a fifth of the steps
    # stand beyond the default gap (9 mm), 4% beyond 20 mm, and a head trained without the
    # weight puts a pressing pusher at its setpoint, inside the block (bench/results/
    # ablations.md). 0: off.
    state_contact_weight: float = 0.0
    state_contact_gap: float = 0.04
    holdout_every: int = 20
    eval_episodes: int = 4  # held-out episodes rolled out open-loop at each evaluation
    eval_steps: int = 64

    def unroll_at(self, step: int) -> int:
        """Predictions unrolled per sequence at training step ``step``."""
        return max(n for k, n in self.unroll if k <= step)


def _dyn(context: int, channels: int, blocks: int, heads: int, emb: int, action_channels: int,
         unroll: tuple[tuple[int, int], ...], **train: Any) -> DynamicsStageConfig:
    return DynamicsStageConfig(
        dynamics=DynamicsConfig(context=context, channels=channels, blocks=blocks, heads=heads, emb_dim=emb,
                                action_channels=action_channels),
        unroll=unroll, train=TrainConfig(**train))


DYNAMICS_PRESETS: dict[str, DynamicsStageConfig] = {
    # Seconds on a CPU: for tests.
    "tiny": dataclasses.replace(
        _dyn(2, 8, 2, 2, 16, 2, ((0, 1), (3, 2)), steps=6, batch_size=4, warmup_steps=2, log_every=1,
             eval_every=3, checkpoint_every=3, ema_decay=0.9),
        eval_episodes=2, eval_steps=6,
    ),
    # The CPU default for 64 px latents (4 x 16 x 16): about 50 minutes on one core beside
    # another 1-thread job (the shipped checkpoint's run).
    "pusht-64": _dyn(3, 64, 8, 4, 128, 8, ((0, 2), (200, 4), (500, 8), (1100, 12)), steps=1400, batch_size=16,
                     lr=1e-3, warmup_steps=50, eval_every=250, checkpoint_every=250, ema_decay=0.995),
}


OBJECTIVES = tuple(objectives.OBJECTIVES)

# The baselines and ablations of the benchmark: the same network, data and budget as ours,
# trained differently (``iwsim train dynamics --variant NAME``). A "dynamics" entry
# changes fields of the network's config.
VARIANTS: dict[str, dict[str, Any]] = {
    "ours": {},
    # Ablation: ours without context-noise augmentation (clean context in training and inference).
    "no-context-noise": {"context_sigma": (0.0, 0.0), "context_label": 0.0},
    # Next latent by MSE regression from a clean context (like DINO-WM's predictor).
    "deterministic": {"objective": "regression", "context_sigma": (0.0, 0.0), "context_label": 0.0},
    # EDM denoiser sampled by 3 Euler steps (like DIAMOND), with our context noise.
    "diffusion": {"objective": "edm"},
    # Ablations of the action pathway, the unrolled training and the change parameterisation.
    "film-actions": {"dynamics": {"spatial_actions": False, "positional_actions": False, "action_film": True}},
    "no-points": {"dynamics": {"positional_actions": False}},
    "no-unroll": {"unroll": ((0, 1),)},
    "no-delta": {"predict_delta": False},
    # Levers for rigid objects: a longer window (the paper's is 10 frames), and
    # longer unrolls with the gradient cut every 8 predictions.
    "window-6": {"dynamics": {"context": 6}},
    "long-unroll": {"unroll": ((0, 2), (200, 4), (500, 8), (800, 16), (1100, 24)), "unroll_grad_every": 8},
    # The dynamics' middle blocks at half the latent's resolution (a one-level U-Net, as the
    # paper's): for fine latents, whose objects span many cells.
    "unet": {"dynamics": {"down": 1}},
    # The robot's own state taken, predicted and fed back (the store's data/state).
    "state": {"predict_state": True},
    # ... with the steps where contact holds a pusher back weighted 5x in the state's loss.
    "state-contact": {"predict_state": True, "state_contact_weight": 4.0},
    # Real sampling: one jump from pure noise learns the expected next latent (the noise is
    # ignored), which averages what contact may do; trained on jumps from every level (half
    # from the top, half to 0, as the decoder is) and sampled in 3 jumps (999, 666, 333, 0),
    # the noise picks one outcome. A fine-tune may add it to a 1-jump model.
    "sampled": {"top_fraction": 0.5, "zero_fraction": 0.5, "jumps": 3},
    # ... trained on jumps from every level, sampled in one jump as ours is.
    "all-levels": {"top_fraction": 0.5, "zero_fraction": 0.5},
    # The fed-back predictions carry no gradient: each prediction learns from its context as
    # it is, not how to make the next one's easier.
    "detached-unroll": {"unroll_grad": False},
    # Twice the context noise (stds up to 0.6 instead of 0.3): a harder context to predict from.
    "context-wide": {"context_sigma": (0.0, 0.6)},
}
# What a fine-tune (--init) may add to a trained model: the others change its objective or network.
FINE_TUNE_VARIANTS = ("ours", "state", "state-contact", "sampled", "all-levels", "detached-unroll",
                      "context-wide")
# The fields of those variants a fine-tune takes from them where they set them (otherwise the model's own).
FINE_TUNE_FIELDS = ("top_fraction", "zero_fraction", "jumps", "unroll_grad", "context_sigma")


def variant(cfg: DynamicsStageConfig, name: str) -> DynamicsStageConfig:
    """``cfg`` changed into the named benchmark variant (see VARIANTS); ``"a+b"`` applies
    variant a, then b (e.g. ``long-unroll+deterministic``: a baseline trained like ours)."""
    for part in name.split("+"):
        if part not in VARIANTS:
            raise InputError(f"unknown variant {part!r}; expected one of {', '.join(VARIANTS)} (or several "
                             "joined by '+').")
        changes = dict(VARIANTS[part])
        if "dynamics" in changes:
            changes["dynamics"] = dataclasses.replace(cfg.dynamics, **changes["dynamics"])
        cfg = dataclasses.replace(cfg, **changes)
    return cfg
