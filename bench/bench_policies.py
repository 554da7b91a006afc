"""Imitation policies against the scripted expert they imitate, in MuJoCo.

    MUJOCO_GL=egl .venv/bin/iwsim collect --policy expert --episodes 100 --steps 300 --workers 2 \\
        --out data/pusht_expert.zarr
    OMP_NUM_THREADS=1 .venv/bin/iwsim train policy --policy dp --data data/pusht_expert.zarr --out runs/pol/dp --steps 4500 &
    OMP_NUM_THREADS=1 .venv/bin/iwsim train policy --policy act --data data/pusht_expert.zarr --out runs/pol/act --steps 6000
    MUJOCO_GL=egl .venv/bin/python bench/bench_policies.py --runs dp=runs/pol/dp,act=runs/pol/act

Scores every policy (its last checkpoint) and the expert on the same MuJoCo seeds
(100000 + i, ``--episodes`` of them, ``--steps`` steps each): mean max IoU, success rate
with its Beta posterior and Clopper-Pearson interval, the ratio to the expert, training
and evaluation time; and the evaluation throughput inside the world model with all
episodes in parallel. Writes results.json and results.md to ``--out``.
"""

from __future__ import annotations

import argparse
import json
import multiprocessing as mp
import sys
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "src"))

from iwsim.eval.policy import evaluate, summarize  # noqa: E402
from iwsim.policies import load_policy  # noqa: E402


def _expert_episode(seed_steps: tuple[int, int]) -> float:
    from iwsim.envs import record_episode

    seed, steps = seed_steps
    return float(np.max(record_episode("pusht", "expert", seed, steps)["iou"]))


def expert(seeds: list[int], steps: int) -> dict:
    """The scripted expert (reading the block pose from the simulator) on the same seeds."""
    t0 = time.perf_counter()
    with mp.get_context("spawn").Pool(2) as pool:
        max_iou = np.array(pool.map(_expert_episode, [(s, steps) for s in seeds]))
    return {**summarize(max_iou, seeds), "seconds": time.perf_counter() - t0}


def training_time(run: Path) -> dict:
    rows = [json.loads(line) for line in (run / "metrics.jsonl").read_text().splitlines() if line.strip()]
    last = [r for r in rows if "elapsed_s" in r][-1]
    return {"steps": last["step"], "train_minutes": last["elapsed_s"] / 60}


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--runs", required=True, help="NAME=RUN_DIR[,NAME=RUN_DIR...]")
    p.add_argument("--episodes", type=int, default=50)
    p.add_argument("--steps", type=int, default=600)
    p.add_argument("--seed", type=int, default=100000)
    p.add_argument("--world-model", default="checkpoints/pusht-64")
    p.add_argument("--wm-steps", type=int, default=30, help="steps of the world-model throughput run")
    p.add_argument("--out", default="bench/results/policies")
    args = p.parse_args()
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    seeds = [args.seed + i for i in range(args.episodes)]
    results: dict = {"command": "MUJOCO_GL=egl .venv/bin/python bench/bench_policies.py " + " ".join(sys.argv[1:]),
                     "episodes": args.episodes, "steps": args.steps}
    print("expert ...", flush=True)
    results["expert"] = expert(seeds, args.steps)
    print(f"  mean max IoU {results['expert']['mean_max_iou']:.3f}", flush=True)
    results["policies"] = {}
    for spec in args.runs.split(","):
        name, run = spec.split("=")
        policy = load_policy(run)
        print(f"{name} in MuJoCo ...", flush=True)
        r = evaluate(policy, "pusht", episodes=args.episodes, seed=args.seed, steps=args.steps,
                     image_size=policy.image_size, out=out / name, videos=4, progress=False,
                     meta={"checkpoint": run})
        r.update(training_time(Path(run)))
        r["fraction_of_expert"] = r["mean_max_iou"] / results["expert"]["mean_max_iou"]
        results["policies"][name] = r
        print(f"  mean max IoU {r['mean_max_iou']:.3f} ({100 * r['fraction_of_expert']:.0f}% of the expert)",
              flush=True)
    from iwsim.world_model import WorldModel

    name, run = args.runs.split(",")[0].split("=")
    print(f"{name} inside the world model ({args.episodes} in parallel, {args.wm_steps} steps) ...", flush=True)
    r = evaluate(load_policy(run), "world-model", episodes=args.episodes, seed=args.seed, steps=args.wm_steps,
                 world_model=WorldModel.load(args.world_model), progress=False)
    results["world_model_throughput"] = {"policy": name, "episodes": args.episodes, "steps": args.wm_steps,
                                         "env_steps_per_s": r["env_steps_per_s"], "seconds": r["seconds"]}
    (out / "results.json").write_text(json.dumps(results, indent=1))
    (out / "results.md").write_text(markdown(results))
    print((out / "results.md").read_text())


def markdown(r: dict) -> str:
    e = r["expert"]
    lines = [
        "# Imitation policies vs the scripted expert (MuJoCo)", "", f"`{r['command']}`", "",
        f"{r['episodes']} episodes x {r['steps']} steps, seeds 100000 + i; score = max IoU in the episode; "
        "success = IoU >= 0.9. Intervals: 95%, Beta posterior (uniform prior) and Clopper-Pearson.", "",
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
    w = r["world_model_throughput"]
    lines += ["", f"Inside the world model: {w['env_steps_per_s']:.1f} environment steps/s with {w['episodes']} "
              f"episodes in parallel ({w['policy']}, {w['steps']} steps, {w['seconds']:.0f} s).", ""]
    return "\n".join(lines)


if __name__ == "__main__":
    main()
