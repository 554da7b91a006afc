"""Stage-2 research loop: train candidates at a fixed budget on cached latents, then score
them (and any checkpoint) on held-out episodes of smooth actions.

    # train variants of the pusht-64 preset for 300 steps each (one core each)
    OMP_NUM_THREADS=1 python bench/ablate_dynamics.py train --variants ours,deterministic \\
        --steps 300 --data data/play.zarr --ae runs/ae_shipped --latent-cache runs/latents_play.safetensors
    # score runs or checkpoints on a store of episodes never used in training
    MUJOCO_GL=egl python bench/ablate_dynamics.py eval --models ours=runs/ablate/ours,... \\
        --data data/play_eval.zarr --out bench/results/dynamics --table bench/results/ablations.md

The table goes to ``OUT/table.md``; tracked files change only when named (``--out``,
``--table``, which appends to a record).

A variant's curriculum (``unroll``) is scaled with its step budget, so a short run goes
through the same stages as the preset's full run.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import logging
import time
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np
import torch

from iwsim import WorldModel
from iwsim.core.checkpoint import resolve_checkpoint, write_text_atomic
from iwsim.core.errors import InputError, reporting_errors
from iwsim.eval.records import command_line, with_command
from iwsim.world_model.presets import DYNAMICS_PRESETS, variant
from iwsim.world_model.train_dynamics import train_dynamics
from iwsim.yardstick.fidelity import POSE_STEPS, STEPS, Episodes, score


def budget(name: str, steps: int, preset: str = "pusht-64"):
    """The preset turned into variant ``name`` at ``steps`` training steps."""
    cfg = variant(DYNAMICS_PRESETS[preset], name)
    scale = steps / cfg.train.steps
    return dataclasses.replace(
        cfg, unroll=tuple((round(k * scale), n) for k, n in cfg.unroll),
        train=dataclasses.replace(cfg.train, steps=steps, eval_every=steps, checkpoint_every=steps,
                                  warmup_steps=min(cfg.train.warmup_steps, steps // 10)))


def train(args: argparse.Namespace) -> None:
    for name in args.variants.split(","):
        t0 = time.time()
        out = Path(args.out) / name.replace("+", "_")  # "+" in --models marks eval's options
        train_dynamics(budget(name, args.steps, args.preset), args.data, args.ae, out,
                       device=torch.device("cpu"), latent_cache=args.latent_cache, progress=False)
        logging.info("%s: %d steps in %.1f min", name, args.steps, (time.time() - t0) / 60)


ROWS = [  # (column, key, baseline key, format)
    ("1-step err (copy-prev)", "one_step", "copy_prev", "{:.3f}"),
    ("1-step err changed cells (copy-prev)", "one_step_changed", "copy_prev_changed", "{:.3f}"),
    ("action gap @5 / @10", "action_gap_5", "action_gap_10", "{:.2f}"),
    ("latent err @1/5/10/20/32", None, None, None),
    ("PSNR 1-32 (copy-first)", "psnr_1_32", "psnr_first_1_32", "{:.2f}"),
    ("PSNR 1-H (copy-first)", "psnr_1_H", "psnr_first_1_H", "{:.2f}"),
    ("pusher err px @10/20/32 (copy-first)", None, None, None),
    ("pusher visible / min peak", "pusher_visible", "pusher_peak_min", "{:.2f}"),
    ("block pos px @10/20/32 (copy-first)", None, None, None),
    ("block yaw deg @10/20/32 (copy-first)", None, None, None),
    ("T found", "t_found", None, "{:.2f}"),
    ("1-step err, context label 0 / cfg / 0.3", None, None, None),
]


def cell(r: dict, col: str, key: str | None, base: str | None, fmt: str | None) -> str:
    if col.startswith("latent err"):
        return " / ".join(f"{r[f'latent_err_{s}']:.3f}" for s in STEPS)
    if col.startswith("1-step err, context"):
        return " / ".join(f"{v:.4f}" for k, v in r.items() if k.startswith("one_step_label"))
    for name, pre in (("pusher err", "pusher_err"), ("block pos", "block_pos"), ("block yaw", "block_yaw")):
        if col.startswith(name):
            return " / ".join(f"{r[f'{pre}_{s}']:.1f}" for s in POSE_STEPS) + " (" + " / ".join(
                f"{r[f'{pre}_first_{s}']:.1f}" for s in POSE_STEPS) + ")"
    if col == "action gap @5 / @10":
        return f"{r[key]:.2f} / {r[base]:.2f}"
    if col.startswith("pusher visible"):
        return f"{r[key]:.2f} / {r[base]:.2f}"
    text = fmt.format(r[key.replace("H", str(r["horizon"]))])
    return text + (f" ({fmt.format(r[base.replace('H', str(r['horizon']))])})" if base else "")


def strip_steps(horizon: int) -> list[int]:
    """Indices of the predicted frames shown in frames.png: steps 1, 10, 20, 32, 64, last."""
    return sorted({min(s, horizon) - 1 for s in (1, 10, 20, 32, 64, horizon)})


def evaluate(args: argparse.Namespace) -> None:
    torch.set_num_threads(args.threads)
    ep = Episodes(args.data, args.episodes)
    horizon = min(args.horizon, ep.length - 1)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    command = command_line(__file__)
    results, curves, strips = {}, {}, {}
    for item in args.models.split(","):
        name, path = item.split("=", 1)
        if name == "command":
            raise InputError("a model may not be named 'command' (results.json's first key is the command).")
        path, _, option = path.partition("+")
        wm = WorldModel.load(resolve_checkpoint(path))
        wm.reencode = option == "reencode"
        t0 = time.time()
        r, curve, u8 = score(wm, ep, horizon)
        step = resolve_checkpoint(path).name  # a run's checkpoints are named by their step
        r.update(horizon=horizon, checkpoint=str(path), step=int(step) if step.isdigit() else "-",
                 reencode=wm.reencode, seconds=time.time() - t0)
        results[name], curves[name], strips[name] = r, curve, u8[0, strip_steps(horizon)]
        logging.info("%s: %s", name, {k: round(v, 4) if isinstance(v, float) else v for k, v in r.items()})
    (out / "results.json").write_text(json.dumps(with_command(command, results), indent=1))
    fig, ax = plt.subplots(figsize=(7, 4))
    steps = np.arange(1, horizon + 1)
    for name, (curve, _) in curves.items():
        ax.plot(steps, curve, label=name)
    ax.plot(steps, next(iter(curves.values()))[1], "k--", label="repeat the first frame")  # same for all
    ax.set_xlabel("step"), ax.set_ylabel("PSNR (dB)"), ax.legend(), ax.grid(alpha=0.3)
    ax.set_title(f"open loop from one frame, {ep.n} held-out episodes")
    fig.tight_layout(), fig.savefig(out / "psnr.png", dpi=100)
    cols = strip_steps(horizon)
    rows = [np.concatenate(list(ep.img[0, [c + 1 for c in cols]]), 1)] + [np.concatenate(list(s), 1)
                                                                            for s in strips.values()]
    import imageio.v2 as imageio
    imageio.imwrite(out / "frames.png", np.kron(np.concatenate(rows, 0), np.ones((2, 2, 1), np.uint8)))
    lines = [f"\n## {time.strftime('%Y-%m-%d %H:%M')} `{command}`\n",
             f"{ep.n} held-out episodes of `{args.data}`, horizon {horizon}; baselines in brackets "
             f"(copy-previous latent, repeat the first frame). Frames: `{out / 'frames.png'}` (truth first row, "
             f"steps {', '.join(str(c + 1) for c in cols)}).\n",
             "| model | " + " | ".join(c for c, *_ in ROWS) + " |", "|---" * (len(ROWS) + 1) + "|"]
    for name, r in results.items():
        lines.append(f"| {name} (step {r['step']}) | " + " | ".join(cell(r, *row) for row in ROWS) + " |")
    write_text_atomic(out / "table.md", "\n".join(lines) + "\n")
    if args.table:
        with open(args.table, "a") as f:
            f.write("\n".join(lines) + "\n")
    print("\n".join(lines))


def main() -> None:
    logging.basicConfig(level=logging.INFO, format="%(levelname)s %(name)s: %(message)s")
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = p.add_subparsers(dest="cmd", required=True)
    q = sub.add_parser("train")
    q.add_argument("--variants", required=True)
    q.add_argument("--steps", type=int, default=300)
    q.add_argument("--preset", default="pusht-64")
    q.add_argument("--data", default="data/play.zarr")
    q.add_argument("--ae", default="runs/ae_shipped")
    q.add_argument("--latent-cache", default="runs/latents_play.safetensors")
    q.add_argument("--out", default="runs/ablate")
    q.set_defaults(func=train)
    q = sub.add_parser("eval")
    q.add_argument("--models", required=True, help="NAME=RUN_OR_CHECKPOINT[+reencode][,...]")
    q.add_argument("--data", default="data/play_eval.zarr")
    q.add_argument("--episodes", type=int, default=20)
    q.add_argument("--horizon", type=int, default=192)
    q.add_argument("--threads", type=int, default=2)
    q.add_argument("--out", default="outputs/ablate_eval", help="results, frames and table.md (default: %(default)s)")
    q.add_argument("--table", help="a markdown file the table is also appended to, e.g. bench/results/ablations.md")
    q.set_defaults(func=evaluate)
    args = p.parse_args()
    args.func(args)


if __name__ == "__main__":
    raise SystemExit(reporting_errors("ablate_dynamics.py", main))
