"""Two policies scored on the same first states, compared episode by episode.

``iwsim eval policy`` run for two policies with the same ``--seed``, ``--episodes``,
``--steps`` and environment scores them on the same first states; the difference of their
scores is then paired, and its interval is far narrower than two independent means' would
be. Reported: each policy's mean max score and success rate, the paired difference of the
max scores with its Student t 95% interval, how many first states each policy did better
on, and the successes only one of them had.

    python bench/compare_policies.py two=runs/dp_two_eval top=runs/dp_top_eval \\
        --out bench/results/two_view_policy
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

from iwsim.core.checkpoint import load_json, write_json_atomic, write_text_atomic
from iwsim.core.errors import InputError, one_line
from iwsim.eval.paired import t_half_width
from iwsim.eval.records import command_line, with_command

SAME = ("env", "steps", "scorer", "world_model")  # what two evaluations must share


def load(spec: str) -> tuple[str, dict]:
    """NAME=EVAL_DIR (or its results.json) -> (NAME, the evaluation's record)."""
    name, sep, path = spec.partition("=")
    if not sep or not name or not path:
        raise InputError(f"expected NAME=EVAL_DIR, got {spec!r}.")
    p = Path(path)
    p = p / "results.json" if p.is_dir() else p
    if not p.is_file():
        raise InputError(f"{path} has no results.json: run iwsim eval policy --out {path} first.")
    record = load_json(p)
    if not record.get("episodes"):
        raise InputError(f"{p} records no episodes.")
    return name, record


def score_key(episode: dict) -> str:
    """The per-episode score of an evaluation: ``max_iou`` (T-push) or ``max_score`` (another task)."""
    return next(k for k in episode if k.startswith("max_"))


def compare(a: tuple[str, dict], b: tuple[str, dict], level: float = 0.95) -> dict:
    """The paired comparison of two evaluations of the same first states (see the module)."""
    (na, ra), (nb, rb) = a, b
    for key in SAME:
        if ra.get(key) != rb.get(key):
            raise InputError(f"{na} and {nb} were evaluated with other {key} ({ra.get(key)!r} against "
                             f"{rb.get(key)!r}); evaluate both alike to compare them.")
    ea = {e["seed"]: e for e in ra["episodes"]}
    eb = {e["seed"]: e for e in rb["episodes"]}
    if sorted(ea) != sorted(eb):
        raise InputError(f"{na} and {nb} were scored on other first states ({len(ea)} and {len(eb)} seeds, "
                         f"{len(set(ea) & set(eb))} shared); evaluate both with the same --seed and --episodes.")
    if len(ea) < 2:
        raise InputError("a paired interval needs at least 2 first states.")
    seeds = sorted(ea)
    key = score_key(ra["episodes"][0])
    x = np.array([ea[s][key] for s in seeds], np.float64)
    y = np.array([eb[s][key] for s in seeds], np.float64)
    d = x - y
    half = t_half_width(d, level)
    sa = np.array([bool(ea[s]["success"]) for s in seeds])
    sb = np.array([bool(eb[s]["success"]) for s in seeds])
    return {"a": na, "b": nb, "episodes": len(seeds), "first_seed": seeds[0], "steps": ra.get("steps"),
            "env": ra.get("env"), "mean": {na: float(x.mean()), nb: float(y.mean())},
            "success": {na: float(sa.mean()), nb: float(sb.mean())},
            "difference": float(d.mean()), "interval": [float(d.mean()) - half, float(d.mean()) + half],
            "level": level, "better": {na: int((d > 0).sum()), nb: int((d < 0).sum()), "tie": int((d == 0).sum())},
            "success_only": {na: int((sa & ~sb).sum()), nb: int((sb & ~sa).sum())},
            "commands": {na: ra.get("command"), nb: rb.get("command")},
            "scores": {na: x.tolist(), nb: y.tolist()}}


def scatter(c: dict, path: Path) -> None:
    """Each first state's max score under one policy against the other's."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    a, b = c["a"], c["b"]
    fig, ax = plt.subplots(figsize=(4.5, 4.5))
    ax.plot([0, 1], [0, 1], color="0.6", lw=1)
    ax.scatter(c["scores"][b], c["scores"][a], s=18)
    ax.set(xlim=(0, 1), ylim=(0, 1), xlabel=f"{b}: max score", ylabel=f"{a}: max score",
           title=f"{a} - {b}: {c['difference']:+.3f} [{c['interval'][0]:+.3f}, {c['interval'][1]:+.3f}]")
    fig.savefig(path, dpi=120, bbox_inches="tight")
    plt.close(fig)


def report(c: dict, command: str) -> str:
    a, b = c["a"], c["b"]
    lo, hi = c["interval"]
    return "\n".join([
        f"# {a} against {b}, on the same {c['episodes']} first states", "", "```", command, "```", "",
        f"{c['env']}, {c['steps']} steps from each first state (seeds {c['first_seed']}-"
        f"{c['first_seed'] + c['episodes'] - 1}).", "",
        "| policy | mean max score | success | first states it did better on | successes only it had |",
        "|---|---|---|---|---|",
        f"| {a} | {c['mean'][a]:.3f} | {c['success'][a]:.2f} | {c['better'][a]} | {c['success_only'][a]} |",
        f"| {b} | {c['mean'][b]:.3f} | {c['success'][b]:.2f} | {c['better'][b]} | {c['success_only'][b]} |", "",
        f"Paired difference of the max scores ({a} - {b}): **{c['difference']:+.3f}**, "
        f"{100 * c['level']:.0f}% Student t interval [{lo:+.3f}, {hi:+.3f}]"
        f" ({c['better']['tie']} ties).", "",
        "Each first state's score under both: `scatter.png` (written with `--out`).", "",
        "The evaluations:", "", *(f"- {k}: `{v}`" for k, v in c["commands"].items()), ""])


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("evaluations", nargs=2, metavar="NAME=EVAL_DIR", help="two iwsim eval policy outputs")
    p.add_argument("--out", help="write results.md and results.json here")
    args = p.parse_args(argv)
    try:
        c = compare(load(args.evaluations[0]), load(args.evaluations[1]))
    except InputError as e:
        print(f"error: {one_line(e)}", file=sys.stderr)
        return 2
    command = command_line(__file__, argv)
    text = report(c, command)
    print(text)
    if args.out:
        out = Path(args.out)
        out.mkdir(parents=True, exist_ok=True)
        write_json_atomic(out / "results.json", with_command(command, c, sort_keys=True), sort_keys=False)
        write_text_atomic(out / "results.md", text)
        scatter(c, out / "scatter.png")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
