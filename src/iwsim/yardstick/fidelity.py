"""Open-loop fidelity on held-out episodes (``bench/ablate_dynamics.py eval``'s table, the
yardstick's held-out play part and the shipped checkpoint's ``fidelity``): one-step errors
from true latents against copying the previous one, the open-loop latent error and the
action gap (another episode's actions against the true ones), PSNR beside repeating the
first frame, and the pushers and T-push's block as the decoded frames show them."""

from __future__ import annotations

from typing import TypeVar

import numpy as np
import torch

from iwsim.core.errors import InputError
from iwsim.core.metrics import psnr
from iwsim.data.frames import to_model
from iwsim.data.store import EpisodeStore, conditioning_key
from iwsim.envs.pusht import pixels
from iwsim.envs.pusht.sim import VIEW_HALF
from iwsim.world_model import WorldModel

STEPS = (1, 5, 10, 20, 32)
POSE_STEPS = (10, 20, 32)
CHANGED = 0.1  # a latent cell changed when a standardised channel moved by more (as in training)
CHUNK = 512  # frames (or windows) a network pass takes: 20 episodes x 192 steps in one pass peaked at 6.8 GB


class Episodes:
    """The evaluation store's episodes as arrays: frames, conditioning actions, pusher
    positions and block poses; all episodes cut to the shortest length."""

    def __init__(self, path: str, n: int) -> None:
        store = EpisodeStore.open(path)
        ends = store.episode_ends.astype(int)
        starts = np.concatenate([[0], ends[:-1]])[:n]
        length = int((ends[:n] - starts).min())
        idx = starts[:, None] + np.arange(length)
        get = lambda k: np.asarray(store.array(k).oindex[idx.ravel()]).reshape(*idx.shape, -1)  # noqa: E731
        self.img = get("img").reshape(*idx.shape, *store.array("img").shape[1:])
        self.actions = get(conditioning_key(store.keys)).astype(np.float32)
        self.state, self.pose = get("state"), get("block_pose")
        self.n, self.length = idx.shape


Metres = TypeVar("Metres", np.ndarray, np.floating)


def px(metres: Metres) -> Metres:
    """Distances on T-push's table (m) as pixels of a 64-pixel frame."""
    return metres * 64 / (2 * VIEW_HALF)


