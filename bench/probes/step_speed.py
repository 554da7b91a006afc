"""A probe of issue 64 (not a feature): single-stream steps/s and frames/s at batch 64 of
world models, measured interleaved (each model in turn, ``--repeats`` times) in one
process on one thread, from MuJoCo's first frame of seed 0; e.g. whether the state head
costs speed. Never run beside a training run.

    MUJOCO_GL=egl python bench/probes/step_speed.py state750=runs/wm_state750 nostate750=runs/wm_nostate750
"""
import argparse

import gymnasium as gym
import numpy as np
import torch

import iwsim  # noqa: F401  (registers the environments)
from iwsim.core.checkpoint import named_checkpoints
from iwsim.eval.profiling import speed
from iwsim.world_model import WorldModel

p = argparse.ArgumentParser()
p.add_argument("models", nargs="+", help="NAME=CHECKPOINT")
p.add_argument("--repeats", type=int, default=3)
args = p.parse_args()
torch.set_num_threads(1)
obs, _ = gym.make("iwsim/BimanualPushT-v0").reset(seed=0)
models = {n: WorldModel.load(c) for n, c in named_checkpoints(args.models, "models").items()}
runs: dict[str, list[tuple[float, float]]] = {n: [] for n in models}
for _ in range(args.repeats):
    for name, wm in models.items():
        r = speed(wm, obs["pixels"], batch=64, n=100)
        runs[name].append((r["steps_per_s"], r["frames_per_s_batch64"]))
for name, v in runs.items():
    a = np.array(v)
    print(f"{name}: single stream {np.median(a[:, 0]):.1f} steps/s (runs {np.round(a[:, 0], 1).tolist()}), "
          f"batch 64 {np.median(a[:, 1]):.1f} frames/s (runs {np.round(a[:, 1], 1).tolist()})")
