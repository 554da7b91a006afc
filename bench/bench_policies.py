"""Imitation policies against the scripted expert they imitate, in MuJoCo.

    MUJOCO_GL=egl .venv/bin/iwsim collect --policy expert --episodes 100 --steps 300 --workers 2 \\
        --out data/pusht_expert.zarr
    OMP_NUM_THREADS=1 .venv/bin/iwsim train policy --policy dp --data data/pusht_expert.zarr \\
        --out runs/pol2/dp --steps 6500 &
    OMP_NUM_THREADS=1 .venv/bin/iwsim train policy --policy act --data data/pusht_expert.zarr \\
        --out runs/pol2/act --steps 7500
    MUJOCO_GL=egl .venv/bin/python bench/bench_policies.py --runs dp=runs/pol2/dp,act=runs/pol2/act

Checkpoint selection first: every kept checkpoint of a run saved within ``--budget-min``
minutes of training is scored on validation seeds (200000 + i, ``--select-episodes`` x
``--select-steps``), and the best goes on. Then every chosen policy and the expert are
scored on the same test seeds (100000 + i, ``--episodes`` x ``--steps``): mean max IoU,
success rate with its Beta posterior and Clopper-Pearson interval, the ratio to the
expert, training and evaluation time. Last, the first policy is evaluated inside the
world model from the same initial states, all episodes in parallel, for its score there
and the throughput. Writes results.json and results.md to ``--out``, and per policy the
evaluation's results, per-step IoU, videos of 4 episodes and frames.png (their first 300
steps as frame strips).
"""

from __future__ import annotations

import argparse
import json
import multiprocessing as mp
import time
from pathlib import Path

import numpy as np

from iwsim.core.errors import reporting_errors
from iwsim.envs.registry import get_task
from iwsim.eval.policy import evaluate, summarize
from iwsim.eval.policy_runs import training_minutes
from iwsim.eval.records import command_line
from iwsim.policies.factory import load_policy


def _expert_episode(seed_steps: tuple[int, int]) -> float:
    from iwsim.envs.pusht.scripted import record_episode

    seed, steps = seed_steps
    return float(np.max(record_episode("pusht", "expert", seed, steps)["iou"]))


def expert(seeds: list[int], steps: int) -> dict:
    """The scripted expert (reading the block pose from the simulator) on the same seeds."""
    t0 = time.perf_counter()
    with mp.get_context("spawn").Pool(2) as pool:
        max_iou = np.array(pool.map(_expert_episode, [(s, steps) for s in seeds]))
    return {**summarize(max_iou, seeds, get_task("pusht").success_score), "seconds": time.perf_counter() - t0}


def select(run: Path, budget_min: float, episodes: int, steps: int, seed: int) -> tuple[Path, dict]:
    """The run's checkpoint (saved within the budget) with the best mean max IoU on the
    validation seeds, and every checkpoint's score (those over the budget, for reference)."""
    minutes = training_minutes(run)
    scores = {}
    for ckpt in sorted(p for p in (run / "checkpoints").iterdir() if p.name.isdigit()):
        step = int(ckpt.name)
        policy = load_policy(ckpt)
        r = evaluate(policy, "pusht", episodes=episodes, seed=seed, steps=steps, image_size=policy.image_size,
                     progress=False)
        scores[step] = {"train_minutes": minutes[step], "mean_max_iou": r["mean_max_iou"],
                        "success_rate": r["success_rate"]}
        print(f"  step {step} ({minutes[step]:.1f} min): validation mean max IoU {r['mean_max_iou']:.3f}", flush=True)
    within = [k for k in scores if scores[k]["train_minutes"] <= budget_min]
    if not within:
        raise SystemExit(f"{run} has no checkpoint saved within {budget_min} minutes of training.")
    best = max(within, key=lambda k: scores[k]["mean_max_iou"])
    return run / "checkpoints" / f"{best:08d}", {"step": best, "candidates": scores}


