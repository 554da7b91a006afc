"""Do a world model's views agree? Cross-view consistency of T-push (issue 68, item 5).

Each held-out episode of a two-view store (MuJoCo, ``iwsim collect --cameras top,side``)
is replayed open loop from its first frame with its recorded setpoints, and the block's
pose is read from every predicted frame twice: from the top view (the pixel scorer's fit,
``estimate_block_pose``) and from the side view (the same fit on the block's footprint
seen through the side camera's known geometry, ``estimate_block_pose_side``; ~1 mm on
MuJoCo's own frames). Reported per model: how far the two readings lie apart (the views'
disagreement), how far each lies from MuJoCo's true pose, each view's PSNR against MuJoCo's
frame, and the share of frames where a view shows no block.

A model is one world model of both views (``NAME=CHECKPOINT``) or, the paper's way, two
single-view models driven by the same actions (``NAME=TOP_CHECKPOINT+SIDE_CHECKPOINT``: a
model of the top view and one of the side view, each started from its view of the first
frame).

    iwsim collect --task pusht --policy play-broad --episodes 16 --steps 200 --seed 760000 \\
        --cameras top,side --workers 2 --out data/two_views_eval.zarr
    MUJOCO_GL=egl python bench/cross_view.py --models joint=runs/wm_two_views \\
        pair=runs/wm_top+runs/wm_side --store data/two_views_eval.zarr --out bench/results/cross_view
"""
from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
import torch
from tqdm import tqdm

from iwsim.core.checkpoint import resolve_checkpoint, write_json_atomic, write_text_atomic
from iwsim.core.errors import InputError, IwsimError, one_line
from iwsim.data.frames import read_frames
from iwsim.data.store import EpisodeStore, StoreError
from iwsim.data.views import stack_views, store_cameras, unstack_views
from iwsim.envs.pusht import geometry as geo
from iwsim.envs.pusht.pixels import estimate_block_pose, estimate_block_pose_side
from iwsim.eval.records import command_line
from iwsim.world_model import WorldModel

VIEWS = ("top", "side")
READERS = {"top": estimate_block_pose, "side": estimate_block_pose_side}


def episodes_of(path: str, steps: int, limit: int | None) -> dict[str, np.ndarray]:
    """The first ``steps`` + 1 frames (both views, stacked), setpoints and block poses of
    every episode of the store that long (at most ``limit`` episodes)."""
    store = EpisodeStore.open(path, "r")
    if store_cameras(store.attrs, store.keys) != VIEWS:
        raise StoreError(f"{path} holds the views {list(store_cameras(store.attrs))}, not {list(VIEWS)}; collect "
                         "it with iwsim collect --task pusht --cameras top,side.")
    for key in ("target", "block_pose"):
        if key not in store.keys:
            raise StoreError(f"{path} has no data/{key}; collect it in MuJoCo with iwsim collect.")
    ends = store.episode_ends.astype(np.int64)
    starts = np.concatenate([[0], ends[:-1]])
    keep = [a for a, b in zip(starts, ends, strict=True) if b - a >= steps + 1][:limit]
    if not keep:
        raise StoreError(f"{path} holds no episode of {steps + 1} frames; lower --steps.")
    index = np.stack([np.arange(a, a + steps + 1) for a in keep])
    return {"frames": read_frames(store, index.ravel()).reshape(*index.shape, *read_frames(store, [0]).shape[1:]),
            **{k: np.asarray(store.array(k).oindex[index.ravel()]).reshape(*index.shape, -1)
               for k in ("target", "block_pose")}}


def load(spec: str) -> tuple[str, list[WorldModel]]:
    """A model spec: one checkpoint of both views, or TOP+SIDE single-view checkpoints."""
    parts = spec.split("+")
    models = [WorldModel.load(resolve_checkpoint(p)) for p in parts]
    if len(models) == 1 and models[0].cameras != VIEWS:
        raise InputError(f"{spec} sees the views {list(models[0].cameras)}; give a model of {list(VIEWS)}, or "
                         "TOP+SIDE single-view models.")
    if len(models) == 2 and any(len(m.cameras) != 1 for m in models):
        raise InputError(f"{spec}: TOP+SIDE names two single-view models.")
    if len(models) > 2:
        raise InputError(f"{spec}: expected CHECKPOINT or TOP+SIDE.")
    return ("joint" if len(models) == 1 else "pair"), models


def predict(models: list[WorldModel], ep: dict[str, np.ndarray], steps: int) -> np.ndarray:
    """Frames (E, steps, H, W, 6) of both views predicted from each episode's first frame."""
    first, actions = ep["frames"][:, 0], ep["target"][:, 1:steps + 1]
    if len(models) == 1:
        return models[0].rollout(first, actions, seed=0)
    views = unstack_views(first, 2)
    return stack_views([m.rollout(v, actions, seed=0) for m, v in zip(models, views, strict=True)])


def readings(frames: np.ndarray) -> dict[str, np.ndarray]:
    """Per view the block pose (..., 3) read from frames (..., H, W, 6), NaN where no block is seen."""
    flat = frames.reshape(-1, *frames.shape[-3:])
    out = {}
    for view, frame in zip(VIEWS, unstack_views(flat, 2), strict=True):
        poses = []
        for f in frame:
            est = READERS[view](f)
            poses.append(est.pose if est.found else np.full(3, np.nan))
        out[view] = np.stack(poses).reshape(*frames.shape[:-3], 3)
    return out


