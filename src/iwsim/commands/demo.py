"""``iwsim demo``: the shipped world model next to MuJoCo, as a video."""

from __future__ import annotations

import argparse

from iwsim.commands.common import check_frames_memory
from iwsim.core.errors import check_seed
from iwsim.envs import TASKS
from iwsim.envs.registry import DEFAULT_TASK as TASK


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("demo", help="the shipped world model next to MuJoCo under the scripted expert, as a video")
    p.add_argument("--task", default=TASK.kind, help=f"task: {', '.join(TASKS)} (default: %(default)s)")
    p.add_argument("--checkpoint", help=f"world model of the task (default: the task's shipped one, {TASK.checkpoint} "
                   f"for {TASK.kind})")
    p.add_argument("--seed", type=int, default=100000,
                   help="MuJoCo initial state; training data uses seeds below 100000 (default: %(default)s)")
    p.add_argument("--steps", type=int, default=192, help="steps (default: %(default)s)")
    p.add_argument("--policy", default="expert", help="scripted policy: expert or play (default: %(default)s)")
    p.add_argument("--out", default="outputs/demo", help="output directory (default: %(default)s)")
    p.set_defaults(func=_demo)


def _demo(args: argparse.Namespace) -> int:
    from iwsim.eval import demo

    check_seed(args, "seed")
    check_frames_memory(f"--steps {args.steps}", args.steps + 1, 2)  # MuJoCo's frames and the model's

    return demo.main(args)
