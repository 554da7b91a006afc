"""Stage 2 training: the latent dynamics on the frozen stage-1 encoder (``iwsim train dynamics``).

A training sequence holds the K latents of a window and the n frames after it. The model
predicts them one after the other, each from a window that holds its own earlier
predictions (training on the model's own unrolled predictions, as Self-Forcing and
DIAMOND's autoregressive training do; n grows over training, ``cfg.unroll``). Each
prediction's context gets Gaussian noise of a random std in the standardised units the
network sees (``cfg.context_sigma``), and the network is told that std. The loss weights
latent cells that change ``1 + cfg.changed_weight`` times more than static ones.

The gradient flows through the fed-back predictions (back-propagation through the whole
unroll) unless ``cfg.unroll_grad`` is off. The benchmark's baselines train in the same
way with another ``objective`` (see ``iwsim.config.VARIANTS``); the "edm" objective's
fed-back context is a real sample (Euler steps, no gradient), since its one-pass
estimate is not what inference produces.

The conditioning actions are the motion the robot executed: ``data/target`` when the
store has it (the task's rate-limited setpoints), else ``data/action``.

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
from iwsim.checkpoint import resolve_checkpoint
from iwsim.config import OBJECTIVES, DynamicsStageConfig
from iwsim.data.frames import split_episodes, to_model, to_uint8
from iwsim.data.store import EpisodeStore, StoreError, conditioning_key
from iwsim.diffusion import edm
from iwsim.diffusion.consistency import sample_levels
from iwsim.diffusion.objectives import OBJECTIVES as OBJECTIVE_TABLE
from iwsim.diffusion.objectives import Levels
from iwsim.diffusion.schedule import Schedule, gaussian
from iwsim.errors import InputError
from iwsim.metrics import psnr
from iwsim.models.dynamics import Dynamics
from iwsim.normalize import scale, widen
from iwsim.training import trainer
from iwsim.world_model import KIND, WorldModel, label

log = logging.getLogger(__name__)


@dataclass
class DynBatch:
    """Standardised latents z (B, K+n, C, h, w): the window, then the n frames to predict;
    normalised actions (B, n+1, A): prediction u takes actions u (the one that produced its
    newest context frame) and u+1 (the one that produces its frame); whether frame K+u
    changed from K+u-1 per cell (B, n, 1, h, w); context-noise stds (B, n) and noise
    (B, n, K, C, h, w); target levels t, s and EDM sigmas (B, n) and noise (B, n, C, h, w)."""

    z: torch.Tensor
    actions: torch.Tensor
    ctx_sigma: torch.Tensor
    ctx_eps: torch.Tensor
    t: torch.Tensor
    s: torch.Tensor
    sigma: torch.Tensor
    eps: torch.Tensor

    def to(self, device: torch.device) -> DynBatch:
        return DynBatch(*(v.to(device) for v in vars(self).values()))


class DynamicsTrainModule(nn.Module):
    """forward(batch) -> the loss of the n unrolled predictions of each sequence under the
    config's objective (see the module docstring)."""

    def __init__(self, dynamics: Dynamics, schedule: Schedule, cfg: DynamicsStageConfig) -> None:
        super().__init__()
        if cfg.objective not in OBJECTIVES:
            raise InputError(f"unknown objective {cfg.objective!r}; expected one of {', '.join(OBJECTIVES)}.")
        self.dynamics, self.schedule, self.cfg = dynamics, schedule, cfg
        self.objective = OBJECTIVE_TABLE[cfg.objective]
        # Whether the loss's one-pass estimate is exactly what inference generates (then it
        # is fed back with its gradient); otherwise a real sample is fed back.
        one_jump = cfg.jumps == 1 and cfg.top_fraction == 1 and cfg.zero_fraction == 1
        self.feeds_estimate = cfg.objective == "regression" or (cfg.objective == "consistency" and one_jump)

    def forward(self, batch: DynBatch) -> tuple[torch.Tensor, dict[str, float]]:
        per = self.unroll(batch)  # (B, n)
        return per.mean(), {"loss_first": per[:, 0].mean().item(), "loss_last": per[:, -1].mean().item(),
                            "unroll": float(per.shape[1])}

    def unroll(self, batch: DynBatch) -> torch.Tensor:
        """The loss (B, n) of each of the n predictions of each sequence."""
        cfg = self.cfg
        k = cfg.dynamics.context
        n = batch.z.shape[1] - k
        ctx = batch.z[:, :k]
        losses = []
        for u in range(n):
            sig = batch.ctx_sigma[:, u]
            ctx_in = ctx + sig.view(-1, 1, 1, 1, 1) * batch.ctx_eps[:, u]
            acts = batch.actions[:, u:u + 2]
            ctx_label = label(sig)

            def net(x: torch.Tensor, t: torch.Tensor, s: torch.Tensor) -> torch.Tensor:
                return self.dynamics(x, ctx_in, t, s, ctx_label, acts)  # noqa: B023  (called in this iteration)

            target = batch.z[:, k + u]
            base = ctx_in[:, -1] if cfg.predict_delta else torch.zeros_like(target)
            levels = Levels(batch.t[:, u], batch.s[:, u], batch.sigma[:, u])
            err, estimate = self.objective.loss(net, self.schedule, target - base, levels, batch.eps[:, u])
            changed = (target - batch.z[:, k + u - 1]).abs().amax(1, keepdim=True) > cfg.changed_threshold
            losses.append((err * (1 + cfg.changed_weight * changed)).mean((1, 2, 3)))
            if u == n - 1:
                break
            if not self.feeds_estimate:
                with torch.no_grad():
                    steps = cfg.euler_steps if cfg.objective == "edm" else cfg.jumps
                    estimate = self.objective.sample(net, self.schedule, torch.randn_like(target), steps)
            pred = base + estimate
            ctx = torch.cat([ctx[:, 1:], (pred if cfg.unroll_grad else pred.detach())[:, None]], 1)
        return torch.stack(losses, 1)


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
            raise InputError(f"{data} holds {size}x{size} frames but the autoencoder {self.ae_path} expects "
                             f"{self.ae.image_size}x{self.ae.image_size}.")
        self.action_key = conditioning_key(store.keys)
        actions = np.asarray(store.array(self.action_key)[:], dtype=np.float32)
        if actions.ndim != 2:
            raise StoreError(f"{data}: data/{self.action_key} must be (frames, action_dim), got {actions.shape}.")
        if store.n_episodes < 2:
            raise InputError(f"{data} holds {store.n_episodes} episode(s); training needs at least 2 "
                             "(one is held out for evaluation).")
        self.train_episodes, self.heldout_episodes = split_episodes(store.n_episodes, cfg.holdout_every)
        ends = store.episode_ends.astype(np.int64)
        starts = np.concatenate([[0], ends[:-1]])
        longest = max(cfg.unroll_at(s) for s, _ in cfg.unroll) if cfg.unroll else 1
        train_long = [e for e in self.train_episodes if ends[e] - starts[e] >= longest + 1]
        if not train_long:
            raise InputError(f"no training episode of {data} has the {longest + 1} frames the longest unroll "
                             f"needs ({longest} predictions); lower cfg.unroll or collect longer episodes.")
        self.ep_starts = torch.from_numpy(starts[train_long])
        self.ep_lengths = torch.from_numpy(ends[train_long] - starts[train_long])
        train_idx = np.concatenate([np.arange(starts[e], ends[e]) for e in self.train_episodes])
        train_actions = torch.from_numpy(actions[train_idx])
        low, high = widen(train_actions.amin(0), train_actions.amax(0), 1e-3)
        self.action_low, self.action_high = low.numpy(), high.numpy()
        self.actions = scale(torch.from_numpy(actions), low, high)
        self.latents = self._encode(store, device, progress, latent_cache)
        # The action size and latent shape follow the data; positional actions where the
        # task declares them (see iwsim.models.dynamics).
        cfg = replace(cfg, dynamics=replace(cfg.dynamics, action_dim=actions.shape[1],
                                            latent_channels=self.latents.shape[1],
                                            latent_size=self.latents.shape[-1],
                                            **self._points(store.attrs, cfg)))
        self.cfg = cfg
        # Standardisation of the latents for the dynamics (see WorldModel): per-element
        # mean over the training frames, and the RMS of the per-element standard deviation.
        train_z = self.latents[torch.from_numpy(train_idx)]
        self.latent_mean = train_z.mean(0)
        self.latent_scale = float(train_z.var(0).mean().sqrt().clamp_min(1e-6))
        self.store, self.starts, self.ends = store, starts, ends
        with torch.random.fork_rng():  # initial weights from the run's seed, global RNG untouched
            torch.manual_seed(cfg.train.seed)
            self.module = DynamicsTrainModule(Dynamics(cfg.dynamics), Schedule(cfg.schedule), cfg)

    def _points(self, attrs: dict, cfg: DynamicsStageConfig) -> dict:
        """The positional-action fields of the network's config: which action entries are
        image positions and the map from normalised actions to image coordinates, from the
        task's declaration in the store (``action_points``, ``view_half``), if any."""
        points, view = attrs.get("action_points"), attrs.get("view_half")
        if not (cfg.dynamics.positional_actions and points and view):
            return {"point_index": (), "point_scale": (), "point_offset": ()}
        half = (self.action_high - self.action_low) / 2 / view
        mid = (self.action_high + self.action_low) / 2 / view
        return {"point_index": tuple(tuple(int(i) for i in p) for p in points),
                "point_scale": tuple(float(v) for v in half), "point_offset": tuple(float(v) for v in mid)}

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
        b, k, n = cfg.train.batch_size, cfg.dynamics.context, cfg.unroll_at(step)
        # Windows end anywhere in a training episode that leaves n frames after them (a
        # share at its first frame); frames before the episode repeat its first frame.
        room = (self.ep_lengths - n).clamp_min(0).double()
        ep = torch.multinomial(room, b, replacement=True, generator=generator)
        offset = (torch.rand(b, generator=generator) * room[ep]).long()
        offset = torch.where(torch.rand(b, generator=generator) < cfg.start_fraction, 0, offset)
        start = self.ep_starts[ep]
        anchor = start + offset  # the newest context frame
        idx = torch.maximum(anchor[:, None] + torch.arange(-(k - 1), n + 1), start[:, None])  # (B, K+n)
        act = anchor[:, None] + torch.arange(-1, n)  # (B, n+1): before the episode, its first action
        act = torch.maximum(act, start[:, None])
        lo, hi = cfg.context_sigma
        ctx_sigma = lo + (hi - lo) * torch.rand(b, n, generator=generator)
        shape = tuple(self.latents.shape[1:])
        ctx_eps = torch.randn(b, n, k, *shape, generator=generator)
        t, s = sample_levels(b * n, cfg.schedule.num_levels, generator, cfg.top_fraction,
                             zero_fraction=cfg.zero_fraction)
        eps = gaussian((b, n, *shape), generator)
        sigma = edm.training_sigmas(b * n, generator).view(b, n)
        z = (self.latents[idx[part]] - self.latent_mean) / self.latent_scale
        return DynBatch(z, self.actions[act[part]], ctx_sigma[part], ctx_eps[part], t.view(b, n)[part],
                        s.view(b, n)[part], sigma[part], eps[part]).to(device)

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
                   device: torch.device, force: bool = False, progress: bool = True,
                   latent_cache: str | Path | None = None) -> dict[str, float]:
    """Train (or resume) stage 2 into the run directory ``out``. The frozen encoder's
    latents are cached in ``latent_cache`` (default: the run directory), which runs on the
    same store and encoder can share; a cache of other frames or weights is rewritten."""
    cache = Path(latent_cache) if latent_cache is not None else Path(out) / "latents.safetensors"
    task = DynamicsTask(cfg, data, ae, device, progress, latent_cache=cache)
    config = task.config(data)
    assert config["kind"] == KIND
    return trainer.train(task, task.cfg.train, Path(out), config, device=device, force=force, progress=progress)
