"""Pile sweeping's generalisation part (issue 45): operator families, the pile at rest and
long rollouts, each in MuJoCo and in the world model from the same first states.

    MUJOCO_GL=egl python bench/pile_families.py --models pile=checkpoints/pilesweep-64 \\
        --zoo runs/experiments/pilesweep/policy_eval/runs/expert-258b0869/{dp-100demos,dp-25demos,act-100demos}

1. Families (:data:`iwsim.yardstick.families.FAMILIES`, T-push's yardstick's; ``miss``
   aims at T-push's block and is left out): every family from ``--seeds`` first states
   (MuJoCo seeds from :data:`iwsim.yardstick.families.SEED`, never used for training or by
   the studies) for ``--steps`` steps in both; an episode's score is its max share of the
   pieces in the tray (the pixel scorer). Per family the offset model - MuJoCo with a 95%
   bootstrap interval; pooled Pearson r, Spearman rho and MMRV over all families and over
   the unseen ones. A family is seen when the model's training data covers it
   (``--trained-on``: the collected policies,
   :data:`iwsim.yardstick.families.TRAINING_FAMILIES`); the learned family is the ``--zoo``
   checkpoints round-robin over the episodes.
2. At rest: the pushers held still for :data:`IDLE_STEPS` steps from ``--idle-episodes``
   fresh starts. A model's frame keeps the pile when the scorer sees MuJoCo's count of that
   step within one and the pieces' pixels overlap MuJoCo's (IoU of piece masks) by at
   least :data:`IN_PLACE`; PSNR against MuJoCo's frame at steps 1, 10 and 50.
3. Long rollouts: MuJoCo's play policy for ``--long-steps`` steps from ``--long-episodes``
   starts; the model from the same first frame under the motion MuJoCo executed. A frame
   keeps the pieces when the scorer sees MuJoCo's count of that step within one; per
   stretch of 200 steps too (the scorer's own count on MuJoCo's frames is the reference,
   so the pieces pushed out of view are not counted against the model).

Cached under ``--work`` per model by its weights; ``--out`` gets results.json and
results.md (one section per model).
"""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any

import numpy as np
import torch

from iwsim.core.checkpoint import load_json, named_checkpoints, write_json_atomic, write_text_atomic
from iwsim.core.errors import InputError, check_positive, reporting_errors
from iwsim.core.resources import set_threads
from iwsim.envs.pilesweep.pixels import count_pieces, piece_fraction
from iwsim.envs.registry import get_task
from iwsim.eval.policy import check_model_task, rollout
from iwsim.eval.records import command_line, with_command
from iwsim.eval.rollout import frame_scores
from iwsim.experiments.common import fingerprint
from iwsim.policies.scripted import ScriptedBatch
from iwsim.world_model import WorldModel
from iwsim.yardstick import families as fam

TASK = get_task("pilesweep")
FAMILIES = [f for f in fam.FAMILIES if f != "miss"]
IDLE_STEPS = 50
IN_PLACE = 0.5  # piece-mask IoU of a frame that keeps the pieces in place (pixels with > 1/2 piece colour)
STRETCH = 200  # steps per stretch of a long rollout's table


def within_one(model: np.ndarray, mujoco: np.ndarray) -> np.ndarray:
    """Whether the pieces seen on each model frame are MuJoCo's of the same step, within one."""
    return np.abs(count_pieces(model)[1] - count_pieces(mujoco)[1]) <= 1


