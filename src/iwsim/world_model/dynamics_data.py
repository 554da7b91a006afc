"""Stage 2's training data: an episode store as latent sequences (``iwsim train dynamics``).

Every frame of the store is encoded once by the frozen stage-1 encoder (on every core this
process may use; in bf16 when the run trains in bf16 on a CPU with the instructions for
it, as :func:`iwsim.core.trainer.training_precision` decides) and cached as float16; the
conditioning actions are min-max normalised over the training episodes; the latents are
standardised for the dynamics (see :class:`iwsim.world_model.WorldModel`). A batch holds
windows of training episodes with everything random a training step needs.
"""

from __future__ import annotations

import hashlib
import json
import logging
import os
import time
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np
import torch
from safetensors import SafetensorError, safe_open
from tqdm import tqdm

from iwsim.core.checkpoint import resolve_checkpoint, save_tensors
from iwsim.core.errors import InputError
from iwsim.core.normalize import scale, widen
from iwsim.core.precision import bf16_available
from iwsim.core.resources import available_cores, torch_threads
from iwsim.data.frames import read_frames, split_episodes, to_model
from iwsim.data.store import EpisodeStore, StoreError, conditioning_key
from iwsim.data.views import store_cameras
from iwsim.diffusion import edm
from iwsim.diffusion.consistency import sample_levels
from iwsim.diffusion.schedule import gaussian
from iwsim.envs.registry import foreign_task
from iwsim.world_model.codecs import load_codec
from iwsim.world_model.codecs.base import Codec, encode_views
from iwsim.world_model.model import WorldModel
from iwsim.world_model.novelty import Novelty, fit_novelty, novelty_features
from iwsim.world_model.presets import DynamicsStageConfig

log = logging.getLogger(__name__)

# The network config's fields of the robot's state, which the data decides.
STATE_FIELDS = ("state_dim", "state_point_scale", "state_point_offset", "state_action_scale", "state_action_offset")
NOVELTY_STEPS = 50_000  # steps of the training data the trust signal's Gaussian is fitted to


@dataclass
class DynBatch:
    """Standardised latents z (B, K+n, C, h, w): the window, then the n frames to predict;
    normalised actions (B, n+1, A): prediction u takes actions u (the one that produced its
    newest context frame) and u+1 (the one that produces its frame); context-noise stds
    (B, n) and noise (B, n, K, C, h, w); target levels t, s and EDM sigmas (B, n) and noise
    (B, n, C, h, w); the noise (B, n, C, h, w) a fed-back sample starts from (objectives
    whose one-pass estimate is not what inference generates, see DynamicsTrainModule); the
    robot's normalised states (B, n+1, S) at the newest context frame and at each frame to
    predict (S = 0 for a network without the state)."""

    z: torch.Tensor
    actions: torch.Tensor
    ctx_sigma: torch.Tensor
    ctx_eps: torch.Tensor
    t: torch.Tensor
    s: torch.Tensor
    sigma: torch.Tensor
    eps: torch.Tensor
    feed_eps: torch.Tensor
    states: torch.Tensor | None = None

    def to(self, device: torch.device) -> DynBatch:
        moved: dict[str, Any] = {k: None if v is None else v.to(device) for k, v in vars(self).items()}
        return DynBatch(**moved)


