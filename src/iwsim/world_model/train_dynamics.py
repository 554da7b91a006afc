"""Stage 2 training: the latent dynamics on the frozen stage-1 encoder (``iwsim train dynamics``).

A training sequence holds the K latents of a window and the n frames after it. The model
predicts them one after the other, each from a window that holds its own earlier
predictions (training on the model's own unrolled predictions, as Self-Forcing and
DIAMOND's autoregressive training do; n grows over training, ``cfg.unroll``). Each
prediction's context gets Gaussian noise of a random std in the standardised units the
network sees (``cfg.context_sigma``), and the network is told that std. The loss weights
latent cells that change ``1 + cfg.changed_weight`` times more than static ones.

The gradient flows through the fed-back predictions (back-propagation through the whole
unroll, or truncated every ``cfg.unroll_grad_every`` predictions) unless ``cfg.unroll_grad``
is off. The benchmark's baselines train in the same
way with another ``objective`` (see ``iwsim.core.config.VARIANTS``); the "edm" objective's
fed-back context is a real sample (Euler steps, no gradient), since its one-pass
estimate is not what inference produces.

The conditioning actions are the motion the robot executed: ``data/target`` when the
store has it (the task's rate-limited setpoints), else ``data/action``.

With ``cfg.predict_state`` the network also takes the robot's own state (``data/state``)
and predicts it after each prediction (``Dynamics.predict_state``, from the predicted
latent); the state of the first prediction is the recorded one, each later one the
previous prediction, cut from the gradient where the latents are. Its loss, an MSE on
the normalised state times ``cfg.state_weight``, is added to each prediction's; with
``cfg.state_contact_weight`` the steps where the recorded state stands apart from what its
setpoint sets (contact holds the robot back) weigh more.

Every checkpoint of a dynamics run is a complete world model (autoencoder + dynamics +
action normalisation + config), loadable with :meth:`iwsim.WorldModel.load`.
"""

from __future__ import annotations

import logging
from dataclasses import replace
from pathlib import Path

import imageio.v2 as imageio
import numpy as np
import torch
from torch import nn

from iwsim.core import trainer
from iwsim.core.checkpoint import last_checkpoint, load_json, load_tensors, resolve_checkpoint
from iwsim.core.errors import InputError
from iwsim.core.metrics import psnr
from iwsim.core.normalize import unscale
from iwsim.data.frames import read_frames, to_model, to_uint8
from iwsim.data.views import tile_views
from iwsim.envs.registry import task_from_store
from iwsim.world_model.denoiser import Denoiser
from iwsim.world_model.dynamics import Dynamics, add_state, widen_window
from iwsim.world_model.dynamics_data import DynamicsData, DynBatch
from iwsim.world_model.model import KIND, WorldModel, complete_run_config
from iwsim.world_model.objectives import Levels
from iwsim.world_model.presets import FINE_TUNE_FIELDS, OBJECTIVES, DynamicsStageConfig

log = logging.getLogger(__name__)


