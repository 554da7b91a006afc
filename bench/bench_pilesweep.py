"""Measure the pile-sweeping task (issue 45): its physics, pixel scorer, scripted policies
and collection throughput.

    MUJOCO_GL=egl OMP_NUM_THREADS=1 .venv/bin/python bench/bench_pilesweep.py [--quick]

Writes OUT/pilesweep.json, pilesweep.md and pilesweep_expert.png (a strip of an expert
episode). Numbers, all in one process:
- physics under stress: pushers driven at full speed through piles, into walls and corners
  (8 seeds x 300 steps): the fastest a piece moved in a step, how far pieces left the table
  plane, the deepest overlap of a piece with a wall, a pusher or another piece;
- the expert (from pixels) and play, and the expert's degraded variants, over held-out
  seeds (100100.., never used to tune them), 200 steps: the score (share of the pieces in
  the tray) at the end and its maximum;
- the pixel scorer against MuJoCo's exact count on every 5th frame of those expert and
  play episodes: the tray count's and the seen count's mean absolute error, beside two
  simpler estimators (connected components alone; piece-coloured area alone);
- ``iwsim collect --task pilesweep --policy play`` throughput with one worker.
Run it alone: the two cores are shared by everything running.
"""

from __future__ import annotations

import argparse
import json
import platform
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from iwsim.core.errors import reporting_errors
from iwsim.eval.records import command_line, with_command

RESULTS = Path(__file__).parent / "results"
HELD_OUT = 100100  # first held-out seed (the policies were tuned on 100000..100011)
DEGRADED = {"noise 5 mm": {"noise": 0.005}, "noise 10 mm": {"noise": 0.01}, "noise 20 mm": {"noise": 0.02},
            "latency 2": {"latency": 2}, "latency 4": {"latency": 4}, "tremor 8 mm + latency 2":
            {"jitter": 0.008, "latency": 2}}


def stress(seeds: int, segments: int) -> dict:
    """Pushers driven at their speed limit through the pile, into walls and corners."""
    from iwsim.envs.pilesweep.sim import PIECE_RADIUS, PileSweepEnv
    from iwsim.envs.tabletop.scene import PUSHER_RADIUS, WALL_INNER, WORKSPACE

    fastest = lift = wall = overlap = pusher = 0.0
    steps, t0 = 0, time.perf_counter()
    env = PileSweepEnv(64)
    z = np.array([env.model.joint(f"piece_{i}_z").qposadr[0] for i in range(30)])
    for seed in range(seeds):
        env.reset(seed=400000 + seed)
        rng = np.random.default_rng(seed)
        for _ in range(segments):
            pile = env.pieces.copy()
            to_walls = rng.integers(3) > 0
            targets = []
            for _ in range(2):
                w = rng.uniform(-1, 1, 2)
                w[rng.integers(2)] = rng.choice([-1, 1])
                targets.append(w * WORKSPACE if to_walls else pile[rng.integers(len(pile))] + rng.normal(0, 0.02, 2))
            for _ in range(25):
                before = env.pieces.copy()
                obs, *_ = env.step(np.concatenate(targets))
                p, steps = env.pieces, steps + 1
                gaps = np.linalg.norm(p[:, None] - p[None], axis=-1) + np.eye(len(p))
                reach = np.linalg.norm(p[:, None] - obs["agent_pos"].reshape(1, 2, 2), axis=-1)
                fastest = max(fastest, float(np.linalg.norm(p - before, axis=1).max()))
                lift = max(lift, float(np.abs(env.data.qpos[z[: env.n_pieces]]).max()))
                wall = max(wall, float(np.abs(p).max() - (WALL_INNER - PIECE_RADIUS)))
                overlap = max(overlap, float(2 * PIECE_RADIUS - gaps.min()))
                pusher = max(pusher, float(PIECE_RADIUS + PUSHER_RADIUS - reach.min()))
    env.close()
    mm = 1000
    return {"seeds": seeds, "steps": steps, "steps_per_second": steps / (time.perf_counter() - t0),
            "fastest_piece_mm_per_step": mm * fastest, "max_off_table_mm": mm * lift,
            "max_wall_overlap_mm": mm * wall, "max_piece_overlap_mm": mm * overlap,
            "max_pusher_overlap_mm": mm * pusher}


