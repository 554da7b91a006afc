"""Does the shape of a model's own score curve rank its errors (issue 66 item 3)? For each
family episode the yardstick evaluated (its cached evaluations under ``--work``), a few
signals read from the world model's per-step IoU alone, fixed before looking at the errors:

- ``jump``: the largest one-step rise (the model snapping the block into place);
- ``drop``: the largest one-step fall;
- ``volatility``: the summed absolute step changes;
- ``time_of_max``: when the episode's max is reached (share of the horizon);
- ``max_minus_last``: how far the score falls back from its max;

beside ``sample_spread`` (the range of the max over the model's samples, where the
evaluation drew several), each as Spearman's rho against the episode's error
|model max IoU - MuJoCo max IoU| over the seen families, the unseen ones and all.

    python bench/probes/score_shape_trust.py --work runs/ys --model-hash ccd7b46d07fd0743
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
from scipy import stats

from iwsim.core.errors import InputError, reporting_errors

SEEN = ("expert", "lag3", "pause")  # the shipped recipe's data held these motions (bench/yardstick.py)


def shape_signals(iou: np.ndarray) -> dict[str, np.ndarray]:
    """The signals of each episode's per-step score curve ``iou`` (E, T + 1)."""
    step = np.diff(iou, axis=1)
    return {"jump": step.max(1), "drop": -step.min(1), "volatility": np.abs(step).sum(1),
            "time_of_max": iou.argmax(1) / step.shape[1], "max_minus_last": iou.max(1) - iou[:, -1]}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--work", type=Path, default=Path("runs/ys"), help="the yardstick's --work")
    ap.add_argument("--model-hash", required=True, help="the model's directory under WORK/families")
    args = ap.parse_args()
    model_dir = args.work / "families" / args.model_hash / "world-model"
    real_dir = args.work / "families" / "mujoco" / "pusht"
    files = sorted(model_dir.glob("*.json"))
    if not files:
        raise InputError(f"no cached family evaluations in {model_dir}")
    errors, signals, seen = [], {}, []
    for path in files:
        model, real = json.loads(path.read_text()), json.loads((real_dir / path.name).read_text())
        if model["key"]["seeds"] != real["key"]["seeds"]:
            raise InputError(f"{path.name}: the model's and MuJoCo's first states differ")
        iou = np.asarray(model["iou_per_step"])
        errors.append(np.abs(iou.max(1) - np.asarray(real["iou_per_step"]).max(1)))
        found = shape_signals(iou)
        if "sample_spread" in model:
            found["sample_spread"] = np.asarray(model["sample_spread"]["per_episode"], dtype=float)
        for name, values in found.items():
            signals.setdefault(name, []).append(values)
        seen.append(np.full(len(iou), path.stem in SEEN))
    error, is_seen = np.concatenate(errors), np.concatenate(seen)
    print(f"{args.model_hash}: {int(is_seen.sum())} seen and {int((~is_seen).sum())} unseen episodes, "
          f"mean error {error.mean():.3f}")
    print("| signal | rho seen | rho unseen | rho all |\n|---|---|---|---|")
    for name, parts in signals.items():
        if len(parts) != len(files):
            continue  # a signal some evaluations lack
        values = np.concatenate(parts)
        rho = [stats.spearmanr(values[m], error[m]).statistic for m in (is_seen, ~is_seen, np.ones_like(is_seen))]
        print(f"| {name} | " + " | ".join(f"{r:+.2f}" for r in rho) + " |")


if __name__ == "__main__":
    raise SystemExit(reporting_errors("score_shape_trust.py", main))
