"""Record episodes into a store: ``iwsim collect`` (MuJoCo under a scripted or learned policy)
and ``iwsim demos`` (a pixel expert's successful takes, in MuJoCo or a world model)."""

from __future__ import annotations

import argparse
from typing import Any

from iwsim.commands.common import check_frames_memory, numbers, wait_for_lock_flag
from iwsim.core.errors import InputError
from iwsim.core.resources import available_cores
from iwsim.envs import IMAGE_SIZES, POLICIES, TASKS
from iwsim.envs.registry import DEFAULT_TASK as TASK
from iwsim.envs.registry import REGISTRY as TASK_REGISTRY


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("collect", help="record episodes of a MuJoCo task (scripted or learned policy) into a store")
    p.add_argument("--task", help=f"task: {', '.join(TASKS)} (default: a learned policy's own, as its checkpoint "
                   f"records it, else {TASK.kind})")
    scripted = "; ".join(f"{', '.join(names)} ({task})" for task, names in POLICIES.items())
    p.add_argument("--policy", default="play", help=f"scripted policy: {scripted}; or a learned policy's "
                   "run or checkpoint directory (its episodes run batched in this process) (default: %(default)s)")
    p.add_argument("--episodes", type=int, required=True, help="total episodes the store should hold")
    p.add_argument("--steps", type=int, default=200, help="steps per episode (default: %(default)s)")
    p.add_argument(
        "--image-size",
        type=int,
        default=TASK.image_size,
        help=f"square image size: {', '.join(map(str, IMAGE_SIZES))} (default: %(default)s)",
    )
    p.add_argument("--cameras", default="top", metavar="NAMES",
                   help="the simulator's views to record, comma-separated, the first in data/img and each other in "
                        "data/img_<name> (tabletop tasks: top, side) (default: %(default)s)")
    p.add_argument(
        "--workers",
        type=int,
        default=available_cores(),
        help="worker processes (default: the CPU cores this process may use, %(default)s)",
    )
    p.add_argument("--seed", type=int, default=0, help="episode i uses seed SEED + i (default: %(default)s)")
    p.add_argument("--out", help="store path (default: data/<task>_<policy>.zarr)")
    wait_for_lock_flag(p)
    p.add_argument("--no-progress", action="store_true", help="hide the progress bar")
    p.set_defaults(func=_collect)
    p = sub.add_parser("demos", help="record a pixel expert's successful takes into a store, in MuJoCo or a world "
                                     "model; with --takeover from where a trained policy hands over (HG-DAgger)")
    p.add_argument("--task", metavar="NAME", help=f"task, the takes in its MuJoCo simulator: {', '.join(TASKS)} "
                                                  f"(default: {TASK.kind}; with --world-model, the model's)")
    p.add_argument("--world-model", metavar="CHECKPOINT",
                   help="world model to record inside instead of MuJoCo (from MuJoCo's initial frames); the task is "
                        "the model's")
    p.add_argument("--episodes", type=int, metavar="N", required=True,
                   help="accepted demonstrations the store should hold")
    p.add_argument("--steps", type=int, metavar="N", default=300, help="horizon of a take (default: %(default)s)")
    p.add_argument("--seed", type=int, metavar="N", default=0,
                   help="candidate i starts from seed SEED + i (default: %(default)s)")
    p.add_argument("--out", metavar="STORE", required=True,
                   help="episode store; rerunning the command resumes it, a store recorded otherwise is refused")
    p.add_argument("--accept-iou", "--accept-score", dest="accept_iou", type=float, metavar="X",
                   help="keep a take once its pixel score (T-push: IoU) reaches this (default: the task's success "
                        "score, 0.9)")
    p.add_argument("--tail", type=int, metavar="N", default=10,
                   help="a kept take ends this many steps after its first success; 0 keeps whole takes "
                        "(default: %(default)s)")
    p.add_argument("--batch", type=int, metavar="N", default=16,
                   help="candidates recorded in lockstep (default: %(default)s)")
    p.add_argument("--max-attempts", type=int, metavar="N", help="candidates tried at most (default: 4 x --episodes)")
    p.add_argument("--give-up-after", type=int, metavar="N",
                   help="stop once this many candidates were tried and none was kept (default: never)")
    experts = "; ".join(f"{', '.join(make().pixel_experts)} ({kind})" for kind, make in TASK_REGISTRY.items())
    p.add_argument("--demonstrator", default="expert", metavar="NAME",
                   help=f"the task's pixel expert: {experts} (default: %(default)s)")
    starts = "; ".join(f"{', '.join(make().starts)} ({kind})" for kind, make in TASK_REGISTRY.items())
    p.add_argument("--start", default="random", metavar="NAME",
                   help=f"MuJoCo's initial states: {starts} (default: %(default)s)")
    p.add_argument("--dart-noise", type=float, default=0.0, metavar="STD",
                   help="std (m) of noise added to the executed commands, the clean ones stored (DART) "
                        "(default: %(default)s)")
    p.add_argument("--takeover", metavar="POLICY", help="a trained policy (run or checkpoint) that drives each take "
                   "until the expert takes over; only the expert's part is stored")
    p.add_argument("--takeover-steps", metavar="LO,HI", help="with --takeover, the expert takes over at a step "
                   "drawn from the candidate's seed in LO..HI (default: 40,200)")
    p.add_argument("--image-size", type=int, metavar="N",
                   help=f"frame size in MuJoCo: {', '.join(map(str, IMAGE_SIZES))} (default: the task's, "
                        f"{TASK.image_size})")
    p.add_argument("--cameras", metavar="NAMES", help="MuJoCo's views to record, comma-separated, as iwsim collect's "
                   "(tabletop tasks: top, side; the takes are scored on the first) (default: top; in a world model, "
                   "its own views)")
    wait_for_lock_flag(p)
    p.add_argument("--no-progress", action="store_true", help="hide the progress bar")
    p.set_defaults(func=_demos)