def block_errors(frames: np.ndarray, poses: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per frame (N, H, W, 3): block position error (px), yaw error (deg) against poses
    (N, 3), and whether a T fits (IoU >= 0.8); a frame without a T counts as lost (NaN)."""
    pos, yaw, fits = [], [], []
    for f, p in zip(frames, poses):
        est = pixels.estimate_block_pose(f)
        ok = est.found and est.fit_iou >= 0.8
        fits.append(ok)
        pos.append(px(np.linalg.norm(est.pose[:2] - p[:2])) if est.found else np.nan)
        d = (est.pose[2] - p[2] + np.pi) % (2 * np.pi) - np.pi
        yaw.append(abs(np.degrees(d)) if est.found else np.nan)
    return np.array(pos), np.array(yaw), np.array(fits)


@torch.inference_mode()
def score(wm: WorldModel, ep: Episodes, horizon: int, seed: int = 0
          ) -> tuple[dict, tuple[np.ndarray, np.ndarray], np.ndarray]:
    """Everything the table reports for one model; its PSNR per step (horizon,) and that of
    repeating the first frame; its frames (E, S, H, W, 3)."""
    if horizon < max(STEPS):
        raise InputError(f"the horizon must be at least {max(STEPS)} steps (the table reports steps up to "
                         f"{max(STEPS)}), got {horizon}.")
    k = wm.cfg.dynamics.context
    flat = ep.img.reshape(-1, *ep.img.shape[2:])
    z = wm.standardize(torch.cat([wm.encode(flat[i:i + CHUNK]) for i in range(0, len(flat), CHUNK)])
                       .unflatten(0, (ep.n, ep.length)))
    a = wm.normalize_actions(ep.actions)
    out: dict = {}
    # Teacher-forced one step, from windows of true latents (padded at the start), every
    # other frame.
    t_idx = torch.arange(0, ep.length - 1, 2)
    win = (t_idx[:, None] + torch.arange(-(k - 1), 1)).clamp_min(0)
    ctx = z[:, win].flatten(0, 1)  # (E*T, K, C, h, w)
    ctx_actions = a[:, (win[:, 1:] - 1).clamp_min(0)].flatten(0, 1)  # (E*T, K-1, A): frame t came from action t-1
    now = a[:, t_idx].flatten(0, 1)
    true, prev = z[:, t_idx + 1].flatten(0, 1), z[:, t_idx].flatten(0, 1)
    changed = ((true - prev).abs().amax(1, keepdim=True) > CHANGED).expand_as(true)

    def one_step() -> torch.Tensor:
        """The standardised next latents (E*T, C, h, w), the same noise at every call (window
        i's from seed + i), CHUNK windows a pass."""
        parts = []
        for lo in range(0, len(ctx), CHUNK):
            hi = min(lo + CHUNK, len(ctx))
            state = wm.reset_state(wm.unstandardize(ctx[lo:hi]), ctx_actions[lo:hi], range(seed + lo, seed + hi),
                                   latents=True)
            parts.append(wm.standardize(wm.step_state(state, now[lo:hi], latents=True)[1]))
        return torch.cat(parts)

    reencode, wm.reencode = wm.reencode, False  # one step from true latents: nothing to feed back
    for lab in (0.0, wm.cfg.context_label, 0.3):
        wm.context_label = lab
        err = (one_step() - true) ** 2
        out[f"one_step_label{lab:g}"] = err.mean().item()
        if lab == wm.cfg.context_label:
            out["one_step"], out["one_step_changed"] = err.mean().item(), err[changed].mean().item()
    wm.context_label, wm.reencode = wm.cfg.context_label, reencode
    copy = (prev - true) ** 2
    out["copy_prev"], out["copy_prev_changed"] = copy.mean().item(), copy[changed].mean().item()
    # Open loop from the first frame: true and shuffled actions (another episode's).
    true_z = z[:, 1:horizon + 1]

    def rollout(actions: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """The standardised latents (E, S, C, h, w) the rollout continues from (with
        ``wm.reencode``, the encodings of the decoded frames) and its predictions (E, S, C, h, w),
        as ``encode`` gives them."""
        state = wm.reset_state(wm.unstandardize(z[:, :1]), seed=seed, latents=True)
        context, predicted = [], []
        for i in range(horizon):
            state, latent = wm.step_state(state, actions[:, i], latents=True)
            context.append(state.context[:, -1])
            predicted.append(latent)
        return torch.stack(context, 1), torch.stack(predicted, 1)

    pred, predicted = rollout(a)
    err = ((pred - true_z) ** 2).mean((2, 3, 4))  # (E, S)
    shuf = ((rollout(a.roll(1, 0))[0] - true_z) ** 2).mean((2, 3, 4))
    for s in STEPS:
        out[f"latent_err_{s}"] = err[:, s - 1].mean().item()
    out["action_gap_5"] = (shuf[:, 4].mean() / err[:, 4].mean()).item()
    out["action_gap_10"] = (shuf[:, 9].mean() / err[:, 9].mean()).item()
    # Frames: PSNR, pushers and the block; the predictions decoded with fresh generators.
    per = max(1, CHUNK // horizon)  # episodes decoded a pass
    frames = torch.cat([wm.decode_latents(predicted[i:i + per], [torch.Generator(wm.device).manual_seed(seed + j)
                                                                 for j in range(i, min(i + per, ep.n))])
                        for i in range(0, ep.n, per)]).clamp(-1, 1)
    truth = to_model(ep.img[:, 1:horizon + 1]).to(frames.device)
    first = to_model(ep.img[:, :1]).expand_as(truth)
    p = psnr(((frames + 1) / 2).flatten(0, 1), ((truth + 1) / 2).flatten(0, 1)).view(ep.n, horizon)
    p0 = psnr(((first + 1) / 2).flatten(0, 1), ((truth + 1) / 2).flatten(0, 1)).view(ep.n, horizon)
    for lo, hi in ((1, 32), (1, horizon)):
        out[f"psnr_{lo}_{hi}"] = p[:, lo - 1:hi].mean().item()
        out[f"psnr_first_{lo}_{hi}"] = p0[:, lo - 1:hi].mean().item()
    u8 = ((frames.clamp(-1, 1) + 1) * 127.5).round().byte().movedim(-3, -1).numpy()  # (E, S, H, W, 3)
    xy, peak = pixels.pusher_peaks(u8)
    perr = px(np.linalg.norm((xy - ep.state[:, 1:horizon + 1]).reshape(ep.n, horizon, 2, 2), axis=-1))
    first_perr = px(np.linalg.norm((ep.state[:, :1] - ep.state[:, 1:horizon + 1]).reshape(ep.n, horizon, 2, 2),
                                   axis=-1))
    for s in POSE_STEPS:
        out[f"pusher_err_{s}"] = float(np.median(perr[:, s - 1]))
        out[f"pusher_err_first_{s}"] = float(np.median(first_perr[:, s - 1]))
    out["pusher_peak_min"] = float(np.median(peak.min(-1), 0).min())  # worst step of the median episode
    out["pusher_visible"] = float((peak >= 0.8).mean())
    for s in POSE_STEPS:
        pos, yaw, _ = block_errors(u8[:, s - 1], ep.pose[:, s])
        pos0, yaw0, _ = block_errors(ep.img[:, 0], ep.pose[:, s])
        out[f"block_pos_{s}"], out[f"block_yaw_{s}"] = float(np.nanmedian(pos)), float(np.nanmedian(yaw))
        out[f"block_pos_first_{s}"], out[f"block_yaw_first_{s}"] = float(np.median(pos0)), float(np.median(yaw0))
    fit_steps = np.arange(0, horizon, 4)
    _, _, fits = block_errors(u8[:, fit_steps].reshape(-1, *u8.shape[2:]), ep.pose[:, fit_steps + 1].reshape(-1, 3))
    out["t_found"] = float(fits.mean())
    return out, (p.mean(0).numpy(), p0.mean(0).numpy()), u8