def strip(run_dir: Path, frames: int = 10, until: int = 300) -> None:
    """frames.png: each recorded episode of ``run_dir`` as a row of ``frames`` frames over
    its first ``until`` steps (the videos stay out of git; this picture goes in)."""
    import av
    from PIL import Image

    rows = []
    for video in sorted(run_dir.glob("episode_*.mp4")):
        with av.open(str(video)) as f:
            decoded = [fr.to_ndarray(format="rgb24") for fr in f.decode(video=0)]
        pick = np.linspace(0, min(until, len(decoded) - 1), frames).round().astype(int)
        rows.append(np.concatenate([decoded[i] for i in pick], 1))
    if rows:
        image = Image.fromarray(np.concatenate(rows, 0))
        image.resize((image.width // 4, image.height // 4), Image.NEAREST).save(run_dir / "frames.png")  # 64 px


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--runs", required=True, help="NAME=RUN_DIR[,NAME=RUN_DIR...]")
    p.add_argument("--episodes", type=int, default=50)
    p.add_argument("--steps", type=int, default=600)
    p.add_argument("--seed", type=int, default=100000)
    p.add_argument("--budget-min", type=float, default=60.0, help="training minutes a checkpoint may have had")
    p.add_argument("--select-episodes", type=int, default=20)
    p.add_argument("--select-steps", type=int, default=300)
    p.add_argument("--select-seed", type=int, default=200000)
    p.add_argument("--world-model", default="checkpoints/pusht-64")
    p.add_argument("--wm-steps", type=int, default=600, help="steps of the world-model evaluation")
    p.add_argument("--out", default="bench/results/policies")
    args = p.parse_args()
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    seeds = [args.seed + i for i in range(args.episodes)]
    command = command_line(__file__)
    results: dict = {"command": command, "episodes": args.episodes, "steps": args.steps, "budget_min": args.budget_min}
    print("expert ...", flush=True)
    results["expert"] = expert(seeds, args.steps)
    print(f"  mean max IoU {results['expert']['mean_max_iou']:.3f}", flush=True)
    results["policies"] = {}
    chosen = {}
    for spec in args.runs.split(","):
        name, run = spec.split("=")
        print(f"{name}: choosing a checkpoint ...", flush=True)
        ckpt, selection = select(Path(run), args.budget_min, args.select_episodes, args.select_steps,
                                 args.select_seed)
        chosen[name] = ckpt
        policy = load_policy(ckpt)
        print(f"{name} ({ckpt}) in MuJoCo ...", flush=True)
        r = evaluate(policy, "pusht", episodes=args.episodes, seed=args.seed, steps=args.steps,
                     image_size=policy.image_size, out=out / name, videos=4, progress=False,
                     meta={"checkpoint": str(ckpt)}, command=command)
        strip(out / name)
        step = selection["step"]
        r.update(steps=step, train_minutes=selection["candidates"][step]["train_minutes"], selection=selection)
        r["fraction_of_expert"] = r["mean_max_iou"] / results["expert"]["mean_max_iou"]
        results["policies"][name] = r
        print(f"  mean max IoU {r['mean_max_iou']:.3f} ({100 * r['fraction_of_expert']:.0f}% of the expert)",
              flush=True)
    from iwsim.world_model import WorldModel

    name = next(iter(chosen))
    print(f"{name} inside the world model ({args.episodes} in parallel, {args.wm_steps} steps) ...", flush=True)
    r = evaluate(load_policy(chosen[name]), "world-model", episodes=args.episodes, seed=args.seed,
                 steps=args.wm_steps, world_model=WorldModel.load(args.world_model), out=out / f"{name}_world_model",
                 videos=4, progress=False, command=command)
    strip(out / f"{name}_world_model")
    results["world_model"] = {"policy": name, "episodes": args.episodes, "steps": args.wm_steps,
                              "mean_max_iou": r["mean_max_iou"], "success_rate": r["success_rate"],
                              "env_steps_per_s": r["env_steps_per_s"], "seconds": r["seconds"]}
    (out / "results.json").write_text(json.dumps(results, indent=1))
    (out / "results.md").write_text(markdown(results))
    print((out / "results.md").read_text())


def markdown(r: dict) -> str:
    def over(c: dict) -> str:
        return ", over budget" if c["train_minutes"] > r["budget_min"] else ""

    e = r["expert"]
    lines = [
        "# Imitation policies vs the scripted expert (MuJoCo)", "", f"`{r['command']}`", "",
        f"{r['episodes']} episodes x {r['steps']} steps, seeds 100000 + i; score = max IoU in the episode; "
        "success = IoU >= 0.9. Intervals: 95%, Beta posterior (uniform prior) and Clopper-Pearson. "
        "Each policy is the checkpoint (saved within the training budget) that scored best on other seeds "
        "(200000 + i); train steps and minutes are that checkpoint's.", "",
        "| policy | train steps | train min | mean max IoU | of expert | success | Beta 95% | Clopper-Pearson 95% "
        "| eval s |",
        "|---|---|---|---|---|---|---|---|---|",
        f"| expert | - | - | {e['mean_max_iou']:.3f} | 100% | {e['success_rate']:.2f} | "
        f"{e['success_beta_posterior']['low']:.2f}-{e['success_beta_posterior']['high']:.2f} | "
        f"{e['success_clopper_pearson'][0]:.2f}-{e['success_clopper_pearson'][1]:.2f} | {e['seconds']:.0f} |",
    ]
    for name, p in r["policies"].items():
        lines.append(
            f"| {name} | {p['steps']} | {p['train_minutes']:.1f} | {p['mean_max_iou']:.3f} | "
            f"{100 * p['fraction_of_expert']:.0f}% | {p['success_rate']:.2f} | "
            f"{p['success_beta_posterior']['low']:.2f}-{p['success_beta_posterior']['high']:.2f} | "
            f"{p['success_clopper_pearson'][0]:.2f}-{p['success_clopper_pearson'][1]:.2f} | {p['seconds']:.0f} |")
    lines += ["", f"Checkpoint selection (mean max IoU on the validation seeds; chosen among those saved within "
              f"{r['budget_min']:.0f} min of training):", ""]
    for name, p in r["policies"].items():
        cands = ", ".join(f"{s} steps ({c['train_minutes']:.1f} min{over(c)}): {c['mean_max_iou']:.3f}"
                          for s, c in p["selection"]["candidates"].items())
        lines.append(f"- {name}: {cands}")
    w = r["world_model"]
    lines += ["", f"Inside the world model ({w['policy']}, same seeds, {w['steps']} steps): mean max IoU "
              f"{w['mean_max_iou']:.3f} (MuJoCo: {r['policies'][w['policy']]['mean_max_iou']:.3f}), success "
              f"{w['success_rate']:.2f}; {w['env_steps_per_s']:.1f} environment steps/s with {w['episodes']} "
              f"episodes in parallel ({w['seconds']:.0f} s).", "",
              "Frame strips of the first 4 episodes (steps 0-300): "
              + ", ".join(f"`{n}/frames.png`" for n in [*r["policies"], f"{w['policy']}_world_model"]) + ".", ""]
    return "\n".join(lines)


if __name__ == "__main__":
    raise SystemExit(reporting_errors("bench_policies.py", main))
