"""Stage 2 training: the latent dynamics on the frozen stage-1 encoder (``iwsim train dynamics``).

A training sequence is L + 1 consecutive frames of one episode. Its first L latents are
the context, each noised to its own small level drawn from ``context_levels`` (never
denoised: the model must cope with imperfect context, its own predictions at inference);
the last L latents are the targets, each noised to its own level t and jumped to s by the
consistency objective. The attention mask of :mod:`iwsim.models.dynamics` lets target
k + 1 see only the context up to k (N - 1 frames back), so one pass trains L predictions.

The benchmark's baselines train in the same way with another ``objective`` (see
``iwsim.config.VARIANTS``): EDM denoising of the targets (sampled by Euler steps) or
plain MSE regression of the next latent from zeros, each with its own context noise.

Every checkpoint of a dynamics run is a complete world model (autoencoder + dynamics +
action normalisation + config), loadable with :meth:`iwsim.WorldModel.load`.
"""

from __future__ import annotations

import logging
import os
from dataclasses import dataclass, replace
from pathlib import Path

import imageio.v2 as imageio
import numpy as np
import torch
from safetensors import safe_open
from safetensors.torch import save_file
from torch import nn
from tqdm import tqdm

from iwsim.autoencoder import Autoencoder
from iwsim.config import OBJECTIVES, DynamicsStageConfig
from iwsim.data.frames import split_episodes, to_model, to_uint8
from iwsim.data.store import EpisodeStore, StoreError
from iwsim.diffusion import edm
from iwsim.diffusion.consistency import jump_loss, sample_levels
from iwsim.diffusion.schedule import Schedule, gaussian
from iwsim.eval.metrics import psnr
from iwsim.models.dynamics import Dynamics, sequence_layout
from iwsim.training import trainer
from iwsim.training.checkpoint import CheckpointError, last_checkpoint
from iwsim.world_model import KIND, WorldModel, level_input, scale_actions

log = logging.getLogger(__name__)


def resolve_checkpoint(path: str | Path) -> Path:
    """A checkpoint directory, or a run directory (its ``checkpoints/last``)."""
    path = Path(path)
    if (path / "model.safetensors").is_file():
        return path
    last = last_checkpoint(path / "checkpoints")
    if last is None:
        raise CheckpointError(f"{path} is neither a checkpoint directory (model.safetensors + config.json) "
                              "nor a run directory with checkpoints.")
    return last


@dataclass
class DynBatch:
    """Latents z (B, L+1, C, h, w); normalised producing actions (B, L+1, A) and whether
    they are known (B, L+1); context levels (B, L) and noise (B, L, C, h, w); target
    levels t, s (B, L), or sigmas (B, L), and noise (B, L, C, h, w)."""

    z: torch.Tensor
    actions: torch.Tensor
    known: torch.Tensor
    ctx_levels: torch.Tensor
    ctx_eps: torch.Tensor
    t: torch.Tensor
    s: torch.Tensor
    eps: torch.Tensor
    sigma: torch.Tensor  # (B, L) EDM noise levels (the "edm" objective's targets)

    def to(self, device: torch.device) -> DynBatch:
        return DynBatch(*(v.to(device) for v in vars(self).values()))