def episodes(policy: object, seeds: range, steps: int, keep_every: int = 0) -> dict:
    """Scores of ``policy`` (a name or a factory of a seed) over ``seeds``; with
    ``keep_every``, every so many frames with their exact counts."""
    from iwsim.envs.pilesweep.scripted import run_scripted

    final, best, frames, counts = [], [], [], []
    t0, n = time.perf_counter(), 0
    for seed in seeds:
        top = 0.0
        made = policy if isinstance(policy, str) else policy(seed)  # type: ignore[operator]
        for t, tr in enumerate(run_scripted(made, seed, steps)):
            top, n = max(top, tr.next_info["score"]), n + 1
            if keep_every and t % keep_every == 0:
                frames.append(tr.obs["pixels"])
                counts.append((tr.info["n_in_tray"], tr.info["n_pieces"]))
        final.append(tr.next_info["score"])
        best.append(top)
    out = {"seeds": [seeds.start, seeds.stop - 1], "steps": steps, "mean_final_score": float(np.mean(final)),
           "min_final_score": float(np.min(final)), "mean_max_score": float(np.mean(best)),
           "success_rate": float(np.mean(np.asarray(final) >= 0.9)),
           "per_seed_final": {int(s): round(float(f), 4) for s, f in zip(seeds, final)},
           "steps_per_second": n / (time.perf_counter() - t0)}
    if keep_every:
        out["_frames"], out["_counts"] = np.array(frames), np.array(counts)
    return out


def scorer_errors(frames: np.ndarray, counts: np.ndarray) -> dict:
    """The pixel scorer's errors against MuJoCo's counts, and two simpler estimators'."""
    from scipy import ndimage

    from iwsim.envs.pilesweep.pixels import MIN_FRACTION, count_pieces, piece_area, piece_fraction
    from iwsim.envs.pilesweep.sim import in_tray
    from iwsim.envs.tabletop.palette import pixel_centers

    t0 = time.perf_counter()
    inside, seen = count_pieces(frames)
    ms = 1000 * (time.perf_counter() - t0) / len(frames)
    components, area = [], []
    for f in frames:
        frac = piece_fraction(f)
        centres = pixel_centers(frac.shape[-1])
        tray = in_tray(centres)
        labels, n = ndimage.label(frac > MIN_FRACTION, structure=np.ones((3, 3), bool))
        cents = np.array(ndimage.center_of_mass(frac, labels, range(1, n + 1))).reshape(-1, 2)
        xy = np.stack([np.interp(cents[:, 1], np.arange(len(centres)), centres[0, :, 0]),
                       np.interp(cents[:, 0], np.arange(len(centres)), centres[:, 0, 1])], axis=-1)
        components.append((int(in_tray(xy).sum()), n))
        one = piece_area(frac.shape[-1])
        area.append((round(float(frac[tray].sum()) / one), round(float(frac.sum()) / one)))

    def errors(est: np.ndarray) -> dict:
        e = est - counts
        return {"tray_mae": float(np.abs(e[:, 0]).mean()), "tray_max_abs": int(np.abs(e[:, 0]).max()),
                "tray_bias": float(e[:, 0].mean()), "seen_mae": float(np.abs(e[:, 1]).mean()),
                "seen_max_abs": int(np.abs(e[:, 1]).max()), "seen_bias": float(e[:, 1].mean()),
                "tray_exact": float(np.mean(e[:, 0] == 0))}

    return {"frames": len(frames), "tray_count_range": [int(counts[:, 0].min()), int(counts[:, 0].max())],
            "ms_per_frame": ms, "scorer": errors(np.stack([inside, seen], axis=1)),
            "components_only": errors(np.array(components)), "area_only": errors(np.array(area))}


def collect_throughput(episodes: int) -> dict:
    from iwsim.envs.collect import collect

    with tempfile.TemporaryDirectory() as tmp:
        stats = collect("pilesweep", "play", episodes, out=Path(tmp) / "play.zarr", steps=200, image_size=64,
                        workers=1, seed=0, progress=False)
    return {"episodes": episodes, "steps": 200, "workers": 1, "image_size": 64,
            "frames_per_second": stats.frames_per_second, "contact_fraction": stats.contact_fraction,
            "mean_max_score": stats.mean_max_score}