class DynamicsTrainModule(nn.Module):
    """forward(batch) -> the loss of the n unrolled predictions of each sequence under the
    config's objective (see the module docstring)."""

    def __init__(self, dynamics: Dynamics, cfg: DynamicsStageConfig) -> None:
        super().__init__()
        if cfg.objective not in OBJECTIVES:
            raise InputError(f"unknown objective {cfg.objective!r}; expected one of {', '.join(OBJECTIVES)}.")
        if cfg.state_contact_weight and not dynamics.cfg.state_action_scale:
            raise InputError("state_contact_weight needs a robot state that holds the action's points (the setpoint "
                             "says where the robot would stand); this model's does not.")
        self.dynamics, self.cfg = dynamics, cfg
        self.denoiser = Denoiser(dynamics, cfg)
        # Whether the loss's one-pass estimate is exactly what inference generates (then it
        # is fed back with its gradient); otherwise a real sample is fed back.
        one_jump = cfg.jumps == 1 and cfg.top_fraction == 1 and cfg.zero_fraction == 1
        self.feeds_estimate = cfg.objective == "regression" or (cfg.objective == "consistency" and one_jump)

    def compile_targets(self) -> tuple[nn.Module, ...]:
        """What ``--compile`` compiles: the network, called once per unrolled prediction (the
        unroll loop itself would be traced into one graph per unroll length)."""
        return (self.dynamics,)

    def forward(self, batch: DynBatch) -> tuple[torch.Tensor, dict[str, float]]:
        per, state_err = self.unroll(batch)  # (B, n) each
        out = {"loss_first": per[:, 0].mean().item(), "loss_last": per[:, -1].mean().item(),
               "unroll": float(per.shape[1])}
        if state_err is not None:
            out["state_mse"] = state_err.mean().item()
        return per.mean(), out

    def unroll(self, batch: DynBatch) -> tuple[torch.Tensor, torch.Tensor | None]:
        """The loss (B, n) of each of the n predictions of each sequence (the state's
        included), and the state's squared error (B, n) alone (None without the state)."""
        cfg = self.cfg
        k = cfg.dynamics.context
        n = batch.z.shape[1] - k
        ctx = batch.z[:, :k]
        with_state = bool(cfg.dynamics.state_dim)
        state = batch.states[:, 0] if with_state and batch.states is not None else None
        if with_state and state is None:
            raise InputError("this dynamics network takes the robot's state; the batch holds none.")
        losses, state_errs = [], []
        for u in range(n):
            sig = batch.ctx_sigma[:, u]
            ctx_in = ctx + sig.view(-1, 1, 1, 1, 1) * batch.ctx_eps[:, u]
            acts = batch.actions[:, u:u + 2]
            target = batch.z[:, k + u]
            levels = Levels(batch.t[:, u], batch.s[:, u], batch.sigma[:, u])
            err, pred = self.denoiser.loss(target, ctx_in, sig, acts, levels, batch.eps[:, u], state)
            changed = (target - batch.z[:, k + u - 1]).abs().amax(1, keepdim=True) > cfg.changed_threshold
            loss = (err * (1 + cfg.changed_weight * changed)).mean((1, 2, 3))
            if not self.feeds_estimate and (u < n - 1 or state is not None):
                with torch.no_grad():
                    pred = self.denoiser.sample(ctx_in, sig, acts, batch.feed_eps[:, u], state=state)
            cut = not cfg.unroll_grad or (cfg.unroll_grad_every and (u + 1) % cfg.unroll_grad_every == 0)
            if state is not None:
                assert batch.states is not None  # with_state
                state = self.dynamics.predict_state(pred, ctx[:, -1], acts, state)
                truth = batch.states[:, u + 1]
                state_errs.append(((state - truth) ** 2).mean(1))
                weight: float | torch.Tensor = cfg.state_weight
                if cfg.state_contact_weight:  # steps where contact holds the robot back from its setpoint
                    held = (self.dynamics.setpoint_state(acts) - truth).abs().amax(1) > cfg.state_contact_gap
                    weight = weight * (1 + cfg.state_contact_weight * held)
                loss = loss + weight * state_errs[-1]
                state = state.detach() if cut else state
            losses.append(loss)
            if u == n - 1:
                break
            ctx = torch.cat([ctx[:, 1:], (pred.detach() if cut else pred)[:, None]], 1)
        return torch.stack(losses, 1), torch.stack(state_errs, 1) if state_errs else None


@torch.no_grad()
def evaluate_open_loop(wm: WorldModel, data: DynamicsData, episodes: int, steps: int,
                       ) -> tuple[dict[str, float], torch.Tensor, torch.Tensor]:
    """Open-loop rollouts of the first ``episodes`` held-out episodes from their first
    frame under the recorded actions, for up to ``steps`` steps: latent MSE (standardised
    units) and decoded PSNR per step (and, for a model that predicts the robot's state, its
    mean absolute error in the data's units, ``state_mae``, the rollout started from the
    recorded state), and the true and predicted images (E, S, 3, H, W)."""
    eps = [e for e in data.heldout_episodes if data.ends[e] - data.starts[e] > 1][:episodes]
    steps = min([steps] + [int(data.ends[e] - data.starts[e]) - 1 for e in eps])
    first = torch.as_tensor(data.starts[eps])
    robot = data.states[first] if wm.state_dim else None
    state = wm.reset_state(data.latents[first][:, None], seed=0, latents=True, state=robot)
    preds, robots = [], []
    for k in range(steps):
        state, z = wm.step_state(state, data.actions[first + k], latents=True)
        preds.append(z)
        r = wm.robot_state(state)
        if r is not None:
            robots.append(r)
    pred = torch.stack(preds, 1)  # (E, S, C, h, w)
    true_idx = first[:, None] + torch.arange(1, steps + 1)
    true = data.latents[true_idx].to(wm.device)
    frames = wm.decode_latents(pred, state.generators)
    truth = to_model(read_frames(data.store, true_idx.flatten().numpy()), wm.views).to(wm.device)
    truth = truth.unflatten(0, (len(eps), steps))
    p = psnr((frames.flatten(0, 1) + 1) / 2, (truth.flatten(0, 1) + 1) / 2).view(len(eps), steps)
    out = {"latent_mse": ((pred - true) ** 2).mean().item() / data.latent_scale ** 2,  # standardised units
           "psnr": p.mean().item(),
           f"psnr_step{steps}": p[:, -1].mean().item()}
    if wm.state_dim:  # the robot's predicted state against the recorded one, in the data's units
        recorded = unscale(data.states[true_idx], torch.as_tensor(data.state_low), torch.as_tensor(data.state_high))
        out["state_mae"] = float(np.abs(np.stack(robots, 1) - recorded.numpy()).mean())
    return out, truth, frames