class DynamicsData:
    """Latents of every frame of the store (encoded once), normalised actions, the
    train/held-out split, and sequences from the training episodes (``batch``). ``cfg``
    is the given config with the sizes the data decides (action size, latent shape,
    positional actions).

    With ``cfg.predict_state`` the store's ``data/state`` (the robot's own state) is
    min-max normalised over the training episodes like the actions; where the store's task
    declares the actions' image positions and the state has the action's size (the
    tabletop tasks' ``agent_pos``: where the pushers are, as the actions say where they
    should go), the state's entries are the same positions.

    With ``init`` (a world model to fine-tune) its autoencoder, action, state and latent
    normalisation and network config are kept, so its weights stay meaningful; the data
    must have its action size. A model without the state fine-tuned with it gains the
    state's inputs (zero weights) and head (see :func:`~iwsim.world_model.dynamics.add_state`).

    ``latent_norm`` (mean, scale): the latent standardisation to use instead of the
    training frames' (a resumed run keeps the one it started with: re-encoded on another
    CPU, bf16 latents differ in their last bits, and so would their statistics)."""

    def __init__(self, cfg: DynamicsStageConfig, data: str | Path, ae_path: str | Path,
                 device: torch.device = torch.device("cpu"), progress: bool = True,
                 latent_cache: Path | None = None, init: WorldModel | None = None,
                 latent_norm: tuple[torch.Tensor, float] | None = None) -> None:
        store = EpisodeStore.open(data, "r")
        for key in ("img", "action"):
            if key not in store.keys:
                raise StoreError(f"{data} has no data/{key} to train the dynamics on.")
        self.ae_path = resolve_checkpoint(ae_path)  # with init: the world model's checkpoint
        self.codec = load_codec(self.ae_path, device) if init is None else init.codec
        size = store.array("img").shape[1]
        if size != self.codec.image_size:
            raise InputError(f"{data} holds {size}x{size} frames but the autoencoder {self.ae_path} expects "
                             f"{self.codec.image_size}x{self.codec.image_size}.")
        self.cameras = store_cameras(store.attrs, store.keys)
        if init is not None and tuple(init.cameras) != self.cameras:
            raise InputError(f"{data} holds the views {list(self.cameras)} but the world model {self.ae_path} sees "
                             f"{list(init.cameras)}.")
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
        if init is None:
            train_actions = torch.from_numpy(actions[train_idx])
            low, high = widen(train_actions.amin(0), train_actions.amax(0), 1e-3)
        else:
            if actions.shape[1] != init.cfg.dynamics.action_dim:
                raise InputError(f"{data} has {actions.shape[1]}-d actions; the world model {self.ae_path} takes "
                                 f"{init.cfg.dynamics.action_dim}-d ones.")
            low, high = init.action_low.cpu(), init.action_high.cpu()
        self.action_low, self.action_high = low.numpy(), high.numpy()
        self.actions = scale(torch.from_numpy(actions), low, high)
        self.states = torch.zeros(len(actions), 0)
        self.state_low = self.state_high = np.zeros(0, np.float32)
        if cfg.predict_state:
            self._load_states(store, data, train_idx, len(actions), init)
        self.latents = encode_store(self.codec, store, device, progress, latent_cache,
                                    bf16=cfg.train.cpu_bf16 and device.type == "cpu" and bf16_available(device))
        # The action size and latent shape follow the data; positional actions where the
        # task declares them (see iwsim.world_model.dynamics).
        cfg = replace(cfg, cameras=self.cameras, dynamics=replace(cfg.dynamics, action_dim=actions.shape[1],
                                            latent_channels=self.latents.shape[1],
                                            latent_size=self.latents.shape[-1],
                                            **self.points(store.attrs, cfg)))
        cfg = replace(cfg, dynamics=replace(cfg.dynamics, **self.state_points(store.attrs, cfg)))
        # Fine-tuning keeps the model's network; only its window may be widened (cfg's) and
        # the state added.
        if init is not None:
            keep = replace(init.cfg.dynamics, context=cfg.dynamics.context)
            if cfg.predict_state and not init.cfg.dynamics.state_dim:
                keep = replace(keep, **{k: getattr(cfg.dynamics, k) for k in STATE_FIELDS})
            cfg = replace(cfg, dynamics=keep)
        self.cfg = cfg
        # Standardisation of the latents for the dynamics (see WorldModel): per-element
        # mean over the training frames, and the RMS of the per-element standard deviation.
        if init is None and latent_norm is not None:
            self.latent_mean, self.latent_scale = latent_norm[0].float().cpu(), float(latent_norm[1])
        elif init is None:
            self.latent_mean, self.latent_scale = latent_stats(self.latents, train_idx)
        else:
            self.latent_mean, self.latent_scale = init.latent_mean.cpu(), float(init.latent_scale)
        self.store, self.starts, self.ends = store, starts, ends
    def points(self, attrs: dict, cfg: DynamicsStageConfig) -> dict:
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

    def _load_states(self, store: EpisodeStore, data: str | Path, train_idx: np.ndarray, frames: int,
                     init: WorldModel | None) -> None:
        """The normalised states (N, S) and their bounds (the training episodes', or the
        fine-tuned model's when it has a state)."""
        if "state" not in store.keys:
            raise StoreError(f"{data} has no data/state (the robot's own state) for the state head to learn; "
                             "train without the 'state' variant, or give a store that records it.")
        states = np.asarray(store.array("state")[:], dtype=np.float32)
        if states.ndim != 2 or len(states) != frames or not np.isfinite(states).all():
            raise StoreError(f"{data}: data/state must be finite (frames, state_dim) values, one row per frame; "
                             f"got shape {states.shape}.")
        if init is not None and init.state_dim:
            if states.shape[1] != init.state_dim:
                raise InputError(f"{data} has {states.shape[1]}-d states; the world model {self.ae_path} takes "
                                 f"{init.state_dim}-d ones.")
            low, high = init.state_low.cpu(), init.state_high.cpu()
        else:
            train_states = torch.from_numpy(states[train_idx])
            low, high = widen(train_states.amin(0), train_states.amax(0), 1e-3)
        self.state_low, self.state_high = low.numpy(), high.numpy()
        self.states = scale(torch.from_numpy(states), low, high)

    def state_points(self, attrs: dict, cfg: DynamicsStageConfig) -> dict:
        """The state fields of the network's config (``cfg``: with the action's points
        filled in): its size and, when it holds the action's image positions (see the class
        docstring), the maps from normalised states to image coordinates (as :meth:`points`,
        from the store's ``view_half``) and from normalised actions to the states they set."""
        dim = self.states.shape[1]
        d = cfg.dynamics
        none = {"state_dim": dim, "state_point_scale": (), "state_point_offset": (), "state_action_scale": (),
                "state_action_offset": ()}
        if not (dim and d.point_index and dim == d.action_dim):
            return none
        view = attrs["view_half"]  # declared wherever the action's points are (see points)
        # a normalised value's data: mid + a * half, per bounds
        a_half, a_mid = (self.action_high - self.action_low) / 2, (self.action_high + self.action_low) / 2
        s_half, s_mid = (self.state_high - self.state_low) / 2, (self.state_high + self.state_low) / 2
        return {**none, "state_point_scale": tuple(float(v) for v in s_half / view),
                "state_point_offset": tuple(float(v) for v in s_mid / view),
                "state_action_scale": tuple(float(v) for v in a_half / s_half),
                "state_action_offset": tuple(float(v) for v in (a_mid - s_mid) / s_half)}

    def split(self) -> dict[str, list[int]]:
        return {"train_episodes": self.train_episodes, "heldout_episodes": self.heldout_episodes}

    def batch(self, step: int, generator: torch.Generator, part: slice, device: torch.device) -> DynBatch:
        """This rank's ``part`` of step ``step``'s global batch of training sequences (see
        :class:`DynBatch`), everything random drawn from ``generator``."""
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
        feed_eps = gaussian((b, n, *shape), generator)  # drawn last: the draws above stay as they were
        z = (self.latents[idx[part]].float() - self.latent_mean) / self.latent_scale
        states = self.states[idx[part, k - 1:]]  # the newest context frame's, then the predicted frames'
        return DynBatch(z, self.actions[act[part]], ctx_sigma[part], ctx_eps[part], t.view(b, n)[part],
                        s.view(b, n)[part], sigma[part], eps[part], feed_eps[part], states).to(device)


