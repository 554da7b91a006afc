"""The world model: stage-1 autoencoder + stage-2 dynamics behind reset / step / rollout.

    wm = WorldModel.load("checkpoints/pusht-64")
    wm.reset(frames)                    # uint8 (B, H, W, 3), or (B, K, H, W, 3) with actions (B, K-1, A)
    frame = wm.step(actions)            # actions (B, A) in the data's units -> uint8 (B, H, W, 3)
    video = wm.rollout(frames, actions) # actions (B, N, A) -> uint8 (B, N, H, W, 3)

Streaming inference: the latest context frame and the new frame go through the dynamics
network together; the keys and values of the last N - 1 context frames are cached, so a
step costs the same at step 10 and at step 10,000, and memory stays flat.

Objectives: a new latent comes from one consistency jump from noise (ours), or, for the
benchmark's baselines, Euler steps of an EDM denoiser or one pass of a regressor
(``cfg.objective``); the streaming cache is the same for all three.

Randomness: the noise of batch item i comes from its own generator, seeded by
``seed + i`` (or ``seeds[i]``) at reset, so a batched rollout equals per-item rollouts.

Independent rollouts (e.g. the browser sessions of ``iwsim play``) can share forward
passes: ``wm.state`` is a :class:`StreamState`, which ``StreamState.cat`` joins and
``.split()`` separates again, so each rollout keeps its own state between batched steps.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from torch import nn

from iwsim.autoencoder import Autoencoder
from iwsim.config import OBJECTIVES, AEConfig, DynamicsStageConfig, from_dict
from iwsim.data.frames import to_model, to_uint8
from iwsim.diffusion import edm
from iwsim.diffusion.consistency import jump, jump_levels
from iwsim.diffusion.schedule import Schedule, gaussian
from iwsim.models.dynamics import Cache, Dynamics
from iwsim.training.checkpoint import CheckpointError, load_json, load_tensors, save_model_dir

KIND = "world_model"


def level_input(objective: str, schedule: Schedule, levels: torch.Tensor) -> torch.Tensor:
    """What the dynamics network is told about frames at DDPM noise ``levels``: the level
    itself, or for the "edm" objective the EDM noise input of the same noise."""
    if objective == "edm":
        return edm.noise_input(edm.level_sigma(schedule, levels))
    return levels.float()


def scale_actions(a: torch.Tensor, low: torch.Tensor, high: torch.Tensor) -> torch.Tensor:
    """Actions in the data's units -> [-1, 1] over [low, high] (not clipped)."""
    return (a - low) / (high - low) * 2 - 1


@dataclass
class StreamState:
    """The state of B streaming rollouts between two steps.

    ``cache`` holds the keys and values of up to N - 1 context frames (None right after
    a one-frame reset); ``z`` (B, C, h, w) is the newest context latent (standardised),
    not yet in the cache, with the action (B, A) and known flag (B,) that produced it and
    its time ``tau``; ``generators`` draw each item's noise.
    """

    cache: Cache | None
    z: torch.Tensor
    action: torch.Tensor
    known: torch.Tensor
    tau: int
    generators: list[torch.Generator]

    @property
    def batch_size(self) -> int:
        return self.z.shape[0]

    @property
    def context_frames(self) -> int:
        """Context frames in the cache: states join only with states of the same count."""
        return 0 if self.cache is None else len(self.cache)

    @staticmethod
    def cat(states: Sequence[StreamState]) -> StreamState:
        """One state for the rollouts of ``states`` (all with the same ``context_frames``).

        Attention sees only time offsets, so times are renumbered from 0 and rollouts that
        started at different steps can share a pass."""
        if not states:
            raise ValueError("StreamState.cat needs at least one state.")
        m = states[0].context_frames
        if any(s.context_frames != m for s in states):
            raise ValueError(f"states with different context lengths cannot share a step: "
                             f"{sorted({s.context_frames for s in states})}.")
        cache = None
        if m:
            first = states[0].cache
            cache = Cache([torch.cat([s.cache.keys[i] for s in states]) for i in range(len(first.keys))],
                          [torch.cat([s.cache.values[i] for s in states]) for i in range(len(first.values))],
                          torch.arange(m, device=first.times.device))
        return StreamState(cache, torch.cat([s.z for s in states]), torch.cat([s.action for s in states]),
                           torch.cat([s.known for s in states]), m,
                           [g for s in states for g in s.generators])

    def split(self) -> list[StreamState]:
        """One state per rollout (views, no copies)."""
        b = self.batch_size

        def item(t: torch.Tensor, i: int) -> torch.Tensor:  # cache rows are (B*h*w, ...), item-major
            n = t.shape[0] // b
            return t[i * n:(i + 1) * n]

        out = []
        for i in range(b):
            cache = None if self.cache is None else Cache(
                [item(k, i) for k in self.cache.keys], [item(v, i) for v in self.cache.values], self.cache.times)
            out.append(StreamState(cache, self.z[i:i + 1], self.action[i:i + 1], self.known[i:i + 1], self.tau,
                                   [self.generators[i]]))
        return out