class DynamicsTrainModule(nn.Module):
    """forward(batch) -> the loss of the L targets of each sequence under the config's
    objective: the consistency jump loss (ours), EDM denoising or MSE regression."""

    def __init__(self, dynamics: Dynamics, schedule: Schedule, objective: str = "consistency") -> None:
        super().__init__()
        if objective not in OBJECTIVES:
            raise ValueError(f"unknown objective {objective!r}; expected one of {', '.join(OBJECTIVES)}.")
        self.dynamics, self.schedule, self.objective = dynamics, schedule, objective

    def forward(self, batch: DynBatch) -> tuple[torch.Tensor, dict[str, float]]:
        b, l1 = batch.z.shape[:2]
        n = l1 - 1
        times, is_ctx = sequence_layout(n, batch.z.device)
        ctx = self.schedule.noise(batch.z[:, :n].flatten(0, 1), batch.ctx_levels.flatten(),
                                  batch.ctx_eps.flatten(0, 1)).unflatten(0, (b, n))
        ctx_in = level_input(self.objective, self.schedule, batch.ctx_levels)
        actions = torch.cat([batch.actions[:, :n], batch.actions[:, 1:]], 1)
        known = torch.cat([batch.known[:, :n], batch.known[:, 1:]], 1)

        def net(x_t: torch.Tensor, t: torch.Tensor, s: torch.Tensor, cond: None = None) -> torch.Tensor:
            x = torch.cat([ctx, x_t.unflatten(0, (b, n))], 1)
            levels = torch.cat([ctx_in, t.view(b, n)], 1)
            jump_to = torch.cat([ctx_in, s.view(b, n)], 1)
            v, _ = self.dynamics(x, levels, jump_to, actions, known, times, is_ctx)
            return v[:, n:].flatten(0, 1)

        x0, eps = batch.z[:, 1:].flatten(0, 1), batch.eps.flatten(0, 1)
        if self.objective == "regression":
            t = torch.full((b * n,), float(self.schedule.T), device=x0.device)
            per = ((net(torch.zeros_like(x0), t, torch.zeros_like(t)) - x0) ** 2).mean((1, 2, 3))
            return per.mean(), {}
        if self.objective == "edm":
            sigma = batch.sigma.flatten()
            x_noisy = x0 + sigma.view(-1, 1, 1, 1) * eps
            _, c_in, _ = edm.precondition(sigma, x0)
            c = edm.noise_input(sigma)
            per = edm.loss(net(c_in * x_noisy, c, c), x0, x_noisy, sigma)
            return per.mean(), {}
        per = jump_loss(net, self.schedule, x0, None, batch.t.flatten(), batch.s.flatten(), eps)
        top = batch.t.flatten() == self.schedule.T - 1
        parts = {"loss_from_noise": per[top].mean().item() if top.any() else float("nan")}
        return per.mean(), parts


