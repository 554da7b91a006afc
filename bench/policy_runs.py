"""One imitation-policy run of the issue-25 campaign: train a preset with some fields
changed, then score chosen checkpoints closed-loop in MuJoCo.

    MUJOCO_GL=egl OMP_NUM_THREADS=1 python bench/policy_runs.py --name dp-lr1e-4 --policy dp \
        --data runs/experiments/demos/sim_expert.zarr:100 --steps 6000 --eval-at 2000,4000,6000 \
        --set train.lr=1e-4

``--set`` changes one field of the preset (``model.X``, ``train.X`` or ``shift``; the
value is JSON, bare words are strings); ``--exec FIELD=VALUE`` changes only how the trained
policy runs (the policy's registered ``execution`` fields, e.g. ``n_action_steps=4`` or ACT's
``temporal_ensemble=null``). Runs go to ``runs/pol/NAME`` and resume exactly; evaluations
are cached beside them, one file per checkpoint, seeds and execution.
Validation seeds (200000+) choose; ``--test`` scores on the test seeds (100000+) instead,
``--on-train`` from the training takes' own first states (can the policy replay them?).
``--score-only`` scores checkpoints a run has already saved without training it further
(e.g. while it trains, or a longer run's earlier steps). One line per scored checkpoint is
printed and appended to ``runs/pol/NAME/scores.jsonl``.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
import time
from pathlib import Path

import torch

from iwsim.core.checkpoint import load_json, write_json_atomic
from iwsim.core.config import from_dict, to_dict
from iwsim.core.errors import reporting_errors
from iwsim.data.store import EpisodeStore
from iwsim.eval.policy import rollout, summarize
from iwsim.eval.policy_runs import TEST_SEED, VAL_SEED, eval_path
from iwsim.experiments.common import checkpoints
from iwsim.policies import POLICIES, PRESETS, PolicyStageConfig
from iwsim.policies.data import parse_mixture
from iwsim.policies.factory import load_policy
from iwsim.policies.train import train_policy


def _value(text: str):
    try:
        return json.loads(text)
    except json.JSONDecodeError:
        return text


def stage_config(preset: str, steps: int, sets: list[str], bf16: bool, seed: int) -> PolicyStageConfig:
    """The preset with ``sets`` (``section.field=value``) applied, trained ``steps`` steps."""
    data = to_dict(PRESETS[preset])
    data["train"].update(steps=steps, seed=seed, cpu_bf16=bf16)
    for item in sets:
        key, _, value = item.partition("=")
        section, _, field = key.partition(".")
        if field:
            data[section][field] = _value(value)
        else:
            data[section] = _value(value)
    return from_dict(PolicyStageConfig, data)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--name", required=True)
    p.add_argument("--policy", choices=tuple(POLICIES), required=True)
    p.add_argument("--preset", help="default: the policy's name")
    p.add_argument("--data", help="the demonstration stores (STORE:N,...); not needed with --score-only")
    p.add_argument("--steps", type=int, help="training steps (not needed with --score-only)")
    p.add_argument("--eval-at", default="", help="comma-separated checkpoint steps to score (default: the last)")
    p.add_argument("--set", action="append", default=[], metavar="SECTION.FIELD=VALUE")
    p.add_argument("--exec", action="append", default=[], metavar="FIELD=VALUE", dest="execution")
    p.add_argument("--bf16", action="store_true")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--episodes", type=int, default=20)
    p.add_argument("--eval-steps", type=int, default=600)
    p.add_argument("--test", action="store_true", help="score on the test seeds (100000+), not validation")
    p.add_argument("--on-train", action="store_true",
                   help="score from the first states of the training takes themselves (the first store's seeds, "
                        "up to --episodes): the memorisation test")
    p.add_argument("--root", default="runs/pol")
    p.add_argument("--score-only", action="store_true",
                   help="score the run's saved checkpoints without training it (--steps is then ignored)")
    args = p.parse_args(argv)
    if args.data is None and not (args.score_only and not args.on_train):
        p.error("--data is required (except with --score-only, without --on-train)")
    if args.steps is None and not args.score_only:
        p.error("--steps is required (except with --score-only)")
    preset = args.preset or args.policy
    steps = PRESETS[preset].train.steps if args.steps is None else args.steps
    cfg = stage_config(preset, steps, args.set, args.bf16, args.seed)
    run = Path(args.root) / args.name
    t0 = time.perf_counter()
    if not args.score_only:
        train_policy(cfg, parse_mixture(args.data), run, device=torch.device("cpu"), progress=sys.stderr.isatty())
    train_seconds = time.perf_counter() - t0
    ckpts = checkpoints(run)
    if not ckpts:
        raise SystemExit(f"{run} has no checkpoint to score.")
    wanted = [int(s) for s in args.eval_at.split(",") if s] or [max(ckpts)]
    missing = [s for s in wanted if s not in ckpts]
    if missing:
        raise SystemExit(f"no checkpoint at steps {missing}; the run has {sorted(ckpts)}.")
    if args.on_train:
        split = "train"
        seeds = [int(s) for s in EpisodeStore.open(parse_mixture(args.data)[0].path).attrs["seeds"][:args.episodes]]
    else:
        first = TEST_SEED if args.test else VAL_SEED
        split = "test" if args.test else "val"
        seeds = list(range(first, first + args.episodes))
    execution = {k: _value(v) for k, _, v in (e.partition("=") for e in args.execution)}
    tag = "".join(f"-{k}{v}" for k, v in sorted(execution.items()))
    with open(run / "scores.jsonl", "a") as f:
        for step in wanted:
            path = eval_path(run, split, args.episodes, args.eval_steps, step, tag)
            if path.is_file():
                r = load_json(path)
            else:
                torch.manual_seed(0)  # the policy's sampling noise: the same evaluation gives the same scores
                policy = load_policy(ckpts[step], **execution)
                result = rollout(policy, "pusht", seeds, args.eval_steps, image_size=policy.image_size,
                                 progress=sys.stderr.isatty())
                r = {**summarize(result["iou"].max(1), seeds, result["success_score"]), "seconds": result["seconds"]}
                path.parent.mkdir(parents=True, exist_ok=True)
                write_json_atomic(path, r)
            row = {"run": args.name, "step": step, "execution": execution, "split": split, "episodes": len(seeds),
                   "eval_steps": args.eval_steps, "mean_max_iou": round(r["mean_max_iou"], 4),
                   "success_rate": round(r["success_rate"], 4), "train_seconds_this_call": round(train_seconds),
                   "config": {"model": cfg.model, "train": dataclasses.asdict(cfg.train), "shift": cfg.shift}}
            f.write(json.dumps(row) + "\n")
            print(f"{args.name}{tag} @{step}: mean max IoU {r['mean_max_iou']:.3f}, success {r['success_rate']:.2f} "
                  f"({len(seeds)} {split} seeds x {args.eval_steps} steps)", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(reporting_errors("policy_runs.py", main))
