"""Issue 25's scaling curve: each policy trained on the first 25 / 50 / 100 / 200 of the
simulator expert's demonstrations with the chosen recipe, its checkpoint chosen on
validation seeds (200000+) among those saved within the training budget, then scored on
the test seeds (100000+). Every run is a ``bench/policy_runs.py`` run (``runs/pol/NAME``,
NAME = scale-POLICY-N), so it resumes exactly and its evaluations are cached: run one
process per policy side by side, then once more to write the report from the cache.

    MUJOCO_GL=egl OMP_NUM_THREADS=1 python bench/policy_scaling.py --policies dp &
    MUJOCO_GL=egl OMP_NUM_THREADS=1 python bench/policy_scaling.py --policies act
    MUJOCO_GL=egl OMP_NUM_THREADS=1 python bench/policy_scaling.py --policies dp,act --report

Writes scaling.md and scaling.png to ``--out`` (with ``--report``, or when a process has
every run of the policies it was given), with every policy's cached runs.
"""

from __future__ import annotations

import argparse
import subprocess
import sys
from pathlib import Path

import numpy as np

from iwsim.core.checkpoint import load_json, write_text_atomic
from iwsim.core.errors import reporting_errors
from iwsim.eval.figures import pyplot, save_figure
from iwsim.eval.policy_runs import eval_path, training_minutes
from iwsim.eval.records import command_line

POLICY_RUNS = Path(__file__).resolve().with_name("policy_runs.py")
DATA = "runs/experiments/demos/sim_expert.zarr"
SIZES = (25, 50, 100, 200)
# The recipe of each policy: steps and the checkpoints scored on validation seeds.
RECIPES = {"dp": (6000, (2000, 3000, 4000, 5000, 6000)), "act": (10000, (6000, 8000, 10000))}
EXPERT = 0.989  # the state expert's mean max IoU on the 50 test seeds x 600 steps (results.md)


def run_name(policy: str, n: int) -> str:
    return f"scale-{policy}-{n}"


def cached(run: Path, split: str, episodes: int, step: int) -> dict | None:
    path = eval_path(run, split, episodes, 600, step)
    return load_json(path) if path.is_file() else None


def policy_run(argv: list[str]) -> None:
    """One ``bench/policy_runs.py`` run with ``argv`` (it trains and scores into the run's
    directory; its output is this process's), in a process of its own: scripts do not
    import each other. Its failure ends this process with its exit status."""
    code = subprocess.run([sys.executable, str(POLICY_RUNS), *argv]).returncode
    if code:
        raise SystemExit(code)


def one(policy: str, n: int, data: str, root: Path, budget: float, test_episodes: int, train: bool) -> dict | None:
    """Train and score one size (or, with ``train`` False, read what is cached)."""
    name, (steps, evals) = run_name(policy, n), RECIPES[policy]
    run = root / name
    stores = ",".join(f"{store}:{n}" for store in data.split(","))
    common = ["--name", name, "--policy", policy, "--data", stores, "--steps", str(steps), "--root", str(root)]
    if train:
        policy_run([*common, "--eval-at", ",".join(map(str, evals))])
    if not (run / "metrics.jsonl").is_file():
        return None
    mins = training_minutes(run)
    val = {s: cached(run, "val", 20, s) for s in evals}
    within = [s for s in evals if val[s] is not None and mins.get(s, np.inf) <= budget]
    if not within:
        return None
    best = max(within, key=lambda s: val[s]["mean_max_iou"])
    if train and cached(run, "test", test_episodes, best) is None:
        policy_run([*common, "--eval-at", str(best), "--test", "--episodes", str(test_episodes)])
    test = cached(run, "test", test_episodes, best)
    return {"n": n, "step": best, "minutes": mins[best], "val": {s: v["mean_max_iou"] for s, v in val.items() if v},
            "test": test}


