"""Measure the T-pushing task's scorers, scripted policies and collection throughput.

    MUJOCO_GL=egl .venv/bin/python bench/bench_task.py [--quick]

Writes bench/results/task.json, task.md and task_expert.png. Numbers:
- pixel IoU vs geometric IoU and the pixel pose estimator on 200 random 64 px states
  (half drawn like episode starts, half near the goal so that IoU spans 0..1);
- the expert's mean max-IoU over seeds 100000..100049, 600 steps, block pose from state
  and from pixels;
- the play policy's contact fraction and `iwsim collect` throughput with 2 workers.
Run it alone: the two cores are shared by everything running.
"""

from __future__ import annotations

import argparse
import json
import multiprocessing as mp
import platform
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from iwsim.core.errors import reporting_errors
from iwsim.eval.records import command_line, with_command

RESULTS = Path(__file__).parent / "results"
EVAL_SEEDS = range(100000, 100050)  # Diffusion Policy's evaluation-seed convention


def scorer_errors(n_states: int) -> dict:
    from iwsim.envs.pusht import geometry as geo
    from iwsim.envs.pusht import pixels
    from iwsim.envs.pusht.sim import GOAL_POSE, BimanualPushTEnv

    env = BimanualPushTEnv(64)
    rng = np.random.default_rng(0)
    rows = []
    t_est = 0.0
    for k in range(n_states):
        state = env.sample_state(rng)
        near = k % 2 == 1
        if near:
            state[4:] = GOAL_POSE + rng.normal(0.0, [0.02, 0.02, 0.25]) * rng.uniform(0, 1)
        obs, info = env.reset(options={"reset_to_state": state})
        t = time.perf_counter()
        est = pixels.estimate_block_pose(obs["pixels"])
        t_est += time.perf_counter() - t
        rows.append((near, info["iou"], pixels.pixel_iou(obs["pixels"]),
                     np.linalg.norm(est.pose[:2] - info["block_pose"][:2]),
                     abs(geo.wrap_angle(est.pose[2] - info["block_pose"][2]))))
    env.close()
    near, geo_iou, pix_iou, pos_err, ang_err = (np.array(c) for c in zip(*rows))
    err = np.abs(pix_iou - geo_iou)

    def summary(sel: np.ndarray) -> dict:
        return {
            "states": int(sel.sum()),
            "geometric_iou_range": [float(geo_iou[sel].min()), float(geo_iou[sel].max())],
            "iou_abs_err_mean": float(err[sel].mean()),
            "iou_abs_err_max": float(err[sel].max()),
            "iou_bias": float((pix_iou - geo_iou)[sel].mean()),
            "pose_pos_err_mm_mean": float(1000 * pos_err[sel].mean()),
            "pose_pos_err_mm_max": float(1000 * pos_err[sel].max()),
            "pose_yaw_err_deg_mean": float(np.degrees(ang_err[sel].mean())),
            "pose_yaw_err_deg_max": float(np.degrees(ang_err[sel].max())),
        }

    return {"all": summary(np.ones_like(near, bool)), "episode_starts": summary(~near),
            "near_goal": summary(near), "pose_estimate_ms": 1000 * t_est / n_states}


def _expert_episode(job: tuple[int, str, int]) -> list[float]:
    from iwsim.envs.pusht.scripted import ExpertPolicy, run_scripted

    seed, source, steps = job
    return [tr.next_info["iou"] for tr in run_scripted(ExpertPolicy(pose_source=source), seed, steps)]


def expert_scores(seeds: range, steps: int, workers: int) -> dict:
    from tqdm import tqdm

    out = {}
    with mp.get_context("spawn").Pool(workers) as pool:
        for source in ("state", "pixels"):
            jobs = [(s, source, steps) for s in seeds]
            t = time.perf_counter()
            curves = np.array(list(tqdm(pool.imap(_expert_episode, jobs), total=len(jobs), desc=f"expert/{source}")))
            best = curves.max(axis=1)
            reached = [int(np.argmax(c >= 0.9)) + 1 if c.max() >= 0.9 else None for c in curves]
            out[source] = {
                "mean_max_iou": float(best.mean()),
                "min_max_iou": float(best.min()),
                "success_rate": float(np.mean(best >= 0.9)),
                "median_steps_to_success": float(np.median([r for r in reached if r is not None] or [np.nan])),
                "per_seed_max_iou": {int(s): round(float(b), 4) for s, b in zip(seeds, best)},
                "seconds": time.perf_counter() - t,
                "_curves": curves,
            }
    return out


def collect_throughput(episodes: int) -> dict:
    from iwsim.envs.collect import collect

    with tempfile.TemporaryDirectory() as tmp:
        stats = collect("pusht", "play", episodes, out=Path(tmp) / "play.zarr", steps=200, image_size=64,
                        workers=2, seed=0)
    return {"episodes": episodes, "steps": 200, "workers": 2, "image_size": 64,
            "frames_per_second": stats.frames_per_second, "play_contact_fraction": stats.contact_fraction}


