"""Where does a world model say the pushers are? (issue 64, item 2)

Each episode of the given stores (collected in MuJoCo, held out from training) starts the
world-model environment (``iwsim/WorldModel-v0``'s vector env) from its first frame and the
pushers' true position there, then sends the recorded commands one per step; the
environment's ``agent_pos`` after each step is compared with MuJoCo's (the store's
``data/state``). The environment reads the pushers off the frame (``PushTTask.observe``'s pixel
heuristic); a model trained with the robot's state (``--variant state``) fills in, from its
own prediction, a pusher the frame does not show (before 2026-12-05 night the environment
reported that prediction everywhere: the rows measured then).

Reported per model and store: the per-pusher error in mm (median, p90) over all steps and
over *pressing* steps, those where the executed setpoint lies more than ``--press-mm`` ahead
of the pusher in MuJoCo (contact holds it back, as learned policies press), and its share.

    iwsim collect --task pusht --policy play-press --episodes 16 --steps 300 --seed 740000 \\
        --workers 2 --out data/press_eval.zarr
    iwsim collect --task pusht --policy expert --episodes 16 --steps 300 --seed 741000 \\
        --workers 2 --out data/expert_eval.zarr
    MUJOCO_GL=egl python bench/pusher_state.py --models shipped=checkpoints/pusht-64 \\
        --stores data/press_eval.zarr data/expert_eval.zarr --out bench/results/pusher_state
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
import torch
from tqdm import tqdm

from iwsim.core.checkpoint import named_checkpoints, write_json_atomic, write_text_atomic
from iwsim.core.errors import IwsimError, one_line
from iwsim.data.store import EpisodeStore, StoreError
from iwsim.world_model import WorldModel
from iwsim.world_model.env import WorldModelVectorEnv, predicts_agent_pos


def episodes_of(path: str, steps: int) -> dict[str, np.ndarray]:
    """The first ``steps`` + 1 frames' state, command and executed setpoint of every episode
    of the store that long, and their first frames."""
    store = EpisodeStore.open(path, "r")
    for key in ("img", "state", "action", "target"):
        if key not in store.keys:
            raise StoreError(f"{path} has no data/{key}; collect it with iwsim collect (MuJoCo records all four).")
    ends = store.episode_ends.astype(np.int64)
    starts = np.concatenate([[0], ends[:-1]])
    keep = [(a, b) for a, b in zip(starts, ends) if b - a >= steps + 1]
    if not keep:
        raise StoreError(f"{path} holds no episode of {steps + 1} frames; lower --steps.")
    index = np.stack([np.arange(a, a + steps + 1) for a, _ in keep])
    out = {k: np.asarray(store.array(k).oindex[index.ravel()]).reshape(*index.shape, -1)
           for k in ("state", "action", "target")}
    out["first"] = np.asarray(store.array("img").oindex[index[:, 0]])
    return out


def pusher_errors(wm: WorldModel, ep: dict[str, np.ndarray], steps: int) -> np.ndarray:
    """Per-pusher distance (E, steps, 2) in metres between the environment's agent_pos after
    each recorded command and MuJoCo's."""
    env = WorldModelVectorEnv(len(ep["first"]), model=wm, max_episode_steps=steps)
    env.reset(seed=0, options={"frames": ep["first"], "agent_pos": ep["state"][:, 0]})
    errs = []
    for t in range(steps):
        obs, *_ = env.step(ep["action"][:, t])
        gap = obs["agent_pos"].reshape(-1, 2, 2) - ep["state"][:, t + 1].reshape(-1, 2, 2)
        errs.append(np.linalg.norm(gap, axis=-1))
    env.close()
    return np.stack(errs, 1)


def summary(err_mm: np.ndarray, pressing: np.ndarray) -> dict[str, float | None]:
    def q(x: np.ndarray, p: float) -> float | None:
        return float(np.percentile(x, p)) if x.size else None

    return {"median_mm": q(err_mm, 50), "p90_mm": q(err_mm, 90), "pressing_share": float(pressing.mean()),
            "pressing_median_mm": q(err_mm[pressing], 50), "pressing_p90_mm": q(err_mm[pressing], 90)}


