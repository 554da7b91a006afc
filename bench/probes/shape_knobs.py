"""A probe of issue 64 (not a feature): do inference settings keep a model's T? For each
setting, the yardstick's two shape measures on one model: a T fits the block over 192
held-out play steps (``iwsim.yardstick.fidelity.score``'s ``t_found``, with its PSNR and the
block's median position (px) and yaw (degrees) error at step 32) and
in a 2000-step play run under MuJoCo's executed targets (``iwsim.eval.profiling.stability``,
every 10th frame; with the step of its last frame before three checks in a row find no T,
``t_run_lost_at``, and the share of the first 200 steps with one). A setting is
``default`` or parts joined by ``+``: ``reencode`` (the newest context latent is the
encoding of the decoded frame), ``jumpsN`` (consistency jumps per frame), ``labelX`` (the
context-noise std the context is labelled with), ``restX`` (the rest threshold),
``deadbandX`` (a cell's predicted change under X is none), ``tempX`` (the noise a new latent
starts from scaled by X: 0 is the model's one deterministic prediction).
One JSON line per setting; with ``--strip DIR``, DIR/SETTING.png shows the run's frames.

    MUJOCO_GL=egl python bench/probes/shape_knobs.py runs/x4_4500 default reencode jumps2 label0.3
"""
import argparse
import dataclasses
import json
import time
from pathlib import Path

import torch

from iwsim.eval.profiling import stability, strip_steps, write_run_strip
from iwsim.world_model.model import WorldModel
from iwsim.yardstick.fidelity import Episodes, score

p = argparse.ArgumentParser()
p.add_argument("model", help="a world model or a stage-2 run's checkpoint")
p.add_argument("settings", nargs="+",
               help="default, or parts joined by '+': reencode, jumpsN, labelX, restX, deadbandX, tempX")
p.add_argument("--data", default="data/play_eval.zarr")
p.add_argument("--episodes", type=int, default=20)
p.add_argument("--steps", type=int, default=2000, help="steps of the stability run")
p.add_argument("--strip", help="a folder: SETTING.png there, the stability run's frames (the model above MuJoCo)")
args = p.parse_args()
torch.set_num_threads(1)
play = Episodes(args.data, args.episodes)


def scaled(noise, temperature: float):
    """``WorldModel._noise`` with its draws (still taken from each stream's generator) scaled."""
    return lambda generators, shape: noise(generators, shape) * temperature


def configured(setting: str) -> WorldModel:
    wm, changes = WorldModel.load(args.model), {}
    fields = {"label": "context_label", "rest": "rest_threshold", "deadband": "delta_deadband"}
    for part in setting.split("+"):
        name = part.rstrip("0123456789.")
        try:
            if part == "reencode":
                wm.reencode = True
            elif name == "jumps":
                wm.jumps = int(part[5:])
            elif name == "temp":
                wm._noise = scaled(wm._noise, float(part[4:]))
            elif name in fields:
                changes[fields[name]] = float(part[len(name):])
            elif part != "default":
                p.error(f"unknown setting {part!r}")
        except ValueError:
            p.error(f"setting {part!r} needs a number after {name!r}")
    # one config, as a loaded model has it: score() resets the label to the config's after its one-step part
    wm.cfg = wm.denoiser.cfg = dataclasses.replace(wm.cfg, **changes)
    wm.context_label = wm.cfg.context_label
    return wm


def lost_at(steps, detected, run: int = 3) -> int:
    """The step of the last check before ``run`` checks in a row find no T (the run's
    length where that never happens)."""
    for i in range(len(detected) - run + 1):
        if not detected[i:i + run].any():
            return int(steps[i - 1]) if i else 0
    return int(steps[-1])


for setting in args.settings:
    wm, t0 = configured(setting), time.time()
    held, _, _ = score(wm, play, 192)
    keep = strip_steps(args.steps) if args.strip else ()
    runs = stability({"m": wm}, args.steps, every=10, progress=False, keep=keep)
    if args.strip:
        Path(args.strip).mkdir(parents=True, exist_ok=True)
        write_run_strip(Path(args.strip) / f"{setting}.png", runs, ["m", "mujoco"])
    print(json.dumps({"model": args.model, "setting": setting, "t_kept_192": round(held["t_found"], 3),
                      "psnr_1_192": round(held["psnr_1_192"], 2),
                      "block_pos_32": round(held["block_pos_32"], 2), "block_yaw_32": round(held["block_yaw_32"], 1),
                      "t_kept_run": round(float(runs["m"]["detected"].mean()), 3),
                      "t_kept_run_200": round(float(runs["m"]["detected"][runs["m"]["step"] <= 200].mean()), 3),
                      "t_run_lost_at": lost_at(runs["m"]["step"], runs["m"]["detected"]),
                      "t_kept_run_mujoco": round(float(runs["mujoco"]["detected"].mean()), 3),
                      "seconds": round(time.time() - t0)}), flush=True)
