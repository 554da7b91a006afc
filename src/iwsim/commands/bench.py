"""World models measured: ``iwsim rollout`` (one recorded episode, open loop, as a video) and
``iwsim bench`` (models side by side)."""

from __future__ import annotations

import argparse

from iwsim.commands.common import check_frames_memory
from iwsim.core.errors import InputError, check_positive


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("rollout", help="open-loop rollout of a recorded episode: truth | prediction video")
    p.add_argument("--checkpoint", required=True, help="world-model checkpoint directory")
    p.add_argument("--data", required=True, help="episode store")
    p.add_argument("--episode", type=int, default=0, help="episode index (default: %(default)s)")
    p.add_argument("--steps", type=int, default=192, help="predicted steps (default: %(default)s)")
    p.add_argument("--context", type=int, default=1, help="context frames (default: %(default)s)")
    p.add_argument("--seed", type=int, default=0, help="noise seed (default: %(default)s)")
    p.add_argument("--out", required=True, help="video path (.mp4); scores go to .json and _psnr.png beside it")
    p.add_argument("--device", default="auto", help="auto, cpu, cuda or cuda:N (default: %(default)s)")
    p.set_defaults(func=_rollout)

    p = sub.add_parser("bench", help="world models side by side: video metrics, IoU error, speed, stability")
    p.add_argument("--checkpoint", required=True, help="our world model (checkpoint or run directory)")
    p.add_argument("--name", default="ours", help="its name in the report (default: %(default)s)")
    p.add_argument("--baselines", default="",
                   help="comma-separated NAME=CHECKPOINT pairs, e.g. deterministic=runs/bench/deterministic")
    p.add_argument("--data", help="episode store (default: the one the checkpoint was trained on)")
    p.add_argument("--out", required=True, help="results directory (e.g. bench/results/NAME)")
    p.add_argument("--episodes", type=int, default=20, help="held-out episodes (default: %(default)s)")
    p.add_argument("--steps", type=int, default=192, help="open-loop steps (default: %(default)s)")
    p.add_argument("--stability-steps", type=int, default=9000,
                   help="long-rollout steps per model, 0 to skip (default: %(default)s)")
    p.add_argument("--stability-every", type=int, default=1,
                   help="decode and score every N-th step of the long rollout (default: %(default)s)")
    p.add_argument("--speed-batch", type=int, default=64, help="batch of the batched speed test (default: %(default)s)")
    p.add_argument("--speed-calls", type=int, default=100, help="timed steps per speed test (default: %(default)s)")
    p.add_argument("--seed", type=int, default=0, help="rollout noise seed (default: %(default)s)")
    p.add_argument("--weights", help="LPIPS/FID/FVD weights directory (default: $IWSIM_WEIGHTS, else the cache)")
    p.add_argument("--device", default="auto", help="auto, cpu, cuda or cuda:N (default: %(default)s)")
    p.add_argument("--no-progress", action="store_true", help="hide the progress bars")
    p.set_defaults(func=_bench)


def _rollout(args: argparse.Namespace) -> int:
    from iwsim.core.trainer import resolve_device
    from iwsim.data.store import EpisodeStore
    from iwsim.eval.rollout import open_loop, write_side_by_side
    from iwsim.world_model import WorldModel

    if not str(args.out).endswith(".mp4"):
        raise InputError(f"--out must be an .mp4 path, got {args.out!r}.")
    check_positive(args, "steps", "context")
    store = EpisodeStore.open(args.data, "r")
    if not 0 <= args.episode < store.n_episodes:  # (a negative index would silently count from the end)
        raise InputError(f"--episode must be in 0..{store.n_episodes - 1} ({args.data} holds {store.n_episodes} "
                         f"episodes), got {args.episode}.")
    wm = WorldModel.load(args.checkpoint, resolve_device(args.device))
    result = open_loop(wm, store, [args.episode], args.steps, args.context, args.seed, progress=True)
    path = write_side_by_side(result, args.out)
    s = result.summary()
    print(f"{path}: mean PSNR {s['psnr']:.2f} dB, SSIM {s['ssim']:.3f}, last-step PSNR {s['psnr_last']:.2f} dB, "
          + ("no scorer (the task has no pixel scorer)" if s["iou_abs_err"] is None else
             f"mean |IoU error| {s['iou_abs_err']:.3f}"))
    return 0


def _bench(args: argparse.Namespace) -> int:
    from pathlib import Path

    from iwsim.core.trainer import resolve_device
    from iwsim.eval.benchmark import run_benchmark
    from iwsim.eval.records import command_line

    models = {args.name: args.checkpoint}
    for item in filter(None, (x.strip() for x in args.baselines.split(","))):
        name, sep, path = item.partition("=")
        if not sep or not name or not path:
            raise InputError(f"--baselines entries must be NAME=CHECKPOINT, got {item!r}.")
        if name in models:
            raise InputError(f"model name {name!r} is given twice.")
        models[name] = path
    check_positive(args, "episodes", "steps", "stability_every", "speed_batch", "speed_calls")
    if args.stability_steps < 0:
        raise InputError(f"--stability-steps must be >= 0, got {args.stability_steps}.")
    # the recorded episodes and every model's rollout of them
    check_frames_memory(f"--episodes {args.episodes} x --steps {args.steps}", args.episodes * (args.steps + 1),
                         len(models) + 1)
    run_benchmark(models, args.out, args.data, episodes=args.episodes, steps=args.steps,
                  stability_steps=args.stability_steps, stability_every=args.stability_every,
                  speed_batch=args.speed_batch, speed_calls=args.speed_calls, seed=args.seed,
                  weights=Path(args.weights) if args.weights else None, device=resolve_device(args.device),
                  progress=not args.no_progress, command=command_line("iwsim", args.argv))
    print(Path(args.out) / "results.md")
    return 0