def _collect(args: argparse.Namespace) -> int:
    from pathlib import Path

    from iwsim.data.views import parse_cameras
    from iwsim.envs import POLICIES
    from iwsim.envs.collect import collect
    from iwsim.envs.registry import DEFAULT_TASK

    cameras = parse_cameras(args.cameras)
    recorder, policy = None, args.policy
    if policy not in POLICIES.get(args.task or DEFAULT_TASK.kind, ()) and Path(policy).is_dir():  # a learned policy
        from iwsim.envs.registry import REGISTRY
        from iwsim.eval.policy import recorder as learned
        from iwsim.policies.factory import load_policy

        if args.out is None:
            raise InputError("collecting a learned policy's episodes needs --out STORE.")
        if cameras != ("top",):
            raise InputError("--cameras: a learned policy's episodes are recorded from the top camera only.")
        net = load_policy(policy)
        own = net.task.name if net.task is not None and net.task.kind in REGISTRY else None
        if args.task is not None and own is not None and own != args.task:
            raise InputError(f"{policy} was trained on episodes of task {own!r} (its checkpoint records it), not "
                             f"--task {args.task}; collect its episodes with --task {own} (or without --task).")
        args.task = args.task or own or DEFAULT_TASK.kind
        if net.image_size != args.image_size:
            raise InputError(f"{policy} was trained on {net.image_size}x{net.image_size} frames, not --image-size "
                             f"{args.image_size}.")
        recorder = learned(net, args.task, args.steps, image_size=args.image_size)
        policy = f"learned:{Path(policy).as_posix()}"
    args.task = args.task or DEFAULT_TASK.kind
    out = args.out or f"data/{args.task}_{args.policy}.zarr"
    collect(
        args.task,
        policy,
        args.episodes,
        out=out,
        steps=args.steps,
        image_size=args.image_size,
        workers=args.workers,
        seed=args.seed,
        progress=not args.no_progress,
        wait_for_lock=args.wait_for_lock,
        recorder=recorder,
        cameras=cameras,
    )
    return 0


def _demos(args: argparse.Namespace) -> int:
    from iwsim.data.views import parse_cameras
    from iwsim.envs.registry import DEFAULT_TASK, get_task
    from iwsim.eval.policy import WORLD_MODEL
    from iwsim.experiments.demos import record_demos

    handover: dict[str, Any] = {}  # --takeover-steps, else record_demos's default
    if args.takeover_steps is not None:
        if args.takeover is None:
            raise InputError("--takeover-steps applies to --takeover (when the expert takes over from the policy).")
        handover["takeover_steps"] = numbers("--takeover-steps", args.takeover_steps, int, "LO,HI, two steps", 2)
    if args.world_model is not None and args.image_size is not None:
        raise InputError("--image-size applies to MuJoCo; a world model renders frames of its own size.")
    cameras = None if args.cameras is None else parse_cameras(args.cameras)
    # a batch's candidates keep every step's frame until they are judged
    check_frames_memory(f"--batch {args.batch} of --steps {args.steps}", args.batch * (args.steps + 1))
    task = None if args.task is None else get_task(args.task)
    env = (task or DEFAULT_TASK()).kind
    if args.world_model is not None:
        env = WORLD_MODEL
    stats = record_demos(env, args.out, args.episodes, args.steps, args.seed, world_model=args.world_model,
                         accept_iou=args.accept_iou, tail=None if args.tail == 0 else args.tail, batch=args.batch,
                         max_attempts=args.max_attempts, give_up_after=args.give_up_after,
                         dart_noise=args.dart_noise, start=args.start, demonstrator=args.demonstrator,
                         takeover=args.takeover, image_size=args.image_size, progress=not args.no_progress,
                         wait_for_lock=args.wait_for_lock, model_task=task, cameras=cameras, **handover)
    print(stats.summary())
    return 0