def latent_stats(latents: torch.Tensor, idx: np.ndarray, block: int = 16384) -> tuple[torch.Tensor, float]:
    """The per-element mean of ``latents[idx]`` and the RMS of its per-element standard
    deviation (unbiased), summed in float64 over passes of ``block`` frames: the x4 latents
    of 1.85M frames would take 14 GB in float32 at once."""
    total = torch.zeros(latents.shape[1:], dtype=torch.float64)
    squares = torch.zeros_like(total)
    for i in range(0, len(idx), block):
        z = latents[torch.from_numpy(idx[i:i + block])].double()
        total += z.sum(0)
        squares += z.square().sum(0)
    n = len(idx)
    mean = total / n
    var = ((squares - n * mean.square()) / max(n - 1, 1)).clamp_min(0)
    return mean.float(), float(var.mean().sqrt().clamp_min(1e-6))


@torch.no_grad()
def encode_store(codec: Codec, store: EpisodeStore, device: torch.device, progress: bool, cache: Path | None,
                 chunk: int = 512, bf16: bool = False, threads: int | None = None,
                 save_every_s: float = 600.0) -> torch.Tensor:
    """Latents (N, C, h, w) float16 of every frame of the store (a store of several views:
    each view encoded by ``codec``, their latents stacked along the channels,
    :func:`~iwsim.world_model.codecs.base.encode_views`). A chunk of frames whose
    bytes, encoder weights and precision match what ``cache`` was written for is not
    encoded again, view by view: a cache made for a store serves a store that extends it
    (``iwsim data merge`` of it and more: only the new frames are encoded), and one made
    for a store of several views serves a store of some of them (``iwsim data import
    --camera``). The cache then holds the latents of the last store that had frames to
    encode. While encoding, the frames encoded so far are written to the cache every
    ``save_every_s`` seconds, so that an encoding stopped part way (hours for a store of
    10,000 episodes in float32) resumes where it was. ``bf16``: encode under
    bf16 autocast (faster on CPUs with AVX-512-BF16 or AMX, latents within rounding of
    float32's: bench/results/speed). ``threads``: torch threads while encoding (default:
    every core this process may use); float16 storage halves the memory of large stores."""
    cameras = store_cameras(store.attrs, store.keys)
    views = len(cameras)
    n = store.array("img").shape[0]
    weights = encoder_key(codec) + ("|bf16" if bf16 else "")
    cached, old = _read_cache(cache, weights, store, n, chunk)
    # Filled in place (not a list joined at the end): the x4 latents of 1.85M frames are 7.6 GB.
    latents: torch.Tensor | None = None
    hashes: list[str] = []
    encoded, saved = False, time.monotonic()
    with torch_threads(threads or available_cores()):
        for k, i in enumerate(tqdm(range(0, n, chunk), desc="encode", disable=not progress)):
            frames = read_frames(store, slice(i, i + chunk))
            want = [hashlib.blake2b(np.ascontiguousarray(frames[..., 3 * v:3 * v + 3]).tobytes(),
                                    digest_size=12).hexdigest() for v in range(views)]
            hashes.append("|".join(want))
            z = _cached_chunk(cached, old[k] if k < len(old) else "", want, slice(i, i + len(frames)))
            if z is None:
                with torch.autocast(device.type, dtype=torch.bfloat16, enabled=bf16):
                    z = encode_views(codec, to_model(frames, views).to(device), views).float().cpu()
                encoded = True
            if latents is None:
                latents = torch.empty((n, *z.shape[1:]), dtype=torch.float16)
            latents[i:i + len(frames)] = z
            if cache is not None and encoded and time.monotonic() - saved > save_every_s and i + chunk < n:
                _write_cache(cache, latents[:i + len(frames)], weights, chunk, hashes)
                saved = time.monotonic()
    if latents is None:
        raise StoreError(f"{store.path} holds no frames to encode.")
    if cache is not None and encoded:
        _write_cache(cache, latents, weights, chunk, hashes)
    return latents


