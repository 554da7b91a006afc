"""``iwsim bench``: world models side by side on the paper's protocol.

- Accuracy: open-loop rollouts of held-out episodes (context = the first frame, then the
  recorded actions) scored against the recorded frames with the seven video metrics (MSE,
  PSNR, SSIM, UIQI, LPIPS, FID, FVD) and the task fidelity |IoU_pred - IoU_true| of the
  pixel scorer; mean +- std over episodes, as the paper's table.
- Speed, measured in one process one model after another: single-stream steps/s
  (dynamics + decode at batch 1) and frames/s at a batch of 64.
- Stability: one long rollout per model under the scripted play policy's actions, driven
  by MuJoCo (which renders the same actions), with frame statistics and block
  detectability over time.
- A figure of predicted and true frames at five steps from 0 to the horizon (0, 48, ..., 192).

LPIPS, FID and FVD need pretrained networks (:mod:`iwsim.eval.features`); when their
weights are missing the report says so in their columns instead of giving a number.
"""

from __future__ import annotations

import logging
import os
import platform
import time
from pathlib import Path
from typing import Any

import numpy as np
import torch

from iwsim.core.checkpoint import check_output_dir, load_json, resolve_checkpoint, write_json_atomic
from iwsim.core.errors import InputError
from iwsim.data.frames import split_episodes
from iwsim.data.store import EpisodeStore
from iwsim.envs.registry import task_of
from iwsim.eval import features as feats
from iwsim.eval.figures import curves_figure, frames_figure, stability_figure
from iwsim.eval.profiling import speed, stability
from iwsim.eval.report import COPY, markdown
from iwsim.eval.rollout import open_loop
from iwsim.eval.scores import FeatureNets, frame_metrics, i3d_features, inception_features, set_metrics, summarize
from iwsim.world_model import WorldModel

log = logging.getLogger(__name__)


def training_info(path: Path) -> dict[str, float]:
    """Steps and wall-clock minutes of a run checkpoint (empty for exported models)."""
    state = path / "training_state" / "state.json"
    if not state.is_file():
        return {}
    s = load_json(state)
    return {"train_steps": int(s["step"]), "train_minutes": float(s["elapsed_s"]) / 60}


def _data_of(path: Path) -> str | None:
    config = load_json(path / "config.json")
    return config.get("data") or config.get("provenance", {}).get("data")


