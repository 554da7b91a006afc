"""Can a world model carry issue 16's studies? Two quick checks on trained checkpoints.

1. Teleoperation: the pixel-reading expert drives the model from MuJoCo first frames (the
   datagen study's candidates, seeds from 300000); how many takes reach pixel IoU 0.9
   (the acceptance rate) and the mean max pixel IoU. MuJoCo gives the reference.
2. Ranking: the policy-eval study's scripted policies (the expert, its noise and latency
   degradations, the play policy) from the same seeds in MuJoCo and in each model:
   mean max IoU per policy and Pearson r / Spearman rho / MMRV against MuJoCo.

    MUJOCO_GL=egl python bench/wm_studies_check.py --models shipped=checkpoints/pusht-64 \\
        tuned=runs/ft/checkpoints/last --out bench/results/wm_studies_check

Evaluations are cached under --work (keyed by policy, seeds, steps and model weights), so
adding a model re-runs only its own. Writes results.json, results.md and expert_strip.png
(the expert's first 100 steps from --strip-seed: one row per model, then MuJoCo) to --out.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np

from iwsim.core.errors import reporting_errors
from iwsim.core.resources import set_threads
from iwsim.eval.ranking import agreement
from iwsim.eval.records import command_line
from iwsim.experiments.common import evaluate_policies
from iwsim.experiments.policy_eval import PolicyEvalConfig
from iwsim.yardstick.studies import TELEOP_SEED, strip, teleop


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--models", nargs="+", required=True, help="NAME=CHECKPOINT world models")
    p.add_argument("--episodes", type=int, default=20, help="ranking episodes per policy (default: %(default)s)")
    p.add_argument("--steps", type=int, default=300, help="steps per episode (default: %(default)s)")
    p.add_argument("--candidates", type=int, default=32, help="teleoperation takes per model (default: %(default)s)")
    p.add_argument("--skip-teleop", action="store_true", help="only the ranking check")
    p.add_argument("--work", default="runs/wm_studies_check", help="cache (default: %(default)s)")
    p.add_argument("--out", default="bench/results/wm_studies_check", help="report (default: %(default)s)")
    p.add_argument("--strip-seed", type=int, default=100000,
                   help="the expert's episode pictured in each model and MuJoCo (default: %(default)s)")
    p.add_argument("--threads", type=int, default=1)
    args = p.parse_args(argv)
    set_threads(args.threads)
    models = dict(m.split("=", 1) for m in args.models)
    work, out = Path(args.work), Path(args.out)
    seeds = list(range(100000, 100000 + args.episodes))
    policies = PolicyEvalConfig().scripted()
    t0 = time.perf_counter()
    real = evaluate_policies(policies, "pusht", seeds=seeds, steps=args.steps, world_model=None,
                             out=work / "eval", progress=False)
    names = sorted(policies, key=lambda n: -real[n]["mean_max_iou"])
    report: dict = {"command": command_line(__file__, argv), "seeds": [seeds[0], seeds[-1]], "steps": args.steps,
                    "mujoco": {n: real[n]["mean_max_iou"] for n in names}, "models": {}}
    if not args.skip_teleop:
        report["mujoco_teleop"] = teleop("mujoco", None, work, args.candidates, TELEOP_SEED, args.steps)
    for name, ckpt in models.items():
        res = evaluate_policies(policies, "world-model", seeds=seeds, steps=args.steps, world_model=ckpt,
                                out=work / "eval" / name, progress=False)
        wm = [res[n]["mean_max_iou"] for n in names]
        # the trivial baseline: every policy scored on the model's first frame (repeat it)
        first = float(np.mean([np.asarray(res[n]["iou_per_step"])[:, 0].mean() for n in names]))
        entry = {"checkpoint": ckpt, "scores": dict(zip(names, wm)), "repeat_first_frame": first,
                 "agreement": agreement([real[n]["mean_max_iou"] for n in names], wm, ("MuJoCo", name))}
        if not args.skip_teleop:
            entry["teleop"] = teleop(name, ckpt, work, args.candidates, TELEOP_SEED, args.steps)
        report["models"][name] = entry
        print(name, json.dumps({k: v for k, v in entry.items() if k != "scores"}), flush=True)
    report["seconds"] = time.perf_counter() - t0
    out.mkdir(parents=True, exist_ok=True)
    strip(out / "expert_strip.png", [*models.values(), None], args.strip_seed)
    (out / "results.json").write_text(json.dumps(report, indent=2))
    (out / "results.md").write_text(markdown(report))
    print((out / "results.md").read_text())
    return 0


def markdown(r: dict) -> str:
    ms = list(r["models"])
    lines = ["# Can the world model carry the studies? (`bench/wm_studies_check.py`)", "", f"`{r['command']}`", "",
             f"Scripted policies from MuJoCo seeds {r['seeds'][0]}-{r['seeds'][1]}, {r['steps']} steps; "
             "mean max IoU (pixel IoU in the model).", "",
             "| policy | MuJoCo | " + " | ".join(ms) + " |", "|---|---|" + "---|" * len(ms)]
    for n, v in r["mujoco"].items():
        lines.append(f"| {n} | {v:.3f} | " + " | ".join(f"{r['models'][m]['scores'][n]:.3f}" for m in ms) + " |")
    lines += ["", "| model | Pearson r | Spearman rho | MMRV | spread (max - min) | repeat first frame | "
                  "teleop kept | teleop mean max IoU |", "|---|---|---|---|---|---|---|---|"]

    def f(v):
        return "undefined" if v is None else f"{v:.3f}"

    if "mujoco_teleop" in r:
        t = r["mujoco_teleop"]
        spread = np.ptp(list(r["mujoco"].values()))
        lines.append(f"| MuJoCo | 1 | 1 | 0 | {spread:.3f} | - | {t['kept']}/{t['candidates']} | "
                     f"{t['mean_candidate_max_iou']:.3f} |")
    for m in ms:
        e = r["models"][m]
        a, t = e["agreement"], e.get("teleop")
        tele = f"{t['kept']}/{t['candidates']} | {t['mean_candidate_max_iou']:.3f}" if t else "- | -"
        lines.append(f"| {m} | {f(a['pearson'])} | {f(a['spearman'])} | {f(a['mmrv'])} | "
                     f"{np.ptp(list(e['scores'].values())):.3f} | {e['repeat_first_frame']:.3f} | {tele} |")
    return "\n".join(lines) + "\n"


if __name__ == "__main__":
    raise SystemExit(reporting_errors("wm_studies_check.py", main))