def _write_cache(cache: Path, latents: torch.Tensor, weights: str, chunk: int, hashes: list[str]) -> None:
    """Write a latent cache atomically: the latents of the chunks ``hashes`` names (the
    first chunks of a store, or all of them)."""
    cache.parent.mkdir(parents=True, exist_ok=True)
    tmp = cache.with_name(f".{cache.name}.{os.getpid()}.tmp")  # per process: two runs may share a cache
    meta = {"weights": weights, "chunk": str(chunk), "hashes": ",".join(hashes)}
    try:
        save_tensors({"latents": latents}, tmp, metadata=meta)
        os.replace(tmp, cache)
    finally:
        tmp.unlink(missing_ok=True)


def _cached_chunk(cached: torch.Tensor | None, have: str, want: list[str], rows: slice) -> torch.Tensor | None:
    """A chunk's latents from the cache, if it holds every view of the chunk: ``have`` is
    the cached chunk's view hashes ("|"-joined; "*": the chunk as it is), ``want`` the
    chunk's own, one per view; each view's latents are taken from the cached view of
    the same frames (None if one is missing)."""
    if cached is None or not have or len(cached) < rows.stop:
        return None
    if have == "*":
        return cached[rows]
    have_views = have.split("|")
    if any(w not in have_views for w in want) or cached.shape[1] % len(have_views):
        return None
    c = cached.shape[1] // len(have_views)
    return torch.cat([cached[rows, j * c:(j + 1) * c] for j in map(have_views.index, want)], 1)


def encoder_key(codec: Codec) -> str:
    """What a latent cache records of the encoder weights it was written with."""
    return ",".join(f"{v.double().sum().item():.10e}" for v in codec.encoder_parameters())


