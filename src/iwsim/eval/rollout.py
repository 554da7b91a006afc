"""Open-loop rollouts of recorded episodes: the world model under the recorded actions,
against the recorded frames (the paper's video-prediction protocol). A model of several
views is rolled out on every view of the episodes (stacked along the channels): PSNR and
SSIM are the views' mean, the task's score reads the first view, videos show the views one
above the other."""

from __future__ import annotations

import json
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from iwsim.core.errors import InputError
from iwsim.core.metrics import psnr, ssim
from iwsim.data.frames import to_model
from iwsim.data.store import EpisodeStore, conditioning_key
from iwsim.data.views import stack_views, store_cameras, tile_views, unstack_views, view_keys
from iwsim.envs.registry import foreign_task, task_of
from iwsim.eval.figures import plot_psnr
from iwsim.eval.video import score_bar, upscale, write_video
from iwsim.world_model import WorldModel


@dataclass
class OpenLoop:
    """Truth and prediction (E, S, H, W, 3 x views) uint8 for E episodes and S steps, with
    per-step PSNR and SSIM (E, S) and the task's pixel score (T-push: the IoU) of both
    videos (E, S), None when the task has no scorer."""

    episodes: list[int]
    truth: np.ndarray
    pred: np.ndarray
    psnr: np.ndarray
    ssim: np.ndarray
    iou_true: np.ndarray | None
    iou_pred: np.ndarray | None

    def select(self, i: int) -> OpenLoop:
        """Episode ``i`` of this result alone."""
        iou_true, iou_pred = (None if v is None else v[i:i + 1] for v in (self.iou_true, self.iou_pred))
        return OpenLoop([self.episodes[i]], self.truth[i:i + 1], self.pred[i:i + 1], self.psnr[i:i + 1],
                        self.ssim[i:i + 1], iou_true, iou_pred)

    def summary(self) -> dict[str, float | None]:
        return {"psnr": float(self.psnr.mean()), "ssim": float(self.ssim.mean()),
                "psnr_last": float(self.psnr[:, -1].mean()), "ssim_last": float(self.ssim[:, -1].mean()),
                "iou_abs_err": None if self.iou_true is None else float(np.abs(self.iou_pred - self.iou_true).mean())}