def write_rollout_strip(path: Path, truth: torch.Tensor, frames: torch.Tensor) -> None:
    """A PNG of episode 0: up to 8 steps of the truth above the same steps predicted,
    from images (E, S, 3, H, W) in [-1, 1]."""
    steps = truth.shape[1]
    cols = np.linspace(0, steps - 1, min(8, steps)).round().astype(int)
    rows = [np.concatenate(list(tile_views(to_uint8(v[0, cols]))), axis=1) for v in (truth, frames)]
    path.parent.mkdir(parents=True, exist_ok=True)
    imageio.imwrite(path, np.concatenate(rows, axis=0))


def longest_unroll(curriculum: tuple[tuple[int, int], ...], n: int) -> tuple[tuple[int, int], ...]:
    """The unroll curriculum ``curriculum`` ((from step, predictions), ...) with ``n``
    predictions at its longest: its stages below n kept, n from the step its first stage of n
    or more began (300 steps after its last stage where none has that many)."""
    kept = tuple((k, m) for k, m in curriculum if m < n)
    later = [k for k, m in curriculum if m >= n]
    start = min(later) if later else max(k for k, _ in curriculum) + 300
    return kept + ((start if kept else 0, n),)


def run_config(cfg: DynamicsStageConfig, init: WorldModel | None = None,
               context: int | None = None, unroll: int | None = None) -> DynamicsStageConfig:
    """The stage-2 config a run trains with: ``cfg``; for a fine-tune of ``init``, the model's
    own (network, objective, context noise, sampling) with ``cfg.train``, every sequence
    unrolled as long as its curriculum's longest (``unroll`` when given), and the robot's
    state or another sampling, unroll gradient or context noise (``FINE_TUNE_FIELDS``) where
    ``cfg`` sets them; with ``context`` latents in the window when given. From scratch, ``unroll``
    sets the curriculum's longest (:func:`longest_unroll`)."""
    if init is not None:
        default = DynamicsStageConfig()
        longest = unroll or (max(n for _, n in init.cfg.unroll) if init.cfg.unroll else 1)
        cfg = replace(init.cfg, train=cfg.train, unroll=((0, longest),),
                      predict_state=cfg.predict_state or init.cfg.predict_state,
                      **{k: getattr(cfg if cfg.predict_state else init.cfg, k)
                         for k in ("state_weight", "state_contact_weight", "state_contact_gap")},
                      **{k: getattr(cfg if getattr(cfg, k) != getattr(default, k) else init.cfg, k)
                         for k in FINE_TUNE_FIELDS})
    if context is not None:
        cfg = replace(cfg, dynamics=replace(cfg.dynamics, context=context))
    if unroll is not None and init is None:
        cfg = replace(cfg, unroll=longest_unroll(cfg.unroll or ((0, 1),), unroll))
    return cfg