class DynamicsTask:
    """Latents of every frame of the store (encoded once), sequences from the training
    episodes, open-loop rollouts of held-out episodes for evaluation."""

    def __init__(self, cfg: DynamicsStageConfig, data: str | Path, ae_path: str | Path,
                 device: torch.device = torch.device("cpu"), progress: bool = True,
                 latent_cache: Path | None = None) -> None:
        store = EpisodeStore.open(data, "r")
        for key in ("img", "action"):
            if key not in store.keys:
                raise StoreError(f"{data} has no data/{key} to train the dynamics on.")
        self.ae_path = resolve_checkpoint(ae_path)
        self.ae = Autoencoder.load(self.ae_path, device)
        size = store.array("img").shape[1]
        if size != self.ae.image_size:
            raise ValueError(f"{data} holds {size}x{size} frames but the autoencoder {self.ae_path} expects "
                             f"{self.ae.image_size}x{self.ae.image_size}.")
        actions = np.asarray(store.array("action")[:], dtype=np.float32)
        if actions.ndim != 2:
            raise StoreError(f"{data}: data/action must be (frames, action_dim), got {actions.shape}.")
        # The action size follows the data.
        cfg = replace(cfg, dynamics=replace(cfg.dynamics, action_dim=actions.shape[1],
                                            latent_channels=self.ae.cfg.encoder.latent_channels))
        if store.n_episodes < 2:
            raise ValueError(f"{data} holds {store.n_episodes} episode(s); training needs at least 2 "
                             "(one is held out for evaluation).")
        self.cfg = cfg
        self.train_episodes, self.heldout_episodes = split_episodes(store.n_episodes, cfg.holdout_every)
        ends = store.episode_ends.astype(np.int64)
        starts = np.concatenate([[0], ends[:-1]])
        n = cfg.seq_len
        train_long = [e for e in self.train_episodes if ends[e] - starts[e] >= n + 1]
        if not train_long:
            raise ValueError(f"no training episode of {data} has the {n + 1} frames a sequence needs "
                             f"(seq_len {n}); lower seq_len or collect longer episodes.")
        self.seq_starts = torch.from_numpy(np.concatenate([np.arange(starts[e], ends[e] - n) for e in train_long]))
        self.episode_starts = torch.from_numpy(starts[train_long])
        train_idx = np.concatenate([np.arange(starts[e], ends[e]) for e in self.train_episodes])
        low, high = actions[train_idx].min(0), actions[train_idx].max(0)
        span = np.maximum(high - low, 1e-3)  # a constant action dimension still normalises
        self.action_low, self.action_high = (low + high) / 2 - span / 2, (low + high) / 2 + span / 2
        self.actions = scale_actions(torch.from_numpy(actions), torch.from_numpy(self.action_low),
                                     torch.from_numpy(self.action_high))
        self.known = torch.ones(len(actions), dtype=torch.float32)
        self.known[torch.from_numpy(starts)] = 0.0
        self.latents = self._encode(store, device, progress, latent_cache)
        # Standardisation of the latents for the dynamics (see WorldModel): per-element
        # mean over the training frames, and the RMS of the per-element standard deviation.
        train_z = self.latents[torch.from_numpy(train_idx)]
        self.latent_mean = train_z.mean(0)
        self.latent_scale = float(train_z.var(0).mean().sqrt().clamp_min(1e-6))
        self.store, self.starts, self.ends = store, starts, ends
        with torch.random.fork_rng():  # initial weights from the run's seed, global RNG untouched
            torch.manual_seed(cfg.train.seed)
            self.module = DynamicsTrainModule(Dynamics(cfg.dynamics), Schedule(cfg.schedule), cfg.objective)

    @torch.no_grad()
    def _encode(self, store: EpisodeStore, device: torch.device, progress: bool, cache: Path | None,
                chunk: int = 512) -> torch.Tensor:
        """Latents of every frame of the store, reused from ``cache`` when it was written
        for the same frames and the same encoder weights."""
        img = store.array("img")
        key = f"{store.path}|{img.shape[0]}|" + ",".join(
            f"{v.double().sum().item():.10e}" for v in self.ae.encoder.state_dict().values())
        if cache is not None and cache.is_file():
            with safe_open(cache, "pt") as f:
                if (f.metadata() or {}).get("key") == key:
                    return f.get_tensor("latents")
        out = []
        for i in tqdm(range(0, img.shape[0], chunk), desc="encode", disable=not progress):
            out.append(self.ae.encode_tensor(to_model(img[i:i + chunk]).to(device)).cpu())
        latents = torch.cat(out)
        if cache is not None:
            cache.parent.mkdir(parents=True, exist_ok=True)
            tmp = cache.with_name(f".{cache.name}.tmp")
            save_file({"latents": latents.contiguous()}, tmp, metadata={"key": key})
            os.replace(tmp, cache)
        return latents

    def split(self) -> dict[str, list[int]]:
        return {"train_episodes": self.train_episodes, "heldout_episodes": self.heldout_episodes}

    def batch(self, step: int, generator: torch.Generator, part: slice, device: torch.device) -> DynBatch:
        cfg = self.cfg
        b, n = cfg.train.batch_size, cfg.seq_len
        first = self.seq_starts[torch.randint(0, len(self.seq_starts), (b,), generator=generator)]
        at_start = torch.rand(b, generator=generator) < cfg.start_fraction
        first = torch.where(at_start, self.episode_starts[torch.randint(0, len(self.episode_starts), (b,),
                                                                        generator=generator)], first)
        idx = first[:, None] + torch.arange(n + 1)  # (B, L+1) global frame indices
        lo, hi = cfg.context_levels
        ctx_levels = torch.randint(lo, hi, (b, n), generator=generator)
        t, s = sample_levels(b * n, cfg.schedule.num_levels, generator, cfg.top_fraction,
                             zero_fraction=cfg.zero_fraction)
        shape = tuple(self.latents.shape[1:])
        ctx_eps = gaussian((b, n, *shape), generator)
        eps = gaussian((b, n, *shape), generator)
        sigma = edm.training_sigmas(b * n, generator).view(b, n)
        idx = idx[part]
        producing = (idx - 1).clamp_min(0)  # frame k was produced by action k - 1 (unknown at k = 0)
        z = (self.latents[idx] - self.latent_mean) / self.latent_scale
        return DynBatch(z, self.actions[producing], self.known[idx], ctx_levels[part],
                        ctx_eps[part], t.view(b, n)[part], s.view(b, n)[part], eps[part],
                        sigma[part]).to(device)

    def world_model(self, dynamics: Dynamics) -> WorldModel:
        return WorldModel(self.ae, dynamics, self.cfg, self.action_low.tolist(), self.action_high.tolist(),
                          self.latent_mean, self.latent_scale)

    @torch.no_grad()
    def evaluate(self, module: nn.Module, step: int, out_dir: Path) -> dict[str, float]:
        """Open-loop rollouts of the first held-out episodes from their first frame under
        the recorded actions: latent MSE and decoded PSNR per step."""
        cfg = self.cfg
        eps = [e for e in self.heldout_episodes if self.ends[e] - self.starts[e] > 1][:cfg.eval_episodes]
        steps = min([cfg.eval_steps] + [int(self.ends[e] - self.starts[e]) - 1 for e in eps])
        wm = self.world_model(module.dynamics).eval()
        first = torch.as_tensor(self.starts[eps])
        wm.reset_latents(self.latents[first][:, None].to(wm.device), seed=0)
        preds = [wm.step_latent(self.actions[first + k].to(wm.device)) for k in range(steps)]
        pred = torch.stack(preds, 1)  # (E, S, C, h, w)
        true_idx = first[:, None] + torch.arange(1, steps + 1)
        true = self.latents[true_idx].to(wm.device)
        frames = wm.decode_latents(pred)
        truth = to_model(np.asarray(self.store.array("img").oindex[true_idx.flatten().numpy()])).to(wm.device)
        truth = truth.unflatten(0, (len(eps), steps))
        p = psnr((frames.flatten(0, 1) + 1) / 2, (truth.flatten(0, 1) + 1) / 2).view(len(eps), steps)
        out = {"latent_mse": ((pred - true) ** 2).mean().item() / self.latent_scale ** 2,  # standardised units
               "psnr": p.mean().item(),
               f"psnr_step{steps}": p[:, -1].mean().item()}
        out_dir.mkdir(parents=True, exist_ok=True)
        cols = np.linspace(0, steps - 1, min(8, steps)).round().astype(int)
        rows = [np.concatenate(list(to_uint8(v[0, cols])), axis=1) for v in (truth, frames)]
        imageio.imwrite(out_dir / f"rollout_{step:08d}.png", np.concatenate(rows, axis=0))
        return out

    def config(self, data: str | Path) -> dict:
        """The run's config.json: a complete world-model description plus where it came from."""
        wm = self.world_model(self.module.dynamics)
        return {**wm.describe(), "data": str(data), "ae_checkpoint": str(self.ae_path), "split": self.split()}

    def export(self, module: nn.Module) -> dict[str, torch.Tensor]:
        return self.world_model(module.dynamics).export()


def train_dynamics(cfg: DynamicsStageConfig, data: str | Path, ae: str | Path, out: str | Path, *,
                   device: torch.device, force: bool = False, progress: bool = True) -> dict[str, float]:
    """Train (or resume) stage 2 into the run directory ``out``."""
    # The frozen encoder's latents are cached in the run directory for resumption.
    task = DynamicsTask(cfg, data, ae, device, progress, latent_cache=Path(out) / "latents.safetensors")
    config = task.config(data)
    assert config["kind"] == KIND
    return trainer.train(task, task.cfg.train, Path(out), config, device=device, force=force, progress=progress)