def pose_gap(a: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Position (mm) and yaw (degrees) between poses (..., 3); the T has no symmetry."""
    return np.hypot(*(a[..., :2] - b[..., :2]).T).T * 1000, np.degrees(np.abs(geo.wrap_angle(a[..., 2] - b[..., 2])))


def psnr(a: np.ndarray, b: np.ndarray) -> float:
    mse = np.mean((a.astype(np.float64) - b.astype(np.float64)) ** 2)
    return float(10 * np.log10(255.0 ** 2 / max(mse, 1e-10)))


def measure(frames: np.ndarray | None, ep: dict[str, np.ndarray], steps: int) -> dict:
    """The views' disagreement and each view's error of predicted frames (E, steps, H, W, 6);
    None: of MuJoCo's own frames (the readers' floor, no PSNR)."""
    truth_frames, truth = ep["frames"][:, 1:steps + 1], ep["block_pose"][:, 1:steps + 1]
    own = frames is None
    frames = truth_frames if frames is None else frames
    read = readings(frames)
    mm, deg = pose_gap(read["top"], read["side"])
    row: dict = {"disagreement_mm": _stats(mm), "disagreement_deg": _stats(deg)}
    for view, pred, real in zip(VIEWS, unstack_views(frames, 2), unstack_views(truth_frames, 2), strict=True):
        e_mm, e_deg = pose_gap(read[view], truth)
        row[view] = {"error_mm": _stats(e_mm), "error_deg": _stats(e_deg), "psnr_db": None if own else psnr(pred, real),
                     "no_block": float(np.isnan(read[view][..., 0]).mean())}
    row["disagreement_curve_mm"] = [None if np.isnan(x).all() else float(np.nanmedian(x)) for x in mm.T]
    return row


def _stats(x: np.ndarray) -> dict[str, float | None]:
    x = x[~np.isnan(x)]
    return {"median": float(np.median(x)) if x.size else None, "p90": float(np.percentile(x, 90)) if x.size else None}


def figure(path: Path, curves: dict[str, list]) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7, 4))
    for name, c in curves.items():
        ax.plot(np.arange(1, len(c) + 1), [np.nan if v is None else v for v in c], label=name)
    ax.set(xlabel="step", ylabel="median top-vs-side pose gap (mm)", title="Do the views agree on the block?")
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], formatter_class=argparse.RawTextHelpFormatter)
    p.add_argument("--models", nargs="+", required=True,
                   help="NAME=CHECKPOINT (a model of the top and side views) or NAME=TOP+SIDE (two single-view models)")
    p.add_argument("--store", required=True, help="held-out MuJoCo episodes of both views (iwsim collect --cameras "
                                                  "top,side)")
    p.add_argument("--steps", type=int, default=192, help="open-loop steps per episode (default: %(default)s)")
    p.add_argument("--episodes", type=int, default=16, help="episodes of the store at most (default: %(default)s)")
    p.add_argument("--out", type=Path, default=Path("bench/results/cross_view"))
    args = p.parse_args(argv)
    if args.steps < 1 or args.episodes < 1:
        p.error(f"--steps and --episodes must be >= 1, got {args.steps} and {args.episodes}.")
    try:
        specs = {}
        for item in args.models:
            name, sep, spec = item.partition("=")
            if not sep or not name or name in specs:
                raise InputError(f"--models takes distinct NAME=CHECKPOINT or NAME=TOP+SIDE, got {item!r}.")
            specs[name] = spec
        ep = episodes_of(args.store, args.steps, args.episodes)
        models = {name: load(spec) for name, spec in specs.items()}
    except (IwsimError, OSError) as e:
        p.error(one_line(e))
    torch.set_num_threads(1)
    report: dict = {"command": command_line(__file__, argv), "steps": args.steps,
                    "episodes": len(ep["frames"]), "store": args.store, "models": {}}
    mujoco = measure(None, ep, args.steps)  # the readers on MuJoCo's own frames
    report["mujoco"] = mujoco
    for name, (kind, nets) in tqdm(models.items(), desc="models"):
        report["models"][name] = {"kind": kind, "checkpoints": specs[name].split("+"),
                                  **measure(predict(nets, ep, args.steps), ep, args.steps)}
    args.out.mkdir(parents=True, exist_ok=True)
    write_json_atomic(args.out / "results.json", report)
    figure(args.out / "disagreement_per_step.png",
           {n: r["disagreement_curve_mm"] for n, r in {"MuJoCo": mujoco, **report["models"]}.items()})

    def f(v: float | None, d: int = 1) -> str:
        return "-" if v is None else f"{v:.{d}f}"

    lines = ["# Cross-view consistency (issue 68, item 5)", "", f"Command: `{report['command']}`", "",
             f"{report['episodes']} held-out episodes x {args.steps} open-loop steps; the block's pose read from the "
             "top view and from the side view of every predicted frame: their gap (the views' disagreement), each "
             "against MuJoCo's pose, each view's PSNR against MuJoCo's frame. Median (p90).", "",
             "| model | kind | views' gap mm | gap deg | top error mm | side error mm | top PSNR | side PSNR | "
             "no block top / side |", "|---|---|---|---|---|---|---|---|---|"]
    for name, r in {"MuJoCo (the readers' own error)": {**mujoco, "kind": "-"}, **report["models"]}.items():
        lines.append(f"| {name} | {r['kind']} | {f(r['disagreement_mm']['median'])} ({f(r['disagreement_mm']['p90'])})"
                     f" | {f(r['disagreement_deg']['median'])} | {f(r['top']['error_mm']['median'])} | "
                     f"{f(r['side']['error_mm']['median'])} | {f(r['top']['psnr_db'], 2)} | "
                     f"{f(r['side']['psnr_db'], 2)} | {r['top']['no_block']:.0%} / {r['side']['no_block']:.0%} |")
    write_text_atomic(args.out / "results.md", "\n".join(lines) + "\n")
    print("\n".join(lines[6:]))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