def report(rows: dict[str, list[dict]], out: Path, test_episodes: int, command: str) -> None:
    """Write scaling.md (headed by ``command``, which rewrites it from the cached runs) and scaling.png."""
    lines = ["# Imitation policies: the scaling curve over demonstrations", "",
             f"`MUJOCO_GL=egl OMP_NUM_THREADS=1 {command}` (the runs: "
             "see its docstring). Demonstrations: the first N of each store its run's config.json names. "
             f"Score: mean max IoU over {test_episodes} test seeds (100000 + i) x 600 steps, the checkpoint chosen "
             "on 20 validation seeds (200000 + i) among those saved within the budget; success: IoU >= 0.9, "
             f"95% Beta-posterior interval. The expert: {EXPERT:.3f}.", "",
             "| policy | demos | chosen step | train min | val mean max IoU by step | test mean max IoU | of expert "
             "| success (95%) |", "|---|---|---|---|---|---|---|---|"]
    fig, ax = pyplot().subplots(figsize=(5, 3.5))
    for policy, rs in rows.items():
        done = [r for r in rs if r["test"] is not None]
        for r in rs:
            vals = ", ".join(f"{s}: {v:.3f}" for s, v in sorted(r["val"].items()))
            if r["test"] is None:
                lines.append(f"| {policy} | {r['n']} | {r['step']} | {r['minutes']:.1f} | {vals} | (pending) | | |")
                continue
            t = r["test"]
            lo, hi = t["success_beta_posterior"]["low"], t["success_beta_posterior"]["high"]
            lines.append(f"| {policy} | {r['n']} | {r['step']} | {r['minutes']:.1f} | {vals} | "
                         f"{t['mean_max_iou']:.3f} | {100 * t['mean_max_iou'] / EXPERT:.0f}% | "
                         f"{t['success_rate']:.2f} ({lo:.2f}-{hi:.2f}) |")
        if done:
            ns = [r["n"] for r in done]
            means = np.array([r["test"]["mean_max_iou"] for r in done])
            sems = np.array([r["test"]["std_max_iou"] / np.sqrt(len(r["test"]["episodes"])) for r in done])
            ax.errorbar(ns, means, yerr=1.96 * sems, marker="o", capsize=3, label=policy)
    ax.axhline(EXPERT, color="k", ls="--", lw=1, label="expert")
    ax.set(xscale="log", xlim=(SIZES[0] / 1.25, SIZES[-1] * 1.25), ylim=(0, 1.05), xlabel="demonstrations",
           ylabel="mean max IoU (test)")
    ax.minorticks_off()
    ax.set(xticks=list(SIZES), xticklabels=[str(s) for s in SIZES])
    ax.legend()
    fig.tight_layout()
    out.mkdir(parents=True, exist_ok=True)
    save_figure(fig, out / "scaling.png")
    write_text_atomic(out / "scaling.md", "\n".join(lines + ["", "![scaling](scaling.png)", ""]))
    print("\n".join(lines))


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--policies", default="dp,act")
    p.add_argument("--sizes", default=",".join(map(str, SIZES)))
    p.add_argument("--data", default=DATA, help="the demonstration store (its first N takes for size N), or several "
                   "separated by commas (the first N of each)")
    p.add_argument("--budget-min", type=float, default=60.0)
    p.add_argument("--test-episodes", type=int, default=50)
    p.add_argument("--root", default="runs/pol")
    p.add_argument("--out", default="bench/results/policies")
    p.add_argument("--report", action="store_true", help="only read the cached runs and write the report")
    args = p.parse_args(argv)
    policies = [s for s in args.policies.split(",") if s]
    unknown = sorted(set(policies) - set(RECIPES))
    if unknown:
        raise SystemExit(f"unknown policies {unknown}; expected some of {sorted(RECIPES)}.")
    sizes = [int(n) for n in args.sizes.split(",")]

    def rows_of(policy: str, train: bool) -> list[dict]:
        found = [one(policy, n, args.data, Path(args.root), args.budget_min, args.test_episodes, train) for n in sizes]
        return sorted((r for r in found if r is not None), key=lambda r: r["n"])

    rows = {policy: rows_of(policy, not args.report) for policy in policies}
    if args.report or all(len(r) == len(sizes) for r in rows.values()):
        # The report is shared by both policies: a process training one keeps the other's cached rows.
        every = {policy: rows[policy] if policy in rows else rows_of(policy, False) for policy in RECIPES}
        done = {policy: r for policy, r in every.items() if r}
        command = command_line(__file__, ["--policies", ",".join(done), "--sizes", args.sizes, "--data", args.data,
                                          "--root", args.root, "--out", args.out, "--report"])
        report(done, Path(args.out), args.test_episodes, command)
    return 0


if __name__ == "__main__":
    raise SystemExit(reporting_errors("policy_scaling.py", main))
