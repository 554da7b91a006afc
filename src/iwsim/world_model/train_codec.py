"""Stage 1 training: any codec (``iwsim train ae``) and stage 3, a world model's decoder
fine-tuned on noised latents (``iwsim train decoder-finetune``), for the generic loop.
The codec supplies its own loss and per-step randomness (:mod:`iwsim.world_model.codecs.base`)."""

from __future__ import annotations

import dataclasses
import logging
from dataclasses import dataclass, field
from pathlib import Path

import imageio.v2 as imageio
import numpy as np
import torch
from torch import nn

from iwsim.core import trainer
from iwsim.core.checkpoint import resolve_checkpoint
from iwsim.core.config import to_dict
from iwsim.core.errors import InputError
from iwsim.core.metrics import psnr, ssim
from iwsim.data.frames import FrameSource, split_episodes, to_model, to_uint8
from iwsim.data.store import EpisodeStore, StoreError
from iwsim.diffusion.schedule import gaussian
from iwsim.world_model.codecs import build_codec, kind_of
from iwsim.world_model.codecs.base import KIND, Codec, reconstruct
from iwsim.world_model.model import WorldModel, complete_run_config

log = logging.getLogger(__name__)


@dataclass
class AEBatch:
    """x0 (B, 3, H, W) in [-1, 1]; the codec's per-sample training noise; for stage 3, the
    latent noise: its std (B,) and its draw (B, C, h, w)."""

    x0: torch.Tensor
    noise: dict[str, torch.Tensor] = field(default_factory=dict)
    z_std: torch.Tensor | None = None
    z_eps: torch.Tensor | None = None

    def to(self, device: torch.device) -> AEBatch:
        return AEBatch(self.x0.to(device), {k: v.to(device) for k, v in self.noise.items()},
                       *(None if v is None else v.to(device) for v in (self.z_std, self.z_eps)))


class AETrainModule(nn.Module):
    """forward(batch) -> the codec's decoder loss on its encoder's latents."""

    def __init__(self, codec: Codec) -> None:
        super().__init__()
        self.codec = codec

    def forward(self, batch: AEBatch) -> tuple[torch.Tensor, dict[str, float]]:
        with torch.set_grad_enabled(torch.is_grad_enabled() and not self.codec.cfg.freeze_encoder):
            z = self.codec.encode(batch.x0)
        if batch.z_eps is not None:  # stage 3: render imperfect (noised) latents cleanly
            assert batch.z_std is not None  # drawn with z_eps
            z = z + batch.z_std.view(-1, 1, 1, 1) * batch.z_eps
        return self.codec.loss(batch.x0, z, batch.noise)


class AETask:
    """Frames from the store's training episodes; held-out episodes for evaluation."""

    def __init__(self, cfg, data: str | Path, init: dict[str, torch.Tensor] | None = None) -> None:
        """``cfg``: the config of the codec to train (an ``AE_PRESETS`` entry); ``init``:
        start from these weights (stage 3) instead of fresh ones."""
        store = EpisodeStore.open(data, "r")
        if "img" not in store.keys:
            raise StoreError(f"{data} has no data/img frames to train on.")
        size = store.array("img").shape[1]
        if size != cfg.image_size:
            raise InputError(f"{data} holds {size}x{size} frames but the config expects {cfg.image_size}x"
                             f"{cfg.image_size}; pick a preset for {size} px or collect {cfg.image_size} px data.")
        if store.n_episodes < 2:
            raise InputError(f"{data} holds {store.n_episodes} episode(s); training needs at least 2 "
                             "(one is held out for evaluation).")
        self.cfg, self.kind = cfg, kind_of(cfg)
        self.train_episodes, self.heldout_episodes = split_episodes(store.n_episodes, cfg.holdout_every)
        self.train_frames = FrameSource(store, self.train_episodes)
        held = FrameSource(store, self.heldout_episodes)
        pick = np.linspace(0, len(held) - 1, min(cfg.eval_images, len(held))).round().astype(int)
        self.eval_frames = held.frames(pick)
        with torch.random.fork_rng():  # initial weights from the run's seed, global RNG untouched
            torch.manual_seed(cfg.train.seed)
            self.module = AETrainModule(build_codec(self.kind, to_dict(cfg)))
        if init is not None:
            self.module.codec.load_state_dict(init)
        else:  # what the codec's loss takes from the training frames (stage 3 has it in init)
            sample = np.linspace(0, len(self.train_frames) - 1, min(1024, len(self.train_frames))).round().astype(int)
            self.module.codec.prepare(to_model(self.train_frames.frames(sample)))
        if cfg.freeze_encoder:
            for p in self.module.codec.encoder_parameters():
                p.requires_grad_(False)

    def split(self) -> dict[str, list[int]]:
        return {"train_episodes": self.train_episodes, "heldout_episodes": self.heldout_episodes}

    def batch(self, step: int, generator: torch.Generator, part: slice, device: torch.device) -> AEBatch:
        b = self.cfg.train.batch_size
        codec = self.module.codec
        idx = torch.randint(0, len(self.train_frames), (b,), generator=generator)
        noise = {k: v[part] for k, v in codec.training_noise(b, generator).items()}
        x0 = to_model(self.train_frames.frames(idx[part].numpy()))
        lo, hi = self.cfg.latent_noise
        if hi <= 0:
            return AEBatch(x0, noise).to(device)
        # stage 3: latent noise of the dynamics' context noise, a std uniform in [lo, hi)
        # in the dynamics' standardised units
        z_std = (lo + (hi - lo) * torch.rand(b, generator=generator)) * self.cfg.latent_noise_scale
        z_eps = gaussian((b, *codec.latent_shape), generator)
        return AEBatch(x0, noise, z_std[part], z_eps[part]).to(device)

    @torch.no_grad()
    def evaluate(self, module: AETrainModule, step: int, out_dir: Path) -> dict[str, float]:
        codec = module.codec
        device = next(codec.parameters()).device
        out: dict[str, float] = {}
        x = to_model(self.eval_frames).to(device)
        recon = {}
        for k in self.cfg.eval_jumps:
            recon[k] = reconstruct(codec, x, k, chunk=64)
            a, b = (x + 1) / 2, (recon[k] + 1) / 2
            out[f"psnr_{k}jump"] = psnr(a, b).mean().item()
            out[f"ssim_{k}jump"] = ssim(a, b).mean().item()
        out_dir.mkdir(parents=True, exist_ok=True)
        first = min(self.cfg.eval_jumps)
        n = min(8, len(x))
        grid = np.concatenate([np.concatenate(list(to_uint8(x[:n])), axis=1),
                               np.concatenate(list(to_uint8(recon[first][:n])), axis=1)], axis=0)
        imageio.imwrite(out_dir / f"recon_{step:08d}.png", grid)
        return out

    def export(self, module: AETrainModule) -> dict[str, torch.Tensor]:
        return module.codec.state_dict()


