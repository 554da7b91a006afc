"""``iwsim demo`` (``make demo``): the shipped world model next to MuJoCo.

From a fresh MuJoCo initial state, a scripted policy of the task (T-push's expert pushes
the T; ``--task pilesweep``'s sweeps the pile) acts in MuJoCo while the world model, given
only the first frame and the same actions, imagines the episode. The two are written side
by side as a video, with the per-step scores.
"""

from __future__ import annotations

import argparse
import json
import logging
from pathlib import Path

from iwsim.core.errors import InputError
from iwsim.envs.registry import get_task
from iwsim.eval.policy import check_model_task
from iwsim.eval.rollout import against_mujoco, write_side_by_side
from iwsim.world_model import WorldModel

log = logging.getLogger(__name__)


def main(args: argparse.Namespace) -> int:
    if args.steps < 1:
        raise InputError(f"--steps must be a positive integer, got {args.steps}.")
    task = get_task(args.task)
    checkpoint = args.checkpoint or task.checkpoint
    if checkpoint is None:
        raise InputError(f"task {task.name!r} has no shipped world model yet; give one with --checkpoint.")
    wm = WorldModel.load(checkpoint)
    check_model_task(wm, task, str(checkpoint))
    result = against_mujoco(wm, args.seed, args.steps, args.policy, progress=True)
    out = Path(args.out)
    video = write_side_by_side(result, out / "world_model_vs_mujoco.mp4")
    s = result.summary()
    summary = {"checkpoint": str(checkpoint), "task": task.name, "seed": args.seed, "policy": args.policy,
               "steps": args.steps,
               **{k: None if v is None else round(v, 4) for k, v in s.items()}}
    print(f"MuJoCo (left) | world model (right), seed {args.seed}, {args.steps} steps of the {args.policy}: "
          f"{video.resolve()}")
    print(json.dumps(summary))
    print(f"Per-step scores: {video.with_suffix('.json').resolve()}")
    print(f"Drive it yourself in the browser: .venv/bin/iwsim play --checkpoint {checkpoint}, "
          "then open http://127.0.0.1:8000/ (WASD / IJKL, mouse drag or a gamepad)")
    return 0