class WorldModel(nn.Module):
    """Encoder, consistency decoder and latent dynamics, with action and latent normalisation.

    The dynamics works on standardised latents ``(z - latent_mean) / latent_scale``: the
    per-element mean over the training frames and one scale, the root-mean-square of the
    frame-to-frame variation. Scene latents barely change from frame to frame (a static
    background, small moving objects), and without this the context noise of stage 2
    (levels up to 100, noise std up to 0.14) would drown the differences that matter.
    """

    def __init__(self, ae: Autoencoder, dynamics: Dynamics, cfg: DynamicsStageConfig,
                 action_low: Sequence[float], action_high: Sequence[float],
                 latent_mean: torch.Tensor | None = None, latent_scale: float = 1.0) -> None:
        super().__init__()
        if cfg.objective not in OBJECTIVES:
            raise ValueError(f"unknown objective {cfg.objective!r}; expected one of {', '.join(OBJECTIVES)}.")
        self.ae, self.dynamics, self.cfg = ae, dynamics, cfg
        ae.decoder.to(memory_format=torch.channels_last)  # see decode_latents
        self.schedule = Schedule(cfg.schedule)
        low = torch.as_tensor(action_low, dtype=torch.float32)
        high = torch.as_tensor(action_high, dtype=torch.float32)
        if low.shape != (cfg.dynamics.action_dim,) or high.shape != low.shape or not bool((high > low).all()):
            raise ValueError(f"action bounds must be two vectors of {cfg.dynamics.action_dim} values with "
                             f"high > low, got {low.tolist()} and {high.tolist()}.")
        self.register_buffer("action_low", low)
        self.register_buffer("action_high", high)
        c = cfg.dynamics.latent_channels
        mean = torch.zeros(c, 1, 1) if latent_mean is None else torch.as_tensor(latent_mean, dtype=torch.float32)
        if mean.ndim != 3 or mean.shape[0] != c or not latent_scale > 0:
            raise ValueError(f"latent mean must be ({c}, h, w) or ({c}, 1, 1) and the scale positive, got "
                             f"{tuple(mean.shape)} and {latent_scale}.")
        self.register_buffer("latent_mean", mean)
        self.latent_scale = float(latent_scale)
        # Inference knobs, from the config and settable: consistency jumps (or Euler steps
        # of the "edm" objective) per new frame and the level context frames are labelled with.
        self.jumps, self.euler_steps, self.context_level = cfg.jumps, cfg.euler_steps, cfg.context_level
        self._state: StreamState | None = None

    # -- properties -------------------------------------------------------------------------
    @property
    def image_size(self) -> int:
        return self.ae.image_size

    @property
    def action_dim(self) -> int:
        return self.cfg.dynamics.action_dim

    @property
    def device(self) -> torch.device:
        return self.action_low.device

    @property
    def batch_size(self) -> int:
        """The batch of the current rollout (0 before ``reset``)."""
        return 0 if self._state is None else self._state.batch_size

    @property
    def state(self) -> StreamState:
        """The rollouts' state: take it after ``reset`` or ``step``, set it to continue them."""
        if self._state is None:
            raise RuntimeError("call reset() before step().")
        return self._state

    @state.setter
    def state(self, value: StreamState) -> None:
        self._state = value

    # -- frames and actions -----------------------------------------------------------------
    def check_frames(self, frames: np.ndarray | torch.Tensor, ndim: int) -> torch.Tensor:
        """uint8 frames of rank ``ndim`` ending in (H, W, 3) at this model's size, as a tensor."""
        x = torch.as_tensor(frames)
        s = self.image_size
        if x.dtype != torch.uint8:
            raise ValueError(f"frames must be uint8, got {x.dtype}.")
        if x.ndim != ndim or tuple(x.shape[-3:]) != (s, s, 3):
            want = "(B, H, W, 3)" if ndim == 4 else "(B, T, H, W, 3)"
            raise ValueError(f"expected frames {want} with H = W = {s}, got shape {tuple(x.shape)}.")
        return x

    def normalize_actions(self, actions: np.ndarray | torch.Tensor, batch: int | None = None) -> torch.Tensor:
        """Actions (..., A) in the data's units -> [-1, 1] (clipped, as the task clips its
        targets to the workspace). Non-finite values and wrong shapes are a ValueError."""
        a = torch.as_tensor(actions, dtype=torch.float32, device=self.device)
        if a.ndim < 1 or a.shape[-1] != self.action_dim or (batch is not None and a.shape[0] != batch):
            lead = "B" if batch is None else str(batch)
            raise ValueError(f"expected actions of shape ({lead}, ..., {self.action_dim}), got {tuple(a.shape)}.")
        bad = ~torch.isfinite(a)
        if bad.any():
            raise ValueError(f"actions must be finite, got {a[bad][0].item()} at index "
                             f"{tuple(i.item() for i in bad.nonzero()[0])}.")
        return scale_actions(a, self.action_low, self.action_high).clamp(-1, 1)

    @torch.inference_mode()
    def encode(self, frames: np.ndarray | torch.Tensor) -> torch.Tensor:
        """uint8 frames (B, H, W, 3) -> latents (B, C, H/4, W/4)."""
        x = self.check_frames(frames, 4)
        return self.ae.encode_tensor(to_model(x).to(self.device))

    @torch.inference_mode()
    def decode(self, latents: torch.Tensor, seed: int = 0) -> np.ndarray:
        """Latents (B, C, h, w) -> uint8 frames (B, 4h, 4w, 3) by one consistency jump."""
        g = torch.Generator(self.device).manual_seed(seed)
        return to_uint8(self.ae.decode_tensor(latents.to(self.device), 1, g))

    # -- streaming rollout on latents ---------------------------------------------------------
    def standardize(self, z: torch.Tensor) -> torch.Tensor:
        """Autoencoder latents (..., C, h, w) -> the dynamics' standardised latents."""
        return (z - self.latent_mean) / self.latent_scale

    def unstandardize(self, z: torch.Tensor) -> torch.Tensor:
        return z * self.latent_scale + self.latent_mean

    @torch.inference_mode()
    def reset_latents(self, latents: torch.Tensor, actions: torch.Tensor | None = None,
                      seed: int | Sequence[int] = 0) -> None:
        """Start rollouts from context latents (B, K, C, h, w) (as ``encode`` returns them)
        and the normalised actions (B, K-1, A) between them. Frames before the last fill
        the cache; the last one joins the context together with the first predicted frame."""
        b, k = latents.shape[:2]
        z = self.standardize(latents.to(self.device))
        if k > 1 and (actions is None or actions.shape[:2] != (b, k - 1)):
            raise ValueError(f"{k} context frames need actions (B, {k - 1}, A) between them.")
        zero = torch.zeros(b, 1, self.action_dim, device=self.device)
        acts = zero if k == 1 else torch.cat([zero, actions.to(self.device)], 1)
        known = torch.ones(b, k, device=self.device)
        known[:, 0] = 0  # the first frame's producing action is unknown
        # Only the last N - 1 context frames matter, but frames before them shape their
        # activations (as in a long rollout), so all of them run through the network.
        cache = None
        if k > 1:
            lv = level_input(self.cfg.objective, self.schedule,
                             torch.full((b, k - 1), self.context_level, device=self.device))
            times = torch.arange(k - 1, device=self.device)
            _, cache = self.dynamics(z[:, :-1], lv, lv, acts[:, :-1], known[:, :-1], times,
                                     torch.ones(k - 1, dtype=torch.bool, device=self.device))
        seeds = [seed + i for i in range(b)] if isinstance(seed, int) else list(seed)
        if len(seeds) != b:
            raise ValueError(f"got {len(seeds)} seeds for a batch of {b}.")
        self._state = StreamState(cache, z[:, -1], acts[:, -1], known[:, -1], k - 1,
                                  [torch.Generator(self.device).manual_seed(int(s)) for s in seeds])

    def _noise(self, shape: tuple[int, ...]) -> torch.Tensor:
        """Clipped Gaussian noise (B, *shape), item i from its own generator."""
        return torch.cat([gaussian((1, *shape), g, self.device) for g in self.state.generators])

    @torch.inference_mode()
    def step_latent(self, actions: torch.Tensor) -> torch.Tensor:
        """Normalised actions (B, A) -> the next latents (B, C, h, w), as ``encode`` gives them."""
        st = self.state
        z_ctx, a_ctx, k_ctx, tau = st.z, st.action, st.known, st.tau
        b = z_ctx.shape[0]
        if actions.shape != (b, self.action_dim):
            raise ValueError(f"expected actions of shape ({b}, {self.action_dim}), got {tuple(actions.shape)}.")
        dev = self.device
        ctx_in = level_input(self.cfg.objective, self.schedule, torch.full((b,), self.context_level, device=dev))
        one = torch.ones(b, device=dev)
        new_cache: Cache | None = None

        def net(x: torch.Tensor, t: torch.Tensor, s: torch.Tensor) -> torch.Tensor:
            """The network's output for the new frame x (B, C, h, w) told levels t, s (B,)."""
            nonlocal new_cache
            if new_cache is None:  # the first pass: the pending context frame joins the cache
                v, new_cache = self.dynamics(
                    torch.stack([z_ctx, x], 1), torch.stack([ctx_in, t], 1), torch.stack([ctx_in, s], 1),
                    torch.stack([a_ctx, actions], 1), torch.stack([k_ctx, one], 1),
                    torch.tensor([tau, tau + 1], device=dev), torch.tensor([True, False], device=dev), st.cache)
            else:
                v, _ = self.dynamics(x[:, None], t[:, None], s[:, None], actions[:, None], one[:, None],
                                     torch.tensor([tau + 1], device=dev), torch.tensor([False], device=dev),
                                     new_cache)
            return v[:, -1]

        x = self._sample(net, tuple(z_ctx.shape[1:]), b)
        self._state = StreamState(new_cache, x, actions, one, tau + 1, st.generators)
        return self.unstandardize(x)

    def _sample(self, net: Callable[[torch.Tensor, torch.Tensor, torch.Tensor], torch.Tensor],
                shape: tuple[int, ...], b: int) -> torch.Tensor:
        """The new standardised latent (B, *shape) by the config's objective."""
        dev = self.device

        def full(v: float) -> torch.Tensor:
            return torch.full((b,), float(v), device=dev)

        if self.cfg.objective == "regression":
            return net(torch.zeros(b, *shape, device=dev), full(self.schedule.T), full(0))
        x = self._noise(shape)
        if self.cfg.objective == "edm":  # Euler steps along the Karras sigmas
            sigmas = edm.karras_sigmas(self.euler_steps)
            x = x * sigmas[0]
            for sigma, nxt in zip(sigmas[:-1], sigmas[1:]):
                c_skip, c_in, c_out = edm.precondition(full(sigma), x)
                c = edm.noise_input(full(sigma))
                denoised = c_skip * x + c_out * net(c_in * x, c, c)
                x = denoised if nxt == 0 else x + (nxt - sigma) / sigma * (x - denoised)
            return x
        levels = jump_levels(self.jumps, self.schedule.T - 1)
        for t, s in zip(levels[:-1], levels[1:]):
            t_b, s_b = full(t), full(s)
            v = net(x, t_b, s_b)
            x = jump(lambda *_: v, self.schedule, x, t_b.long(), s_b.long(), None)
        return x

    # -- the public, uint8 API ----------------------------------------------------------------
    def reset(self, frames: np.ndarray | torch.Tensor, actions: np.ndarray | torch.Tensor | None = None,
              seed: int | Sequence[int] = 0) -> None:
        """Start B rollouts from one context frame each, uint8 (B, H, W, 3), or from K
        frames (B, K, H, W, 3) with the K - 1 actions (B, K-1, A) taken between them."""
        x = torch.as_tensor(frames)
        x = self.check_frames(x[:, None] if x.ndim == 4 else x, 5)
        b, k = x.shape[:2]
        a = None
        if k > 1:
            if actions is None:
                raise ValueError(f"{k} context frames need the {k - 1} actions (B, {k - 1}, A) between them.")
            a = self.normalize_actions(actions, b)
            if a.shape != (b, k - 1, self.action_dim):
                raise ValueError(f"expected actions ({b}, {k - 1}, {self.action_dim}), got {tuple(a.shape)}.")
        self.reset_latents(self.encode(x.flatten(0, 1)).unflatten(0, (b, k)), a, seed)

    @torch.inference_mode()
    def step(self, actions: np.ndarray | torch.Tensor) -> np.ndarray:
        """Actions (B, A) in the data's units -> the next frames, uint8 (B, H, W, 3)."""
        z = self.step_latent(self.normalize_actions(actions, self.state.batch_size))
        return to_uint8(self.decode_latents(z))

    @torch.inference_mode()
    def decode_latents(self, z: torch.Tensor) -> torch.Tensor:
        """Latents (B, ..., C, h, w) -> images (B, ..., 3, H, W) in [-1, 1], item i's
        noise from its own generator."""
        lead = tuple(z.shape[1:-3])
        size = self.image_size
        noise = self._noise((*lead, self.ae.cfg.decoder.image_channels, size, size)).flatten(0, len(lead))
        # channels-last activations: ~25% faster decoder convolutions on CPU (measured at batch 4)
        cl = torch.channels_last
        images = self.ae.decode_tensor(z.flatten(0, len(lead)).contiguous(memory_format=cl), 1,
                                       noise=noise.contiguous(memory_format=cl))
        return images.contiguous().view(*z.shape[:-3], *noise.shape[1:])

    def rollout(self, context_frames: np.ndarray | torch.Tensor, actions: np.ndarray | torch.Tensor,
                context_actions: np.ndarray | torch.Tensor | None = None, seed: int | Sequence[int] = 0,
                progress: bool = False) -> np.ndarray:
        """Open-loop rollout: context frames (B, [K,] H, W, 3), actions (B, N, A) ->
        predicted frames uint8 (B, N, H, W, 3)."""
        from tqdm import tqdm

        a = self.normalize_actions(actions)
        if a.ndim != 3:
            raise ValueError(f"expected actions (B, N, {self.action_dim}), got {tuple(a.shape)}.")
        self.reset(context_frames, context_actions, seed)
        if a.shape[0] != self.batch_size:
            raise ValueError(f"{self.batch_size} context frames but actions for {a.shape[0]} rollouts.")
        out = []
        with torch.inference_mode():
            for i in tqdm(range(a.shape[1]), desc="rollout", disable=not progress):
                out.append(to_uint8(self.decode_latents(self.step_latent(a[:, i]))))
        return np.stack(out, 1) if out else np.zeros((self.batch_size, 0, self.image_size, self.image_size, 3),
                                                     np.uint8)

    # -- checkpoints ----------------------------------------------------------------------------
    def export(self) -> dict[str, torch.Tensor]:
        """The tensors of a world-model ``model.safetensors``."""
        return {**{f"ae.{k}": v for k, v in self.ae.state_dict().items()},
                **{f"dynamics.{k}": v for k, v in self.dynamics.state_dict().items()},
                "latent_mean": self.latent_mean}

    def describe(self) -> dict:
        """The parts of ``config.json`` that ``load`` reads."""
        from iwsim.config import to_dict

        return {"kind": KIND, "ae": to_dict(self.ae.cfg), "stage2": to_dict(self.cfg),
                "action_norm": {"low": self.action_low.tolist(), "high": self.action_high.tolist()},
                "latent_norm": {"scale": self.latent_scale}}

    def save(self, path: str | Path, extra: dict | None = None, force: bool = False) -> Path:
        """Write a self-contained checkpoint directory atomically; ``extra`` entries
        (provenance) are added to ``config.json``."""
        return save_model_dir(Path(path), self.export(), {**(extra or {}), **self.describe()}, force)

    @classmethod
    def load(cls, path: str | Path, device: str | torch.device = "cpu") -> WorldModel:
        """From a checkpoint directory (``model.safetensors`` + ``config.json``), e.g. one
        written by ``iwsim train dynamics`` or ``iwsim export-model``."""
        path = Path(path)
        if not path.is_dir():
            raise CheckpointError(f"{path} is not a checkpoint directory (model.safetensors + config.json).")
        config = load_json(path / "config.json")
        if config.get("kind") != KIND:
            raise CheckpointError(f"{path} is not a world-model checkpoint (config kind {config.get('kind')!r}, "
                                  f"expected {KIND!r}).")
        for part in ("ae", "stage2", "action_norm", "latent_norm"):
            if part not in config:
                raise CheckpointError(f"{path / 'config.json'} is missing the {part!r} part of the world model.")
        try:
            ae_cfg = from_dict(AEConfig, config["ae"])
            cfg = from_dict(DynamicsStageConfig, config["stage2"])
        except (TypeError, ValueError, KeyError) as e:
            raise CheckpointError(f"{path / 'config.json'} does not describe a world model: {e}") from None
        tensors = load_tensors(path / "model.safetensors")
        parts = {}
        for part in ("ae", "dynamics"):
            parts[part] = {k[len(part) + 1:]: v for k, v in tensors.items() if k.startswith(part + ".")}
            if not parts[part]:
                raise CheckpointError(f"{path / 'model.safetensors'} has no {part} weights ({part}.*).")
        if "latent_mean" not in tensors:
            raise CheckpointError(f"{path / 'model.safetensors'} has no latent normalisation (latent_mean).")
        ae, dyn = Autoencoder(ae_cfg), Dynamics(cfg.dynamics)
        try:
            ae.load_state_dict(parts["ae"])
            dyn.load_state_dict(parts["dynamics"])
        except RuntimeError as e:
            raise CheckpointError(f"{path / 'model.safetensors'} does not match its config: "
                                  f"{' '.join(str(e).split())[:200]}") from None
        norm = config["action_norm"]
        return cls(ae, dyn, cfg, norm["low"], norm["high"], tensors["latent_mean"],
                   config["latent_norm"]["scale"]).to(device).eval()


def export_model(run: str | Path, out: str | Path, force: bool = False) -> Path:
    """A standalone world-model checkpoint (``model.safetensors`` + ``config.json``) from a
    run of ``train dynamics`` or ``train decoder-finetune`` (its last checkpoint) or from
    one of its checkpoints (``iwsim export-model``)."""
    from iwsim.training.dynamics import resolve_checkpoint

    src = resolve_checkpoint(run)
    config = load_json(src / "config.json")
    provenance = {k: config[k] for k in ("data", "ae_checkpoint", "finetuned_from") if k in config}
    return WorldModel.load(src).save(out, {"provenance": {"source": str(src), **provenance}}, force)
