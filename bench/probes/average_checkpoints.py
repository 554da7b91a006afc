"""Issue 44: does averaging the weights of a run's checkpoints (stochastic weight averaging,
Izmailov et al. 2018, over checkpoints saved at a constant learning rate) lift an ACT run
above its noisy best checkpoint? Writes the uniform average of the checkpoints' inference
weights (each already an EMA) as a one-checkpoint run that ``bench/policy_runs.py
--score-only`` scores:

    python bench/probes/average_checkpoints.py --run runs/pol/act-s2-lr3 --steps 10000,11000,12000,13000,14000 \
        --out runs/pol/act-lr3-swa
    MUJOCO_GL=egl OMP_NUM_THREADS=1 python bench/policy_runs.py --score-only --name act-lr3-swa --policy act \
        --eval-at 14000

The average is stored at the last step averaged (``OUT/checkpoints/<step>``). Floating-point
tensors are averaged; any other tensor must agree across the checkpoints and is kept.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import torch

from iwsim.core.checkpoint import load_json, load_tensors, save_model_dir
from iwsim.core.errors import reporting_errors
from iwsim.experiments.common import checkpoints


def average(paths: list[Path]) -> dict[str, torch.Tensor]:
    """The uniform average of the ``model.safetensors`` under ``paths`` (same keys and shapes)."""
    tensors = [load_tensors(p / "model.safetensors") for p in paths]
    first = tensors[0]
    for path, t in zip(paths[1:], tensors[1:], strict=True):
        if t.keys() != first.keys() or any(t[k].shape != first[k].shape for k in first):
            raise SystemExit(f"{path} does not hold the same tensors as {paths[0]}.")
    out = {}
    for k, v in first.items():
        if v.is_floating_point():
            out[k] = (sum(t[k].double() for t in tensors) / len(tensors)).to(v.dtype)
        elif all(torch.equal(t[k], v) for t in tensors[1:]):
            out[k] = v
        else:
            raise SystemExit(f"the non-float tensor {k} differs between the checkpoints; it cannot be averaged.")
    return out


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--run", required=True, help="a policy run (runs/pol/NAME)")
    p.add_argument("--steps", required=True, help="the saved steps to average, comma-separated")
    p.add_argument("--out", required=True, help="the run to write (its checkpoints/<last step>)")
    args = p.parse_args(argv)
    saved = checkpoints(Path(args.run))
    steps = sorted(int(s) for s in args.steps.split(","))
    missing = [s for s in steps if s not in saved]
    if missing:
        raise SystemExit(f"{args.run} has no checkpoint at steps {missing}; it has {sorted(saved)}.")
    paths = [saved[s] for s in steps]
    config = load_json(paths[-1] / "config.json")
    if any(load_json(q / "config.json") != config for q in paths[:-1]):
        raise SystemExit("the checkpoints' configs differ; average checkpoints of one run.")
    out = save_model_dir(Path(args.out) / "checkpoints" / f"{steps[-1]:08d}", average(paths), config)
    print(f"averaged {len(paths)} checkpoints of {args.run} (steps {steps}) into {out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(reporting_errors("average_checkpoints.py", main))
