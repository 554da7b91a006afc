"""Issue 45: does the pile model's over-credit of policies come from the score's
denominator? The task's pixel score divides the pieces in the tray by the pieces seen in
the same frame, so a model that loses pieces outside the tray scores a policy up. Scored
instead against the pieces of the episode's first frame (a conserved number, as MuJoCo's
exact score divides by the pieces there are), lost pieces count against the model. Each
POLICY runs closed loop in MuJoCo and in the model from the same first states (the
ranking study's seeds); the mean max share under both denominators, each policy's offset
(model - MuJoCo) and the agreement over the policies given:

    MUJOCO_GL=egl python bench/probes/pile_denominator.py checkpoints/pilesweep-64 \\
        expert expert:noise=0.008 expert:latency=3 play runs/.../dp-wm0-sim100 --work runs/pile_denominator

A POLICY is a scripted policy of the task (``KIND`` or ``KIND:noise=0.008,latency=3``) or a
policy checkpoint or run. Each policy's rollouts are cached in ``--work`` (another process
can fill it with other policies); the table covers every policy cached there.
"""
import argparse
import json
from pathlib import Path
from typing import Any

import numpy as np
import torch

from iwsim.core.resources import set_threads
from iwsim.envs.pilesweep.pixels import count_pieces
from iwsim.eval.policy import rollout
from iwsim.eval.ranking import agreement
from iwsim.policies.factory import load_policy
from iwsim.policies.scripted import ScriptedBatch, ScriptedConfig
from iwsim.world_model import WorldModel

ENVS = ("pilesweep", "world-model")


def scripted(spec: str) -> ScriptedConfig | None:
    """The scripted policy ``KIND[:k=v,...]``, or None for a checkpoint's path."""
    if "/" in spec:
        return None
    kind, _, args = spec.partition(":")
    kw = {k: (int(v) if k == "latency" else float(v)) for k, v in (a.split("=") for a in args.split(",") if a)}
    return ScriptedConfig(kind, **kw)


def shares(frames: np.ndarray) -> dict[str, Any]:
    """Per episode, the max over steps of the pieces in the tray over those seen in the
    frame (``seen``) and over those seen in the first frame (``first``, at most 1); and
    the mean pieces seen in the first and the last frame."""
    inside, seen = count_pieces(frames)
    now = inside / np.maximum(seen, 1)
    first = np.minimum(inside / np.maximum(seen[:, :1], 1), 1.0)
    return {"seen": now.max(1).tolist(), "first": first.max(1).tolist(),
            "seen_first": seen[:, 0].mean().item(), "seen_last": seen[:, -1].mean().item()}


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("model")
    p.add_argument("policies", nargs="*")
    p.add_argument("--seeds", type=int, default=20)
    p.add_argument("--steps", type=int, default=200)
    p.add_argument("--work", default="runs/pile_denominator")
    args = p.parse_args()
    set_threads(1)
    work = Path(args.work)
    work.mkdir(parents=True, exist_ok=True)
    wm = WorldModel.load(args.model)
    seeds = list(range(100000, 100000 + args.seeds))
    for spec in args.policies:
        cfg = scripted(spec)
        ckpt = Path(spec)
        name = cfg.name if cfg is not None else (f"{ckpt.parent.parent.name}@{int(ckpt.name)}"
                                                 if ckpt.parent.name == "checkpoints" else ckpt.name)
        path = work / f"{name}.json"
        if path.is_file():
            continue
        row = {"learned": cfg is None}
        for env in ENVS:
            policy = ScriptedBatch(cfg, task="pilesweep") if cfg is not None else load_policy(spec)
            torch.manual_seed(0)
            r = rollout(policy, env, seeds, args.steps, world_model=wm if env == "world-model" else None,
                        record=len(seeds), progress=False)
            row[env] = shares(r["frames"])
        path.write_text(json.dumps(row))
        print(f"{name}: done")
    rows = {f.stem: json.loads(f.read_text()) for f in sorted(work.glob("*.json"))}
    print(f"\n{len(seeds)} first states x {args.steps} steps; mean max share in the tray over the pieces seen in "
          "the frame (now) and in the first frame (first)\n")
    print("| policy | MuJoCo now | model now (offset) | MuJoCo first | model first (offset) | pieces seen @0 -> @end "
          "(MuJoCo; model) |")
    print("|---|---|---|---|---|---|")
    mean = {(n, env, d): float(np.mean(r[env][d])) for n, r in rows.items() for env in ENVS for d in ("seen", "first")}
    for n, r in sorted(rows.items(), key=lambda kv: -mean[(kv[0], "pilesweep", "seen")]):
        m, w = r["pilesweep"], r["world-model"]
        cells = []
        for d in ("seen", "first"):
            a, b = mean[(n, "pilesweep", d)], mean[(n, "world-model", d)]
            cells += [f"{a:.3f}", f"{b:.3f} ({b - a:+.3f})"]
        print(f"| {n}{' (learned)' if r['learned'] else ''} | {' | '.join(cells)} | {m['seen_first']:.1f} -> "
              f"{m['seen_last']:.1f}; {w['seen_first']:.1f} -> {w['seen_last']:.1f} |")
    print()
    for group, names in (("all", list(rows)), ("scripted", [n for n in rows if not rows[n]["learned"]]),
                         ("learned", [n for n in rows if rows[n]["learned"]])):
        if len(names) < 3:
            continue
        for d in ("seen", "first"):
            a = agreement([mean[(n, "pilesweep", d)] for n in names], [mean[(n, "world-model", d)] for n in names])
            off = np.mean([mean[(n, "world-model", d)] - mean[(n, "pilesweep", d)] for n in names])
            r, rho, mmrv = (f"{a[k]:.3f}" if a[k] is not None else "-" for k in ("pearson", "spearman", "mmrv"))
            print(f"{group} ({len(names)}), {d:5s}: r {r} rho {rho} MMRV {mmrv}, mean offset {off:+.3f}")


if __name__ == "__main__":
    main()