def frame_scores(truth: np.ndarray, pred: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """PSNR and SSIM of uint8 frames (..., H, W, 3) on [0, 1] images; each shaped (...).
    Frames of several views (..., H, W, 3V): the mean over the views."""
    lead, views = truth.shape[:-3], truth.shape[-1] // 3
    a = (to_model(np.stack(unstack_views(truth, views), -4).reshape(-1, *truth.shape[-3:-1], 3)) + 1) / 2
    b = (to_model(np.stack(unstack_views(pred, views), -4).reshape(-1, *pred.shape[-3:-1], 3)) + 1) / 2
    return (psnr(a, b).numpy().reshape(*lead, views).mean(-1), ssim(a, b).numpy().reshape(*lead, views).mean(-1))


def open_loop(wm: WorldModel, store: EpisodeStore, episodes: list[int], steps: int, context: int = 1,
              seed: int = 0, progress: bool = False) -> OpenLoop:
    """Roll ``wm`` out on ``episodes`` of ``store`` (batched): the first ``context`` frames
    (and the actions between them) are the context; then ``steps`` recorded actions."""
    if context < 1 or steps < 1:
        raise InputError(f"context and steps must be >= 1, got {context} and {steps}.")
    task = task_of(wm)  # its pixel scorer, if it has one: never T-push's IoU on another robot's frames
    other = foreign_task(store.path, task)
    if other is not None:
        raise InputError(f"{store.path} holds episodes of task {other!r} but the world model is of {task.name!r}; "
                         f"roll it out on episodes of {task.name!r}.")
    if store_cameras(store.attrs, store.keys) != tuple(wm.cameras):
        raise InputError(f"{store.path} holds the views {list(store_cameras(store.attrs))} but the world model sees "
                         f"{list(wm.cameras)}.")
    keys = list(view_keys(tuple(wm.cameras)).values())
    eps = [store.episode(e) for e in episodes]  # raises on a bad index
    eps = [{**ep, "img": stack_views([ep[k] for k in keys])} for ep in eps]
    for e, ep in zip(episodes, eps):
        if len(ep["img"]) < context + steps:
            raise InputError(f"episode {e} of {store.path} has {len(ep['img'])} frames; {context} context frames "
                             f"and {steps} steps need {context + steps} (use --steps {len(ep['img']) - context}).")
    frames = np.stack([ep["img"][:context] for ep in eps])
    key = conditioning_key(store.keys)  # the executed motion when the store has it
    actions = np.stack([ep[key][context - 1:context - 1 + steps] for ep in eps])
    ctx_actions = np.stack([ep[key][:context - 1] for ep in eps]) if context > 1 else None
    truth = np.stack([ep["img"][context:context + steps] for ep in eps])
    pred = wm.rollout(frames, actions, ctx_actions, seed=seed, progress=progress)
    p, s = frame_scores(truth, pred)
    return OpenLoop(list(episodes), truth, pred, p, s, task.score(truth[..., :3]), task.score(pred[..., :3]))


def against_mujoco(wm: WorldModel, seed: int, steps: int, policy: str = "expert", noise_seed: int = 0,
                   progress: bool = False) -> OpenLoop:
    """Roll ``wm`` out from its task's simulator's initial frame for ``seed`` under a
    scripted policy's actions (the policy sees the simulator), against the simulator's
    frames of the same actions; the model is conditioned on the motion the simulator
    executed (the recorded ``target``)."""
    if steps < 1:
        raise InputError(f"steps must be >= 1, got {steps}.")
    task = task_of(wm)
    if not task.has_ground_truth:
        raise InputError(f"the world model's task {task.name!r} has no simulator to compare it with.")
    cameras = tuple(wm.cameras)  # frames 0..steps of every view the model sees, and the actions between
    ep = task.record_episode(policy, seed, steps + 1, wm.image_size, **({} if cameras == ("top",) else
                                                                        {"cameras": cameras}))
    frames = stack_views([ep[k] for k in view_keys(cameras).values()]) if len(cameras) > 1 else ep["img"]
    truth = frames[None, 1:]
    pred = wm.rollout(frames[None, 0], ep["target"][None, :steps], seed=noise_seed, progress=progress)
    p, s = frame_scores(truth, pred)
    return OpenLoop([seed], truth, pred, p, s, task.score(truth[..., :3]), task.score(pred[..., :3]))


def write_side_by_side(result: OpenLoop, out: str | os.PathLike, fps: float = 10.0, scale: int = 4) -> Path:
    """Video of episode 0 of ``result``: truth | prediction, with a PSNR bar (10-40 dB,
    green from 25 dB) under each frame; per-step scores in ``<out>.json`` and a plot in
    ``<out>_psnr.png``."""
    out = Path(out)
    truth, pred = upscale(tile_views(result.truth[0]), scale), upscale(tile_views(result.pred[0]), scale)
    gap = np.full((*truth.shape[:2], 4, 3), 255, np.uint8)
    video = np.concatenate([truth, gap, pred], axis=2)
    bar = score_bar((result.psnr[0] - 10) / 30, video.shape[2], 8, 0.5)
    write_video(out, np.concatenate([video, bar], axis=1), fps)
    first = result.select(0)
    scores = {"episode": first.episodes[0], "steps": int(first.psnr.shape[1]), **first.summary(),
              "psnr_per_step": first.psnr[0].round(3).tolist(), "ssim_per_step": first.ssim[0].round(4).tolist(),
              **({"iou_true": None, "iou_pred": None} if first.iou_true is None or first.iou_pred is None else
                 {"iou_true": first.iou_true[0].round(4).tolist(), "iou_pred": first.iou_pred[0].round(4).tolist()})}
    tmp = out.with_name(f".{out.stem}.json.tmp")
    tmp.write_text(json.dumps(scores, indent=1) + "\n")
    os.replace(tmp, out.with_suffix(".json"))
    plot_psnr({"episode " + str(result.episodes[0]): result.psnr[0]}, out.with_name(f"{out.stem}_psnr.png"))
    return out
