"""Can a trust signal or the other policies tighten the paired estimates (issue 66)? On the
yardstick's families (a ``bench/yardstick.py --paired-episodes`` results.json: each
family's model and MuJoCo scores of the same 16 first states, its trust signals and 50
held-out MuJoCo episodes) or the policy-evaluation study's zoo (an ``iwsim experiment
policy-eval --paired-episodes`` results.json: each policy's scores of the same 20 first
states in both, and its held-out mean; no per-episode signals), many random choices of
which n first states are paired, and for each design the share of 95% intervals that
cover the held-out mean and their mean half-width (clipped to [0, 1]):

- ``real alone``: the n MuJoCo episodes' mean, Student t (the trivial baseline);
- ``PPI``: :func:`iwsim.eval.paired.paired_estimate` as the studies use it;
- ``stratified by SIGNAL``: the states split at the signal's median, 60% of the pairs in
  the half the signal distrusts (at least 2 in each), a PPI estimate per half
  combined by the halves' shares, Welch-Satterthwaite degrees of freedom (stratified PPI;
  the signal chooses which states to pair, and the estimate stays unbiased);
- ``cross-fitted lam``: the model's weight fitted on the other families' pairs (their
  pooled within-family slope of MuJoCo on the model, clipped to [0, 1]), so the family's
  own n pairs keep n - 1 degrees of freedom.

    python bench/probes/pairing_designs.py runs/ys_paired/results.json --model shipped
    python bench/probes/pairing_designs.py runs/pe_paired/results.json
"""

from __future__ import annotations

import argparse
import json
import math

import numpy as np
from scipy import stats

from iwsim.core.errors import InputError, reporting_errors
from iwsim.eval.paired import paired_estimate, real_alone

SIGNALS = ("sample_spread", "command_lead")
TILT = 0.6  # the share of the pairs in the distrusted half (at least 2 in each)


def clipped_half(estimate: float, half: float) -> tuple[float, float]:
    """The [0, 1]-clipped interval's (lo, hi) of ``estimate`` +- ``half``."""
    return max(0.0, estimate - half), min(1.0, estimate + half)


def ppi(f: np.ndarray, y: np.ndarray, idx: np.ndarray, lam: float | None = None) -> tuple[float, float]:
    lo, hi = paired_estimate(f, y[idx], idx, lam=lam, bounds=(0.0, 1.0))["interval"]
    return lo, hi


