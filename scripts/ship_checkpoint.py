"""Record a shipped checkpoint's metrics.json (what tests/test_shipped_checkpoint.py and _pile.py check).

    MUJOCO_GL=egl .venv/bin/python scripts/ship_checkpoint.py --checkpoint checkpoints/pusht-64 \
        [--bench bench/results/pusht-64/results.json --bench-model shipped]

- ``mujoco_rollout``: 32-step rollouts from the MuJoCo initial frames of seeds 100000..100003
  under the scripted expert's actions, PSNR/SSIM against MuJoCo's frames (noise seed 0).
- ``open_loop_192``: copied from an ``iwsim bench`` result, when given.
- ``fidelity``: copied from a ``bench/ablate_dynamics.py eval`` result, when given (action
  gap, one-step error against copy-previous, pusher and block tracking, T found).
- ``yardstick``: the model's row of a ``bench/yardstick.py`` result, when given (T kept,
  teleoperated takes, the scripted policies' ranking, the 2000-step run, speed).
- ``training``: steps and wall-clock of both stages, from the runs named in the provenance.
  With ``--extends "WHAT"`` the new model is a fine-tune of the one it replaces: the chain
  already in its metrics.json is kept and this run is appended to it as the next
  ``stage2_finetuneN`` (``WHAT`` says how it was trained, e.g. ``--init contactmore2, lr 2e-4``).
  Recording the same model again keeps its chain as it is.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from iwsim.core.checkpoint import write_json_atomic
from iwsim.core.errors import reporting_errors
from iwsim.eval.benchmark import training_info
from iwsim.eval.rollout import against_mujoco
from iwsim.world_model import WorldModel

SEEDS = (100000, 100001, 100002, 100003)
STEPS = 32
TOLERANCE_DB = 0.5  # CPU builds and BLAS libraries may differ in the last bits


def mujoco_rollout(wm: WorldModel, seeds: tuple[int, ...] = SEEDS, steps: int = STEPS) -> dict:
    results = [against_mujoco(wm, s, steps, "expert") for s in seeds]
    psnr = [float(r.psnr.mean()) for r in results]
    return {"policy": "expert", "steps": steps, "seeds": list(seeds), "noise_seed": 0,
            "psnr": float(np.mean(psnr)), "psnr_per_seed": psnr,
            "ssim": float(np.mean([r.ssim.mean() for r in results])),
            "tolerance_db": TOLERANCE_DB}


def run_info(checkpoint: Path) -> dict:
    info = training_info(checkpoint)
    return {"steps": info["train_steps"], "minutes": round(info["train_minutes"], 1)} if info else {}


def training_chain(old: dict, prov: dict, extends: str | None) -> dict:
    """The training chain of the model whose provenance is ``prov``. ``old`` is the chain in
    the metrics.json being replaced: kept as it is when it already ends with this model's
    run (the same model recorded again), extended by that run with ``extends``."""
    source = Path(prov.get("source", "-"))
    run = source.parent.parent if source.parent.name == "checkpoints" else source
    if run.is_absolute() and run.is_relative_to(Path.cwd()):  # export-model records absolute sources
        run = run.relative_to(Path.cwd())
    if old and str(list(old.values())[-1].get("run", "")).split(" ")[0] == str(run):
        return old
    if not extends:
        return {"stage1": run_info(Path(prov.get("ae_checkpoint", "-"))), "stage2": run_info(source)}
    if not old:
        raise SystemExit("--extends: the replaced checkpoint's metrics.json holds no training chain to extend.")
    n = 1 + sum(k.startswith("stage2_finetune") for k in old)
    return {**old, f"stage2_finetune{n if n > 1 else ''}": {**run_info(source), "run": f"{run} ({extends})"}}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--checkpoint", type=Path, default=Path("checkpoints/pusht-64"))
    ap.add_argument("--bench", type=Path, help="an iwsim bench results.json holding this checkpoint")
    ap.add_argument("--bench-model", default="shipped", help="the checkpoint's name in that result")
    ap.add_argument("--ablate", type=Path, help="a bench/ablate_dynamics.py eval results.json holding it")
    ap.add_argument("--ablate-model", default="shipped", help="the checkpoint's name in that result")
    ap.add_argument("--yardstick", type=Path, help="a bench/yardstick.py results.json holding it")
    ap.add_argument("--yardstick-model", default="shipped", help="the checkpoint's name in that result")
    ap.add_argument("--extends", metavar="WHAT", help="the model is a fine-tune of the replaced one: keep its "
                    "training chain and append this run, described as WHAT")
    args = ap.parse_args()
    old_metrics = args.checkpoint / "metrics.json"
    old_chain = json.loads(old_metrics.read_text()).get("training", {}) if old_metrics.is_file() else {}
    wm = WorldModel.load(args.checkpoint)
    config = json.loads((args.checkpoint / "config.json").read_text())
    prov = config.get("provenance", {})
    while "exported_from" in prov:  # exported from an exported checkpoint: the run is the first export's
        prov = prov["exported_from"]
    metrics = {"mujoco_rollout": mujoco_rollout(wm), "training": training_chain(old_chain, prov, args.extends)}
    if args.bench:
        r = json.loads(args.bench.read_text())
        m = r["models"][args.bench_model]
        metrics["open_loop_192"] = {"episodes": len(r["episodes"]), "steps": r["steps"], "data": r["data"],
                                    **{k: v for k, v in m["accuracy"].items()}, "speed": m.get("speed")}
    if args.ablate:
        metrics["fidelity"] = json.loads(args.ablate.read_text())[args.ablate_model]
    if args.yardstick:
        r = json.loads(args.yardstick.read_text())
        metrics["yardstick"] = {"results": str(args.yardstick), "model": args.yardstick_model,
                                **r["models"][args.yardstick_model]}
    write_json_atomic(args.checkpoint / "metrics.json", metrics, sort_keys=False)
    print(json.dumps(metrics["mujoco_rollout"]))


if __name__ == "__main__":
    raise SystemExit(reporting_errors("ship_checkpoint.py", main))