class DynamicsTask:
    """Stage 2 for the generic training loop: the data (:class:`DynamicsData`), the loss
    module, open-loop evaluation of held-out episodes, and the world model it exports.

    With ``init`` (a world-model checkpoint, or a run: its last) training fine-tunes it: its autoencoder,
    normalisation, stage-2 config (network, objective, context noise) and weights are the
    start, only ``cfg.train`` is taken from ``cfg`` (``ae_path`` is ignored), and the
    unroll curriculum, which the model has been through, starts at its longest. ``context``
    (latents in the window) replaces the config's; a fine-tuned model's window is widened
    to it (:func:`~iwsim.world_model.dynamics.widen_window`). ``resume``: the run directory;
    a run from scratch that has a checkpoint there keeps its latent standardisation
    (:func:`run_latent_norm`)."""

    def __init__(self, cfg: DynamicsStageConfig, data: str | Path, ae_path: str | Path | None,
                 device: torch.device = torch.device("cpu"), progress: bool = True,
                 latent_cache: Path | None = None, init: str | Path | None = None,
                 context: int | None = None, resume: Path | None = None, unroll: int | None = None) -> None:
        wm = None
        if init is not None:
            init = resolve_checkpoint(init)  # a checkpoint, or a run's last one
            wm = WorldModel.load(init, device)
            ae_path = init
        cfg = run_config(cfg, wm, context, unroll)
        if ae_path is None:
            raise InputError("a dynamics task needs a stage-1 checkpoint (ae_path) or a world model to fine-tune "
                             "(init).")
        self.data = DynamicsData(cfg, data, ae_path, device, progress, latent_cache, init=wm,
                                 latent_norm=None if wm is not None or resume is None else run_latent_norm(resume))
        self.cfg = cfg = self.data.cfg
        with torch.random.fork_rng():  # initial weights from the run's seed, global RNG untouched
            torch.manual_seed(cfg.train.seed)
            self.module = DynamicsTrainModule(Dynamics(cfg.dynamics), cfg)
        if wm is not None:
            weights = widen_window(wm.dynamics.state_dict(), wm.cfg.dynamics, cfg.dynamics.context)
            if cfg.dynamics.state_dim and not wm.cfg.dynamics.state_dim:
                weights = add_state(weights, wm.cfg.dynamics, self.module.dynamics)
            self.module.dynamics.load_state_dict(weights)
        self.init = None if init is None else str(init)
        # The robot task the checkpoints record: the fine-tuned model's, else the store's.
        d = self.data
        self.task = wm.task if wm is not None and wm.task is not None else task_from_store(
            data, d.action_low.tolist(), d.action_high.tolist())

    def batch(self, step: int, generator: torch.Generator, part: slice, device: torch.device) -> DynBatch:
        return self.data.batch(step, generator, part, device)

    def world_model(self, dynamics: Dynamics) -> WorldModel:
        d = self.data
        wm = WorldModel(d.codec, dynamics, self.cfg, d.action_low.tolist(), d.action_high.tolist(), d.latent_mean,
                        d.latent_scale, d.state_low.tolist(), d.state_high.tolist())
        wm.task = self.task
        return wm

    def evaluate(self, module: DynamicsTrainModule, step: int, out_dir: Path) -> dict[str, float]:
        """Open-loop rollouts of held-out episodes (:func:`evaluate_open_loop`); a strip of
        the first is written to ``out_dir/rollout_<step>.png``."""
        wm = self.world_model(module.dynamics).eval()
        out, truth, frames = evaluate_open_loop(wm, self.data, self.cfg.eval_episodes, self.cfg.eval_steps)
        write_rollout_strip(out_dir / f"rollout_{step:08d}.png", truth, frames)
        return out

    def config(self, data: str | Path) -> dict:
        """The run's config.json: a complete world-model description plus where it came from."""
        wm = self.world_model(self.module.dynamics)
        return {**wm.describe(), "data": str(data), "ae_checkpoint": str(self.data.ae_path),
                "init": self.init, "split": self.data.split()}

    def export(self, module: DynamicsTrainModule) -> dict[str, torch.Tensor]:
        return self.world_model(module.dynamics).export()


def run_latent_norm(run: Path) -> tuple[torch.Tensor, float] | None:
    """The latent standardisation (mean, scale) of the dynamics run in ``run``, from its
    config and its last checkpoint; None where it has no checkpoint yet (or is not one)."""
    last = last_checkpoint(run / "checkpoints")
    if last is None or not (run / "config.json").is_file():
        return None
    scale = load_json(run / "config.json").get("latent_norm", {}).get("scale")
    tensors = load_tensors(last / "model.safetensors")
    if not isinstance(scale, int | float) or "latent_mean" not in tensors:
        return None
    return tensors["latent_mean"], float(scale)


def train_dynamics(cfg: DynamicsStageConfig, data: str | Path, ae: str | Path | None, out: str | Path, *,
                   device: torch.device, force: bool = False, progress: bool = True,
                   latent_cache: str | Path | None = None, init: str | Path | None = None,
                   context: int | None = None, compile: bool = False, unroll: int | None = None) -> dict[str, float]:
    """Train (or resume) stage 2 into the run directory ``out``, from scratch on the
    stage-1 checkpoint ``ae`` or, with ``init``, fine-tuning that world model, with a
    window of ``context`` latents and ``unroll`` predictions at the longest if given (see
    :class:`DynamicsTask`). The frozen encoder's latents are cached in ``latent_cache``
    (default: the run directory), which runs on the same store and encoder can share; a cache
    of other frames or weights is rewritten. ``compile``: ``torch.compile`` the dynamics
    network (a speed setting only)."""
    if (ae is None) == (init is None):
        raise InputError("train dynamics takes either --ae (train from scratch) or --init (fine-tune), not both.")
    cache = Path(latent_cache) if latent_cache is not None else Path(out) / "latents.safetensors"
    task = DynamicsTask(cfg, data, ae, device, progress, latent_cache=cache, init=init, context=context,
                        resume=Path(out), unroll=unroll)
    config = task.config(data)
    assert config["kind"] == KIND
    return trainer.train(task, task.cfg.train, Path(out), config, device=device, force=force, progress=progress,
                         complete=complete_run_config, compile=compile)