def stratified(f: np.ndarray, y: np.ndarray, u: np.ndarray, n: int, rng: np.random.Generator
               ) -> tuple[float, float]:
    order = np.argsort(-u, kind="stable")
    halves = (order[: len(order) // 2], order[len(order) // 2:])  # distrusted first
    tilted = max(2, min(n - 2, math.ceil(TILT * n)))
    counts = (tilted, n - tilted)
    parts = []
    for states, k in zip(halves, counts):
        pick = np.sort(rng.choice(len(states), k, replace=False))
        est = paired_estimate(f[states], y[states][pick], pick, lam=1.0)
        parts.append((len(states) / len(f), est["estimate"], est["std_error"] ** 2, est["df"]))
    estimate = sum(w * e for w, e, _, _ in parts)
    var = sum(w**2 * v for w, _, v, _ in parts)
    df = var**2 / sum((w**2 * v) ** 2 / d for w, _, v, d in parts)
    return clipped_half(estimate, float(stats.t.ppf(0.975, df)) * math.sqrt(var))


def cross_lambda(model: dict[str, np.ndarray], real: dict[str, np.ndarray], picks: dict[str, np.ndarray],
                 family: str) -> float:
    xs, ys = [], []
    for other in model:
        if other != family:
            a, b = model[other][picks[other]], real[other][picks[other]]
            xs.append(a - a.mean())
            ys.append(b - b.mean())
    x, z = np.concatenate(xs), np.concatenate(ys)
    return float(np.clip((x * z).sum() / max(float((x * x).sum()), 1e-12), 0.0, 1.0))


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], formatter_class=argparse.RawTextHelpFormatter)
    p.add_argument("results", help="a bench/yardstick.py results.json with the families part and --paired-episodes")
    p.add_argument("--model", default="shipped", help="the model's name in it (default: %(default)s)")
    p.add_argument("--ns", default="2,5,10", help="paired episodes per family (default: %(default)s)")
    p.add_argument("--draws", type=int, default=400, help="random choices of the paired states (default: %(default)s)")
    p.add_argument("--seed", type=int, default=0)
    args = p.parse_args()
    with open(args.results) as fh:
        r = json.load(fh)
    model, real, truth, signals = (_study if "policies" in r else _families)(r, args)
    fams = list(model)
    rng = np.random.default_rng(args.seed)
    print(f"{len(fams)} policies x {len(model[fams[0]])} first states, {args.draws} random pairings each; "
          "95% intervals against the held-out MuJoCo episodes")
    print("| n | design | coverage | mean half-width |\n|---|---|---|---|")
    for n in (int(x) for x in args.ns.split(",")):
        rows: dict[str, list[tuple[bool, float]]] = {}
        for _ in range(args.draws):
            picks = {f: np.sort(rng.choice(len(model[f]), n, replace=False)) for f in fams}
            for f in fams:
                designs = {"real alone": real_alone(real[f][picks[f]]), "PPI": ppi(model[f], real[f], picks[f]),
                           "cross-fitted lam": ppi(model[f], real[f], picks[f],
                                                   lam=cross_lambda(model, real, picks, f))}
                if n >= 4:
                    for s, u in signals.items():
                        designs[f"stratified by {s}"] = stratified(model[f], real[f], u[f], n, rng)
                for name, (lo, hi) in designs.items():
                    rows.setdefault(name, []).append((lo <= truth[f] <= hi, (hi - lo) / 2))
        for name, v in rows.items():
            a = np.asarray(v, np.float64)
            print(f"| {n} | {name} | {a[:, 0].mean():.3f} | {a[:, 1].mean():.3f} |")


Scores = dict[str, np.ndarray]


def _families(r: dict, args: argparse.Namespace) -> tuple[Scores, Scores, dict[str, float], dict[str, Scores]]:
    """A yardstick report's families: model and MuJoCo scores, held-out means, signals."""
    try:
        g = r["models"][args.model]["generalisation"]
        mujoco, holdout = r["mujoco"]["families"], r["mujoco"]["families_holdout"]
    except KeyError as e:
        raise InputError(f"{args.results} has no families part with held-out episodes for model "
                         f"{args.model!r} (missing {e}).") from None
    fams = [f for f in g["scores"] if f in holdout]
    return ({f: np.asarray(g["scores"][f], np.float64) for f in fams},
            {f: np.asarray(mujoco[f], np.float64) for f in fams}, {f: float(np.mean(holdout[f])) for f in fams},
            {s: {f: np.asarray(g["signals"][s][f], np.float64) for f in fams} for s in SIGNALS})


def _study(r: dict, args: argparse.Namespace) -> tuple[Scores, Scores, dict[str, float], dict[str, Scores]]:
    """A policy-evaluation study's zoo: each policy's scores in the model and in the task's
    simulator, and its held-out mean (the paired section's truth)."""
    if "paired" not in r:
        raise InputError(f"{args.results} is a study without paired estimates (--paired-episodes).")
    task = r["config"]["task"]
    key = "max_iou" if task == "pusht" else "max_score"
    truth = next(iter(r["paired"]["by_n"].values()))["policies"]
    names = [p["name"] for p in r["policies"]]
    return ({p["name"]: np.asarray(p["world-model"][key], np.float64) for p in r["policies"]},
            {p["name"]: np.asarray(p[task][key], np.float64) for p in r["policies"]},
            {n: float(truth[n]["truth"]) for n in names}, {})


if __name__ == "__main__":
    raise SystemExit(reporting_errors("pairing_designs.py", main))