def figure(path: Path, curves: dict[str, np.ndarray]) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7, 4))
    for name, c in curves.items():
        ax.plot(np.arange(1, len(c) + 1), c, label=name)
    ax.set(xlabel="step", ylabel="median pusher error (mm)", yscale="log",
           title="The pushers' position in the world model against MuJoCo's")
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], formatter_class=argparse.RawTextHelpFormatter)
    p.add_argument("--models", nargs="+", required=True, help="NAME=CHECKPOINT (world models)")
    p.add_argument("--stores", nargs="+", required=True, help="held-out MuJoCo stores (iwsim collect)")
    p.add_argument("--steps", type=int, default=299, help="commands sent per episode (a store's episode of T steps "
                                                           "holds T frames: T - 1 of them follow a command)")
    p.add_argument("--press-mm", type=float, default=20.0, help="a setpoint this far ahead of its pusher is pressing")
    p.add_argument("--out", type=Path, default=Path("bench/results/pusher_state"))
    args = p.parse_args(argv)
    if args.steps < 1 or not args.press_mm > 0:
        p.error(f"--steps must be >= 1 and --press-mm > 0, got {args.steps} and {args.press_mm}.")
    try:
        models = named_checkpoints(args.models)
        data = {s: episodes_of(s, args.steps) for s in args.stores}
    except IwsimError as e:
        p.error(one_line(e))
    torch.set_num_threads(1)
    report: dict = {"command": "python bench/pusher_state.py " + " ".join(argv or sys.argv[1:]),
                    "steps": args.steps, "press_mm": args.press_mm, "models": {}}
    curves = {}
    for name, ckpt in tqdm(models.items(), desc="models"):
        wm = WorldModel.load(ckpt)
        source = "read off the frame, the model's prediction where unseen" if wm.state_dim and \
            predicts_agent_pos(wm, wm.task) else "read off the frame (pixel heuristic)"
        row: dict = {"checkpoint": ckpt, "agent_pos": source, "stores": {}}
        for store, ep in data.items():
            err = pusher_errors(wm, ep, args.steps) * 1000
            gap = np.linalg.norm((ep["target"][:, :-1] - ep["state"][:, 1:]).reshape(*err.shape, 2), axis=-1) * 1000
            row["stores"][store] = {"episodes": len(err), **summary(err, gap > args.press_mm)}
            curves[f"{name}: {Path(store).stem}"] = np.median(err, axis=(0, 2))
        report["models"][name] = row
    args.out.mkdir(parents=True, exist_ok=True)
    write_json_atomic(args.out / "results.json", report)
    figure(args.out / "error_per_step.png", curves)
    lines = ["# The pushers' position in the world model (issue 64, item 2)", "", f"Command: `{report['command']}`", "",
             f"{args.steps} steps of each held-out episode's recorded commands; per-pusher error against MuJoCo's "
             f"agent_pos, in mm; pressing: the executed setpoint more than {args.press_mm:g} mm ahead of the pusher.",
             "", "| model | agent_pos | store | episodes | median | p90 | pressing share | pressing median | "
             "pressing p90 |", "|---|---|---|---|---|---|---|---|---|"]

    def mm(v: float | None) -> str:
        return "-" if v is None else f"{v:.1f}"

    for name, row in report["models"].items():
        for store, r in row["stores"].items():
            lines.append(f"| {name} | {row['agent_pos']} | `{store}` | {r['episodes']} | {mm(r['median_mm'])} | "
                         f"{mm(r['p90_mm'])} | {r['pressing_share']:.0%} | {mm(r['pressing_median_mm'])} | "
                         f"{mm(r['pressing_p90_mm'])} |")
    write_text_atomic(args.out / "results.md", "\n".join(lines) + "\n")
    print("\n".join(lines[6:]))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