def _read_cache(cache: Path | None, weights: str, store: EpisodeStore, frames: int,
                chunk: int) -> tuple[torch.Tensor | None, list[str]]:
    """A latent cache's latents and per-chunk frame hashes, if written for these encoder
    weights (none otherwise). A cache written before the hashes, keyed by the store's path
    and frame count, counts for that store with every chunk matching ("*")."""
    if cache is None or not os.path.lexists(cache):
        return None, []
    if not cache.is_file():
        raise InputError(f"the latent cache {cache} is {'a directory' if cache.is_dir() else 'not a regular file'}; "
                         "expected the path of a .safetensors file (it is created if missing).")
    if not _is_latent_cache(cache):
        raise InputError(f"{cache} is not a latent cache (a .safetensors file of latents); it is left as it is: "
                         "choose another latent cache path, or remove it.")
    try:
        with safe_open(cache, "pt") as f:
            meta = f.metadata() or {}
            if meta.get("weights") == weights and meta.get("chunk") == str(chunk):
                hashes = meta["hashes"].split(",")
            elif meta.get("key") == f"{store.path}|{frames}|{weights}":
                hashes = ["*"] * -(-frames // chunk)
            else:
                return None, []
            latents = f.get_tensor("latents")
            # the hashes' chunks must all lie in the latents: the last one may be partial
            if latents.ndim != 4 or not (len(hashes) - 1) * chunk < latents.shape[0] <= len(hashes) * chunk:
                raise ValueError(f"{latents.shape[0]} latents for {len(hashes)} chunks of {chunk} frames")
            return latents, hashes
    except (SafetensorError, OSError, ValueError, KeyError, RuntimeError) as e:  # a cache: damaged is rebuilt
        log.warning("the latent cache %s is damaged (%s); encoding the store again", cache, " ".join(str(e).split()))
    return None, []


def _is_latent_cache(path: Path) -> bool:
    """Whether ``path`` starts like a latent cache: a safetensors header (a little-endian
    length, then that much JSON) naming ``latents``. Read with a cap, so any file is cheap."""
    with path.open("rb") as f:
        head = f.read(8)
        n = int.from_bytes(head, "little") if len(head) == 8 else 0
        if not 0 < n <= 1 << 24:
            return False
        try:
            header = json.loads(f.read(n))
        except ValueError:
            return False
    return isinstance(header, dict) and "latents" in header


def fit_store_novelty(wm: WorldModel, data: str | Path, progress: bool = True,
                      max_steps: int = NOVELTY_STEPS) -> Novelty:
    """The trust signal's Gaussian (:mod:`iwsim.world_model.novelty`) of the steps of the
    store ``data`` (the model's training data; whole episodes, evenly spread, up to
    ``max_steps`` steps): the step's newest latent, standardised by the model, and the
    normalised actions before and at it (at an episode's first step its first action
    stands for both, as after a reset)."""
    store = EpisodeStore.open(data, "r")
    other = None if wm.task is None else foreign_task(data, wm.task)
    if wm.task is not None and other is not None:
        raise InputError(f"{data} holds episodes of task {other!r} but the world model is of {wm.task.name!r}; "
                         "the trust signal is fitted on the model's own training data.")
    img = store.array("img")
    if img.shape[1] != wm.image_size:
        raise InputError(f"{data} holds {img.shape[1]}x{img.shape[1]} frames but the world model renders "
                         f"{wm.image_size}x{wm.image_size}.")
    if store_cameras(store.attrs, store.keys) != tuple(wm.cameras):
        raise InputError(f"{data} holds the views {list(store_cameras(store.attrs))} but the world model sees "
                         f"{list(wm.cameras)}.")
    ends = store.episode_ends.astype(np.int64)
    starts = np.concatenate([[0], ends[:-1]])
    every = max(1, int(np.ceil(ends[-1] / max_steps)))
    chosen = range(0, len(ends), every)
    actions = wm.normalize_actions(np.asarray(store.array(conditioning_key(store.keys))[:], dtype=np.float32)).cpu()
    feats = []
    for e in tqdm(chosen, desc="novelty", disable=not progress):
        idx = np.arange(starts[e], ends[e])
        z = wm.standardize(wm.encode(read_frames(store, slice(starts[e], ends[e])))).cpu()
        feats.append(novelty_features(z, actions[np.maximum(idx - 1, starts[e])], actions[idx]))
    return fit_novelty(torch.cat(feats))