def strip(seed: int, steps: int, every: int, path: Path) -> None:
    """An expert episode as one row of frames (every ``every`` steps, 3x enlarged)."""
    import imageio.v3 as iio

    from iwsim.envs.pilesweep.scripted import run_scripted

    frames = []
    for t, tr in enumerate(run_scripted("expert", seed, steps)):
        if t % every == 0:
            frames.append(tr.obs["pixels"])
    frames.append(tr.next_obs["pixels"])
    gap = np.full((64, 2, 3), 255, np.uint8)
    row = np.concatenate([x for f in frames for x in (f, gap)][:-1], axis=1)
    iio.imwrite(path, row.repeat(3, axis=0).repeat(3, axis=1))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--quick", action="store_true", help="a few seeds, to check the script runs")
    ap.add_argument("--seeds", type=int, default=30, help="held-out seeds per policy (default: %(default)s)")
    ap.add_argument("--out", type=Path, default=RESULTS)
    args = ap.parse_args()
    n = 3 if args.quick else args.seeds
    seeds = range(HELD_OUT, HELD_OUT + n)
    args.out.mkdir(parents=True, exist_ok=True)
    from iwsim.envs.pilesweep.scripted import degraded_expert

    results: dict = {"machine": f"{platform.processor() or platform.machine()}", "python": sys.version.split()[0],
                     "quick": args.quick}
    results["physics"] = stress(2 if args.quick else 8, 4 if args.quick else 12)
    expert = episodes("expert", seeds, 200, keep_every=5)
    play = episodes("play", seeds, 200, keep_every=5)
    results["scorer"] = scorer_errors(np.concatenate([expert.pop("_frames"), play.pop("_frames")]),
                                      np.concatenate([expert.pop("_counts"), play.pop("_counts")]))
    results["expert"], results["play"] = expert, play
    few = range(HELD_OUT, HELD_OUT + (2 if args.quick else 10))
    results["degraded"] = {name: episodes(lambda s, kw=kw: degraded_expert(s, **kw), few, 200)
                           for name, kw in DEGRADED.items()}
    results["collect"] = collect_throughput(2 if args.quick else 10)
    strip(HELD_OUT, 200, 20, args.out / "pilesweep_expert.png")
    command = command_line(__file__)
    quick = "QUICK RUN, not the recorded numbers." if args.quick else ""
    head = [f"Machine: {results['machine']}, one thread. {quick}"]
    text = "\n".join(["# Pile-sweeping benchmark (`bench/bench_pilesweep.py`)", "", f"`{command}`", "", *head, "",
                      *report(results, seeds, few)])
    for name, content in (("pilesweep.json", json.dumps(with_command(command, results), indent=2) + "\n"),
                          ("pilesweep.md", text)):
        (args.out / name).write_text(content)
    print(text)


def report(results: dict, seeds: range, few: range) -> list[str]:
    """The Markdown report's sections."""
    ph, sc, c = results["physics"], results["scorer"], results["collect"]
    lines = [
        "## Physics under stress",
        "",
        f"{ph['steps']} steps ({ph['seeds']} seeds) of pushers at full speed through piles, into walls and corners: "
        f"the fastest piece moved {ph['fastest_piece_mm_per_step']:.0f} mm in a step; pieces left the table plane "
        f"by at most {ph['max_off_table_mm']:.2f} mm and overlapped a wall by {ph['max_wall_overlap_mm']:.2f} mm, "
        f"another piece by {ph['max_piece_overlap_mm']:.2f} mm, a pusher by {ph['max_pusher_overlap_mm']:.2f} mm "
        f"({ph['steps_per_second']:.0f} steps/s with rendering).",
        "",
        f"## Policies, held-out seeds {seeds.start}..{seeds.stop - 1}, 200 steps",
        "",
        "| policy | mean score at 200 | min | success (>= 0.9) | mean max score | steps/s |",
        "|---|---|---|---|---|---|",
    ]
    for name, r in [("expert (pixels)", results["expert"]), ("play", results["play"]),
                    *((f"expert, {k} ({few.stop - few.start} seeds)", v) for k, v in results["degraded"].items())]:
        lines.append(f"| {name} | {r['mean_final_score']:.3f} | {r['min_final_score']:.2f} | "
                     f"{100 * r['success_rate']:.0f}% | {r['mean_max_score']:.3f} | {r['steps_per_second']:.0f} |")
    lines += [
        "",
        f"## Pixel scorer against MuJoCo's count ({sc['frames']} held-out frames of those expert and play "
        f"episodes, every 5th; tray counts {sc['tray_count_range'][0]}..{sc['tray_count_range'][1]})",
        "",
        "| estimator | tray MAE | tray max | tray bias | tray exact | seen MAE | seen max | seen bias |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for name in ("scorer", "components_only", "area_only"):
        r = sc[name]
        lines.append(f"| {name} | {r['tray_mae']:.3f} | {r['tray_max_abs']} | {r['tray_bias']:+.3f} | "
                     f"{100 * r['tray_exact']:.1f}% | {r['seen_mae']:.3f} | {r['seen_max_abs']} | "
                     f"{r['seen_bias']:+.3f} |")
    lines += [
        "",
        f"The scorer takes {sc['ms_per_frame']:.1f} ms per 64 px frame.",
        "",
        "## Collection",
        "",
        f"`iwsim collect --task pilesweep --policy play --episodes {c['episodes']} --steps 200 --workers 1`: "
        f"**{c['frames_per_second']:.0f} frames/s**; pusher-piece contact in {100 * c['contact_fraction']:.1f}% "
        f"of steps; mean max score {c['mean_max_score']:.3f}.",
        "",
        "![an expert episode](pilesweep_expert.png)",
        "",
    ]
    return lines




if __name__ == "__main__":
    raise SystemExit(reporting_errors("bench_pilesweep.py", main))