def plot(expert: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (a, b) = plt.subplots(1, 2, figsize=(11, 4))
    for source, r in expert.items():
        c = r["_curves"]
        running = np.maximum.accumulate(c, axis=1)
        a.plot(np.arange(1, c.shape[1] + 1), running.mean(axis=0), label=f"{source}")
        b.hist(c.max(axis=1), bins=np.linspace(0, 1, 41), alpha=0.6, label=f"{source} (mean {r['mean_max_iou']:.3f})")
    a.axhline(0.9, color="k", ls=":", lw=1)
    a.set(xlabel="step", ylabel="mean running max IoU", title="Expert: max IoU so far (50 seeds)", ylim=(0, 1))
    b.set(xlabel="max IoU in 600 steps", ylabel="episodes", title="Expert: per-seed max IoU")
    a.legend(title="block pose from"), b.legend()
    fig.tight_layout()
    fig.savefig(path, dpi=120)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--quick", action="store_true", help="a few seeds and states, to check the script runs")
    ap.add_argument("--out", type=Path, default=RESULTS)
    args = ap.parse_args()
    seeds = range(100000, 100004) if args.quick else EVAL_SEEDS
    steps = 100 if args.quick else 600
    args.out.mkdir(parents=True, exist_ok=True)

    results = {"machine": f"{platform.processor() or platform.machine()}, {mp.cpu_count()} cores",
               "python": sys.version.split()[0], "quick": args.quick}
    results["collect"] = collect_throughput(4 if args.quick else 40)
    results["scorer"] = scorer_errors(20 if args.quick else 200)
    expert = expert_scores(seeds, steps, workers=2)
    plot(expert, args.out / "task_expert.png")
    results["expert"] = {k: {kk: vv for kk, vv in v.items() if not kk.startswith("_")} for k, v in expert.items()}
    results["expert_setup"] = {"seeds": [seeds.start, seeds.stop - 1], "steps": steps}
    command = command_line(__file__)
    (args.out / "task.json").write_text(json.dumps(with_command(command, results), indent=2) + "\n")

    s, e, c = results["scorer"], results["expert"], results["collect"]
    lines = [
        "# Task benchmark (`bench/bench_task.py`)",
        "",
        f"`{command}`",
        "",
        f"Machine: {results['machine']}. {'QUICK RUN, not the recorded numbers.' if args.quick else ''}",
        "",
        "## Pixel scorer vs geometry (64 px)",
        "",
        "| states | n | geometric IoU range | mean abs IoU err | max abs IoU err | pos err mean / max (mm) "
        "| yaw err mean / max (deg) |",
        "|---|---|---|---|---|---|---|",
    ]
    for name in ("all", "episode_starts", "near_goal"):
        r = s[name]
        lines.append(
            f"| {name} | {r['states']} | {r['geometric_iou_range'][0]:.2f}-{r['geometric_iou_range'][1]:.2f} | "
            f"{r['iou_abs_err_mean']:.4f} | {r['iou_abs_err_max']:.4f} | "
            f"{r['pose_pos_err_mm_mean']:.2f} / {r['pose_pos_err_mm_max']:.2f} | "
            f"{r['pose_yaw_err_deg_mean']:.2f} / {r['pose_yaw_err_deg_max']:.2f} |"
        )
    lines += [
        "",
        f"Pose estimate: {s['pose_estimate_ms']:.1f} ms per frame.",
        "",
        f"## Expert, seeds {seeds.start}..{seeds.stop - 1}, {steps} steps",
        "",
        "| block pose from | mean max IoU | min max IoU | success (max IoU >= 0.9) | median steps to success |",
        "|---|---|---|---|---|",
    ]
    for src in ("state", "pixels"):
        r = e[src]
        lines.append(f"| {src} | {r['mean_max_iou']:.3f} | {r['min_max_iou']:.3f} | {100 * r['success_rate']:.0f}% | "
                     f"{r['median_steps_to_success']:.0f} |")
    lines += [
        "",
        "![expert](task_expert.png)",
        "",
        "## Play data and collection",
        "",
        f"`iwsim collect --policy play --episodes {c['episodes']} --steps 200 --image-size 64 --workers 2`: "
        f"**{c['frames_per_second']:.0f} frames/s**; pusher-block contact in "
        f"**{100 * c['play_contact_fraction']:.1f}%** of steps.",
        "",
    ]
    (args.out / "task.md").write_text("\n".join(lines))
    print("\n".join(lines))


if __name__ == "__main__":
    raise SystemExit(reporting_errors("bench_task.py", main))