def train_autoencoder(cfg, data: str | Path, out: str | Path, *, device: torch.device, force: bool = False,
                      progress: bool = True) -> dict[str, float]:
    """Train (or resume) stage 1, the codec that the config ``cfg`` is for (an
    ``AE_PRESETS`` entry), into the run directory ``out``."""
    task = AETask(cfg, data)
    config = {"kind": KIND, "codec": task.kind, "model": to_dict(cfg), "data": str(data), "split": task.split()}
    return trainer.train(task, cfg.train, Path(out), config, device=device, force=force, progress=progress,
                         complete=complete_run_config)


class DecoderFinetuneTask(AETask):
    """Stage 3 on a world model: its decoder learns to render noised latents; every
    checkpoint is the world model with the fine-tuned decoder."""

    def __init__(self, wm: WorldModel, cfg, data: str | Path) -> None:
        super().__init__(cfg, data, init=wm.codec.state_dict())
        self.wm = wm

    def world_model(self, codec: Codec) -> WorldModel:
        wm = self.wm
        return WorldModel(codec, wm.dynamics, wm.cfg, wm.action_low, wm.action_high, wm.latent_mean,
                          wm.latent_scale, wm.state_low, wm.state_high)

    def export(self, module: AETrainModule) -> dict[str, torch.Tensor]:
        return self.world_model(module.codec).export()


def finetune_decoder(world_model: str | Path, data: str | Path, out: str | Path, *, device: torch.device,
                     steps: int = 500, batch_size: int | None = None, lr: float = 1e-4,
                     latent_noise: tuple[float, float] | None = None, seed: int | None = None,
                     symmetric_foreground: bool = False, force: bool = False, progress: bool = True
                     ) -> dict[str, float]:
    """Stage 3: fine-tune a world model's decoder on noised latents (``iwsim train
    decoder-finetune``), at a lower learning rate, with the encoder frozen. The noise is
    the stage-2 context noise (``context_sigma`` stds in the dynamics' standardised units,
    unless ``latent_noise`` says otherwise), so the decoder learns to render latents as
    imperfect as predicted ones. ``symmetric_foreground`` weights the foreground the decoder
    paints as the target's (a conv codec's ``foreground_symmetric``)."""
    src = resolve_checkpoint(world_model)
    wm = WorldModel.load(src, device)
    base = wm.codec.cfg
    train = dataclasses.replace(base.train, steps=steps, lr=lr, warmup_steps=min(50, steps), lr_decay="cosine",
                                batch_size=batch_size or base.train.batch_size,
                                seed=base.train.seed if seed is None else seed,
                                eval_every=min(100, steps), checkpoint_every=min(100, steps))
    noise = wm.cfg.context_sigma if latent_noise is None else latent_noise  # stds, standardised units
    cfg = dataclasses.replace(base, train=train, freeze_encoder=True, latent_noise=tuple(noise),
                              latent_noise_scale=wm.latent_scale)
    if symmetric_foreground:
        if not getattr(base, "foreground_weight", 0) > 0:
            raise InputError(f"{src}: --symmetric-foreground needs a codec whose loss weights the foreground "
                             f"(a conv codec with foreground_weight > 0).")
        cfg = dataclasses.replace(cfg, foreground_symmetric=True)
    task = DecoderFinetuneTask(wm, cfg, data)
    config = {**task.world_model(task.module.codec).describe(), "data": str(data), "finetuned_from": str(src),
              "split": task.split()}
    return trainer.train(task, cfg.train, Path(out), config, device=device, force=force, progress=progress,
                         complete=complete_run_config)
