"""The studies' quick checks on a world model (``bench/wm_studies_check.py``, the yardstick's
core part): the datagen study's teleoperation of a model, cached by its key, and a frame
strip of one episode in each model and in MuJoCo."""

from __future__ import annotations

import shutil
from collections.abc import Callable
from pathlib import Path
from typing import Any

import imageio.v2 as imageio
import numpy as np
import torch

from iwsim.core.checkpoint import load_json, write_json_atomic
from iwsim.eval.policy import rollout
from iwsim.experiments.common import fingerprint
from iwsim.experiments.datagen import DatagenConfig
from iwsim.experiments.demos import record_demos
from iwsim.policies.scripted import ScriptedBatch
from iwsim.world_model import WorldModel

TELEOP_SEED = DatagenConfig().wm_seed  # the datagen study's first candidate in the model


def teleop(name: str, model: str | None, work: Path, candidates: int, seed: int, steps: int) -> dict:
    """The datagen study's teleoperation of ``model`` (MuJoCo when None), cached by its key."""
    env = "pusht" if model is None else "world-model"
    key = {"model": model and fingerprint(model), "candidates": candidates, "seed": seed, "steps": steps}
    cached = work / "teleop" / f"{name}.json"
    if cached.is_file() and (saved := load_json(cached))["key"] == key:
        return saved["result"]
    store = work / "teleop" / f"{name}.zarr"
    shutil.rmtree(store, ignore_errors=True)  # a fresh count: the candidates decide, not an old store
    stats = record_demos(env, store, candidates, steps, seed, world_model=model, max_attempts=candidates,
                         batch=16, progress=False)
    result = {"candidates": stats.candidates, "kept": stats.episodes, "acceptance_rate": stats.acceptance_rate,
              "mean_candidate_max_iou": stats.mean_candidate_max_iou, "seconds": stats.seconds}
    write_json_atomic(cached, {"key": key, "result": result})
    return result


def strip(path: Path, models: list[str | None], seed: int, steps: int = 100, every: int = 10,
          policy: Callable[[], Any] = lambda: ScriptedBatch("expert")) -> list[float]:
    """One row per model (None: MuJoCo): the episode of a fresh ``policy()`` (default: the
    pixel expert) from ``seed``, a frame every ``every`` steps. Returns each row's max IoU."""
    rows, best = [], []
    for model in models:
        wm = None if model is None else WorldModel.load(model)
        torch.manual_seed(0)  # a learned policy's sampling noise
        run = rollout(policy(), "pusht" if model is None else "world-model", [seed], steps,
                      world_model=wm, image_size=64, record=1, progress=False)
        rows.append(np.concatenate(list(run["frames"][0, :steps:every]), axis=1))
        best.append(float(run["iou"][0].max()))
    imageio.imwrite(path, np.concatenate(rows, axis=0))
    return best