def run_benchmark(models: dict[str, str | Path], out: str | Path, data: str | Path | None = None, *,
                  episodes: int = 20, steps: int = 192, stability_steps: int = 9000, stability_every: int = 1,
                  speed_batch: int = 64, speed_calls: int = 100, seed: int = 0, weights: Path | None = None,
                  device: torch.device | str = "cpu", progress: bool = True, command: str | None = None) -> dict:
    """Benchmark ``models`` (name -> world-model checkpoint; the first is "ours") into
    ``out``: results.json, results.md, curves.png, frames.png, stability.png; both reports
    begin with ``command`` when given (the command line that ran this, from
    :func:`iwsim.eval.records.command_line`)."""
    if not models:
        raise InputError("no model to benchmark.")
    check_output_dir(out)
    paths = {name: resolve_checkpoint(p) for name, p in models.items()}
    wms = {name: WorldModel.load(p, device) for name, p in paths.items()}
    task = task_of(next(iter(wms.values())))
    if task.score_name is None:
        raise InputError(f"iwsim bench compares the models' pixel scores; task {task.name!r} has no pixel scorer "
                         "(iwsim rollout gives PSNR and SSIM for any task).")
    first = next(iter(paths.values()))
    data = data or _data_of(first)
    if data is None:
        raise InputError(f"{first} does not say which store it was trained on; pass --data.")
    store = EpisodeStore.open(data, "r")
    sizes = {wm.image_size for wm in wms.values()}
    if sizes != {store.array("img").shape[1]}:
        raise InputError(f"the models' image sizes {sorted(sizes)} do not match the {store.array('img').shape[1]} "
                         f"px frames of {data}.")
    _, held = split_episodes(store.n_episodes, next(iter(wms.values())).cfg.holdout_every)
    long_enough = [e for e in held if len(store.episode(e)["action"]) >= steps + 1]
    if len(long_enough) < episodes:
        raise InputError(f"{data} has {len(long_enough)} held-out episodes of at least {steps + 1} frames; "
                         f"{episodes} were asked for (lower --episodes or --steps).")
    chosen = long_enough[:episodes]
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    nets = FeatureNets.load(weights, device)
    for k, why in nets.missing.items():
        log.warning("%s: %s (set %s to a directory holding it)", k.upper(), why, feats.WEIGHTS_ENV)

    result: dict = {} if command is None else {"command": command}
    result |= {"machine": f"{platform.machine()}, {torch.get_num_threads()} threads", "data": str(data),
                    "episodes": chosen, "steps": steps, "seed": seed, "ours": next(iter(models)),
                    "unavailable": nets.missing, "models": {}}
    per_step: dict[str, dict[str, np.ndarray]] = {}
    preds: dict[str, np.ndarray] = {}
    truth = context = None
    truth_feats: dict[str, np.ndarray] = {}
    for name, wm in wms.items():
        t0 = time.perf_counter()
        ol = open_loop(wm, store, chosen, steps, seed=seed, progress=progress)
        if truth is None:
            truth, context = ol.truth, np.stack([store.episode(e)["img"][0] for e in chosen])
            truth_iou = ol.iou_true
            if nets.inception is not None:
                truth_feats["fid"] = inception_features(nets.inception, truth)
            if nets.i3d is not None:
                truth_feats["fvd"] = i3d_features(nets.i3d, truth)
        scores = frame_metrics(truth, ol.pred, nets, device=device)
        assert ol.iou_pred is not None and truth_iou is not None  # the task has a pixel scorer (checked above)
        scores["iou_err"] = np.abs(ol.iou_pred - truth_iou)
        entry: dict[str, Any] = {"checkpoint": str(paths[name]), "objective": wm.cfg.objective,
                                 **training_info(paths[name]),
                                 "accuracy": summarize(scores, set_metrics(truth_feats, ol.pred, nets)),
                                 "accuracy_seconds": time.perf_counter() - t0}
        result["models"][name] = entry
        per_step[name], preds[name] = scores, ol.pred
        log.info("%s: PSNR %.2f dB, SSIM %.3f", name, entry["accuracy"]["psnr"]["mean"],
                 entry["accuracy"]["ssim"]["mean"])
    assert truth is not None and context is not None  # set by the first model's rollouts
    # For scale: a "model" that repeats the context frame.
    still = np.repeat(context[:, None], steps, 1)
    scores = frame_metrics(truth, still, nets, device=device)
    context_iou = task.score(context)
    assert context_iou is not None  # the task has a pixel scorer
    scores["iou_err"] = np.abs(context_iou[:, None] - truth_iou)
    result["reference"] = {COPY: {"accuracy": summarize(scores, set_metrics(truth_feats, still, nets))}}
    for name, wm in wms.items():
        result["models"][name]["speed"] = speed(wm, context[0], speed_batch, speed_calls)
    curves_figure(per_step, out / "curves.png")
    frames_figure(context, truth, preds, out / "frames.png")
    if stability_steps > 0:
        t0 = time.perf_counter()
        rows = stability(wms, stability_steps, every=stability_every, progress=progress)
        stability_figure(rows, out / "stability.png")
        for name, r in rows.items():
            s = {"frame_mean": float(r["mean"].mean()), "frame_std": float(r["std"].mean()),
                 "block_pixels": float(r["block"].mean()), "block_detected": float(r["detected"].mean()),
                 "block_detected_last_10pct": float(r["detected"][-max(1, len(r["detected"]) // 10):].mean())}
            (result.setdefault("mujoco", {}) if name == "mujoco" else result["models"][name])["stability"] = s
        mem = rows["mujoco"]["memory_mib"]
        result["stability"] = {"steps": stability_steps, "every": stability_every,
                               "minutes": (time.perf_counter() - t0) / 60,
                               "memory_mib_first": float(mem[min(len(mem) - 1, 1)]), "memory_mib_last": float(mem[-1])}
    write_json_atomic(out / "results.json", result, sort_keys=False)  # models in the order given
    tmp = out / ".results.md.tmp"
    tmp.write_text(markdown(result))
    os.replace(tmp, out / "results.md")
    return result