def mask_iou(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """IoU of the piece masks of frames ``a`` and ``b`` (..., H, W, 3) (1 where neither has a piece)."""
    pa, pb = piece_fraction(a) > 0.5, piece_fraction(b) > 0.5
    inter, union = (pa & pb).sum((-2, -1)), (pa | pb).sum((-2, -1))
    return np.where(union > 0, inter / np.maximum(union, 1), 1.0)


def cached(path: Path, key: dict, run: Any) -> dict:
    """``run()``'s result, read from ``path`` when its key matches, else computed and written."""
    if path.is_file() and (saved := load_json(path))["key"] == key:
        return saved["result"]
    result = run()
    path.parent.mkdir(parents=True, exist_ok=True)
    write_json_atomic(path, {"key": key, "result": result})
    return result


def mujoco_frames(policy: str, seeds: list[int], steps: int) -> dict[str, np.ndarray]:
    """MuJoCo's frames (E, T + 1, H, W, 3) and executed targets (E, T, A) of ``policy``."""
    r = rollout(ScriptedBatch(policy, task=TASK), TASK.kind, seeds, steps, record=len(seeds), progress=True)
    return {"frames": r["frames"], "target": r["target"]}


def idle(ckpt: str, work: Path, episodes: int) -> dict[str, Any]:
    """Part 2 for the model ``ckpt``."""
    seeds = [fam.SEED + i for i in range(episodes)]

    def run() -> dict[str, Any]:
        ref = mujoco_frames("still", seeds, IDLE_STEPS)["frames"]
        torch.manual_seed(0)
        frames = rollout(ScriptedBatch("still", task=TASK), "world-model", seeds, IDLE_STEPS,
                         world_model=WorldModel.load(ckpt), record=episodes, progress=True)["frames"]
        count, iou = within_one(frames[:, 1:], ref[:, 1:]), mask_iou(frames[:, 1:], ref[:, 1:])
        psnr, _ = frame_scores(ref[:, 1:], frames[:, 1:])  # (E, T)
        per_step = [float(psnr[:, s - 1].mean()) for s in (1, 10, IDLE_STEPS)]
        return {"kept": float((count & (iou >= IN_PLACE)).mean()), "count_kept": float(count.mean()),
                "mask_iou": float(iou.mean()), "psnr": float(psnr.mean()),
                "psnr_at": dict(zip(("1", "10", str(IDLE_STEPS)), per_step)),
                "kept_per_step": (count & (iou >= IN_PLACE)).mean(0).round(3).tolist()}

    return cached(work / "idle" / f"{fingerprint(ckpt)}.json", {"episodes": episodes, "steps": IDLE_STEPS}, run)


def long_rollouts(ckpt: str, work: Path, episodes: int, steps: int) -> dict[str, Any]:
    """Part 3 for the model ``ckpt``."""
    seeds = [fam.SEED + i for i in range(episodes)]

    def run() -> dict[str, Any]:
        ref = mujoco_frames("play", seeds, steps)
        wm = WorldModel.load(ckpt)
        torch.manual_seed(0)
        wm.reset(ref["frames"][:, 0], seed=seeds)
        frames = np.stack([wm.step(ref["target"][:, t]) for t in range(steps)], 1)  # (E, T, H, W, 3)
        ok = within_one(frames, ref["frames"][:, 1:])  # (E, T)
        stretches = [float(ok[:, s:s + STRETCH].mean()) for s in range(0, steps, STRETCH)]
        return {"kept": float(ok.mean()), "kept_per_stretch": stretches,
                "mujoco_seen_first_last": [count_pieces(ref["frames"][:, i])[1].tolist() for i in (0, -1)]}

    return cached(work / "long" / f"{fingerprint(ckpt)}.json", {"episodes": episodes, "steps": steps}, run)


def section(name: str, r: dict[str, Any], settings: dict[str, Any]) -> list[str]:
    """results.md's section for one model."""
    fams, pooled = r["families"]["families"], r["families"]["pooled"]
    lines = [f"## {name} (`{r['checkpoint']}`)", "",
             f"Families: {settings['seeds']} first states each, {settings['steps']} steps, mean max share in the "
             "tray; offset = model - MuJoCo (95% interval over episodes).", "",
             "| family | seen | MuJoCo | model | offset | interval |", "|---|---|---|---|---|---|"]
    for f, row in fams.items():
        lo, hi = row["offset_interval"]
        lines.append(f"| {f} | {'yes' if row['seen'] else 'no'} | {row['mujoco']:.3f} | {row['model']:.3f} | "
                     f"{row['offset']:+.3f} | {lo:+.3f} to {hi:+.3f} |")
    lines += ["", "| pooled over episodes | r | rho | MMRV | max abs family offset |", "|---|---|---|---|---|"]
    for part, p in pooled.items():
        stats = " | ".join("undefined" if p[k] is None else f"{p[k]:.{d}f}"
                           for k, d in (("pearson", 2), ("spearman", 2), ("mmrv", 3)))
        lines.append(f"| {part} families ({len(p['families'])}) | {stats} | {p['max_abs_offset']:.3f} |")
    i, g = r["idle"], r["long"]
    psnr_at = ", ".join(f"{k}: {v:.2f}" for k, v in i["psnr_at"].items())
    lines += ["", f"At rest ({settings['idle_episodes']} starts x {IDLE_STEPS} steps, pushers still): "
              f"frames keeping the pile {i['kept']:.0%} (count within one {i['count_kept']:.0%}, piece-mask IoU "
              f"{i['mask_iou']:.2f}); PSNR against MuJoCo {i['psnr']:.2f} (at step {psnr_at}).", "",
              f"Long rollouts ({settings['long_episodes']} starts x {settings['long_steps']} steps of play): frames "
              f"whose count is MuJoCo's within one {g['kept']:.0%}; per {STRETCH} steps: "
              + ", ".join(f"{v:.0%}" for v in g["kept_per_stretch"]) + ".", ""]
    return lines


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--models", nargs="+", required=True, help="NAME=CHECKPOINT_OR_RUN world models of pile sweeping")
    p.add_argument("--zoo", nargs="+", default=[], help="policy runs or checkpoints of the learned family")
    p.add_argument("--trained-on", nargs="+", default=["play", "expert-noisy"],
                   help="the policies that collected the models' training data (default: %(default)s)")
    p.add_argument("--seeds", type=int, default=16, help="first states per family (default: %(default)s)")
    p.add_argument("--steps", type=int, default=TASK.horizon, help="steps per family episode (default: %(default)s)")
    p.add_argument("--idle-episodes", type=int, default=16, help="starts of the rest test (default: %(default)s)")
    p.add_argument("--long-episodes", type=int, default=4, help="long rollouts (default: %(default)s)")
    p.add_argument("--long-steps", type=int, default=2000, help="steps of a long rollout (default: %(default)s)")
    p.add_argument("--jobs", type=int, default=1, help="families evaluated at once (default: %(default)s)")
    p.add_argument("--work", default="runs/pile_families", help="cache (default: %(default)s)")
    p.add_argument("--out", default="bench/results/pilesweep/families", help="report directory (default: %(default)s)")
    args = p.parse_args(argv)
    check_positive(args, "seeds", "steps", "idle_episodes", "long_episodes", "long_steps", "jobs")
    try:
        seen = fam.seen_families(args.trained_on)
    except ValueError as e:
        raise InputError(str(e)) from None
    models = named_checkpoints(args.models)
    for name, ckpt in models.items():
        check_model_task(WorldModel.load(ckpt), TASK, f"--models {name}={ckpt}")
    wanted = FAMILIES if args.zoo else [f for f in FAMILIES if f != fam.LEARNED]
    set_threads(1)
    work, out = Path(args.work), Path(args.out)
    settings = {k: getattr(args, k) for k in ("zoo", "trained_on", "seeds", "steps", "idle_episodes",
                                              "long_episodes", "long_steps")}
    report: dict[str, Any] = {"settings": settings, "models": {}}
    print("MuJoCo: the families", flush=True)
    mujoco, _ = fam.family_scores(None, work, wanted, args.seeds, args.steps, args.zoo, args.jobs, task=TASK.kind)
    for name, ckpt in models.items():
        print(f"{name}: the families", flush=True)
        scores, _ = fam.family_scores(ckpt, work, wanted, args.seeds, args.steps, args.zoo, args.jobs, task=TASK.kind)
        print(f"{name}: at rest, then long rollouts", flush=True)
        report["models"][name] = {"checkpoint": ckpt, "families": fam.compare(mujoco, scores, seen),
                                  "idle": idle(ckpt, work, args.idle_episodes),
                                  "long": long_rollouts(ckpt, work, args.long_episodes, args.long_steps)}
    command = command_line(__file__, argv)
    out.mkdir(parents=True, exist_ok=True)
    write_json_atomic(out / "results.json", with_command(command, report, sort_keys=True), sort_keys=False)
    lines = ["# Pile sweeping: families, at rest, long rollouts (`bench/pile_families.py`, issue 45)", "",
             "Command:", "", f"    {command}", "",
             f"Seen families (the training data's, `--trained-on {' '.join(args.trained_on)}`): "
             f"{', '.join(f for f in seen if f in wanted)}; the others are unseen.", ""]
    for name, r in report["models"].items():
        lines += section(name, r, settings)
    write_text_atomic(out / "results.md", "\n".join(lines))
    print((out / "results.md").read_text())
    return 0


if __name__ == "__main__":
    raise SystemExit(reporting_errors("pile_families.py", main))
