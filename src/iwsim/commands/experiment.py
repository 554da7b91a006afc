"""``iwsim experiment``: the robot-learning studies (data generation, policy evaluation)."""

from __future__ import annotations

import argparse
from typing import TYPE_CHECKING, Any, TypeVar

from iwsim.commands.common import numbers
from iwsim.envs.registry import DEFAULT_TASK as TASK
from iwsim.policies import POLICIES as LEARNED_POLICIES

if TYPE_CHECKING:
    from pathlib import Path

C = TypeVar("C")  # a study's config class


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("experiment", help="the robot-learning studies: data generation, policy evaluation")
    exp_sub = p.add_subparsers(dest="experiment", required=True, metavar="EXPERIMENT")
    q = exp_sub.add_parser("datagen", help="policies trained on world-model demonstrations vs simulator ones")
    q.add_argument("--preset", default="default", choices=("default", "act", "tiny"),
                   help="default: Diffusion Policy, mixtures and sizes; act: ACT, mixtures (default: %(default)s)")
    _study_task_flags(q, TASK)
    q.add_argument("--policy", choices=tuple(LEARNED_POLICIES), help="policy type (default: the preset's)")
    q.add_argument("--episodes", type=int, help="MuJoCo evaluation episodes per policy (default: the preset's, 50)")
    q.add_argument("--steps", type=int, help=f"steps per evaluation episode (default: the preset's, the task's "
                                             f"horizon: {TASK.horizon} for {TASK.kind})")
    q.add_argument("--total", type=int, help="demonstrations per mixture run (default: the preset's, 100)")
    q.add_argument("--fractions", help="world-model shares of the mixture runs, comma-separated (default: the "
                                       "preset's, 0,0.25,0.5,0.75,1)")
    q.add_argument("--sizes", help="simulator dataset sizes, comma-separated (default: the preset's)")
    q.add_argument("--wm-sizes", help="world-model dataset sizes, comma-separated (default: the preset's)")
    q.add_argument("--train-steps", type=int, help="training steps per policy (default: the preset's)")
    q.add_argument("--accept-iou", "--accept-score", dest="accept_iou", type=float,
                   help="keep takes whose max pixel score (T-push: IoU) reaches this (default: the preset's, 0.9)")
    q.add_argument("--demo-steps", type=int, help="horizon of a demonstration take (default: the preset's)")
    _study_run_flags(q, "datagen, or datagen-act for --preset act")
    q.set_defaults(func=_experiment_datagen)
    q = exp_sub.add_parser("policy-eval", help="does the world model rank policies like MuJoCo? (r, rho, MMRV)")
    q.add_argument("--preset", default="default", choices=("default", "tiny"), help="scale (default: %(default)s)")
    _study_task_flags(q, TASK)
    q.add_argument("--episodes", type=int, help="episodes per policy and simulator (default: the preset's, 20)")
    q.add_argument("--steps", type=int, help=f"steps per episode (default: the preset's, the task's horizon: "
                                             f"{TASK.horizon} for {TASK.kind})")
    q.add_argument("--seed", type=int, help="episode i starts from MuJoCo seed SEED + i (default: 100000)")
    q.add_argument("--demos", help="demonstration store of the task the policies train on, e.g. from iwsim collect "
                                   "--policy expert (default: the simulator expert's, recorded under --work when "
                                   "missing)")
    q.add_argument("--demo-episodes", type=int, help="demonstrations of the full-data runs (default: 100)")
    q.add_argument("--small-demos", type=int, help="demonstrations of the small-data run (default: 25)")
    q.add_argument("--paired-episodes", help="N,N,...: paired estimates from each policy's first N first states in "
                   "both simulators (e.g. 2,5,10), judged against MuJoCo on --holdout-episodes other first states "
                   "(default: none)")
    q.add_argument("--holdout-episodes", type=int, help="MuJoCo episodes per policy that judge the paired "
                   "estimates (default: 50)")
    _study_run_flags(q, "policy_eval")
    q.set_defaults(func=_experiment_policy_eval)


def _study_task_flags(q: argparse.ArgumentParser, default: Any) -> None:
    """A study's --task, --world-model and --demonstrator (``default``: the default task)."""
    from iwsim.envs import TASKS
    from iwsim.envs.registry import ANY_EXPERTS

    q.add_argument("--task", default=default.kind, choices=tuple(TASKS),
                   help="the task, its MuJoCo simulator the ground truth and its pixel expert the demonstrator "
                        "(default: %(default)s)")
    q.add_argument("--world-model", help=f"a world-model checkpoint of the task (default: the task's shipped one, "
                                         f"{default.checkpoint} for {default.kind}; a task without one needs it)")
    q.add_argument("--demonstrator", choices=ANY_EXPERTS,
                   help="the task's pixel expert that records the demonstrations, e.g. T-push's expert-wide (wider "
                        "margins, easier to imitate); its takes get their own stores (default: expert)")


def _study_run_flags(q: argparse.ArgumentParser, report: str) -> None:
    """A study's --jobs, --out (``report``: its default under bench/results/experiments),
    --work and --no-progress."""
    from iwsim.core.resources import available_cores

    q.add_argument("--jobs", type=int, default=min(2, available_cores()),
                   help="trainings/evaluations at once, one thread each (default: %(default)s)")
    q.add_argument("--out", help=f"report directory (default: bench/results/experiments/{report}; another task's "
                                 "under bench/results/experiments/TASK)")
    q.add_argument("--work", default="runs/experiments", help="demos, runs, evaluations; another task's under "
                                                               "WORK/TASK (default: %(default)s)")
    q.add_argument("--no-progress", action="store_true", help="hide the progress bars")


def _study_config(args: argparse.Namespace, presets: dict[str, C], report: str, **overrides: Any) -> tuple[C, Path]:
    """A study's config: its preset on --task (:func:`iwsim.experiments.common.on_task`),
    the task's world model and the flags' ``overrides`` (None: not given); and its report
    directory (--out, else ``report`` under the task's ``bench/results/experiments``)."""
    import dataclasses
    from pathlib import Path

    from iwsim.envs.registry import get_task, shipped_world_model
    from iwsim.experiments.common import on_task, study_dir

    task = get_task(args.task)
    cfg: Any = on_task(presets[args.preset], task)  # a study's config dataclass
    overrides["world_model"] = args.world_model or shipped_world_model(task)
    cfg = dataclasses.replace(cfg, **{k: v for k, v in overrides.items() if v is not None})
    return cfg, Path(args.out) if args.out else study_dir("bench/results/experiments", task) / report


def _experiment_datagen(args: argparse.Namespace) -> int:
    import dataclasses

    from iwsim.experiments.datagen import PRESETS, run_datagen

    def given(flag: str, text: str | None, kind: type) -> tuple | None:
        return None if text is None else numbers(flag, text, kind)

    base = PRESETS[args.preset]
    recipe = {"accept_iou": args.accept_iou, "steps": args.demo_steps, "demonstrator": args.demonstrator}
    report = "datagen" + ("-act" if args.preset == "act" else "")
    cfg, out = _study_config(
        args, PRESETS, report, policy=args.policy, episodes=args.episodes, steps=args.steps, total=args.total,
        train_steps=args.train_steps, wm_fractions=given("--fractions", args.fractions, float),
        sim_sizes=given("--sizes", args.sizes, int), wm_sizes=given("--wm-sizes", args.wm_sizes, int),
        recipe=dataclasses.replace(base.recipe, **{k: v for k, v in recipe.items() if v is not None}))
    run_datagen(cfg, out=out, work=args.work, preset=args.preset, jobs=args.jobs, progress=not args.no_progress)
    print(f"{out}/results.md")
    return 0


def _experiment_policy_eval(args: argparse.Namespace) -> int:
    import dataclasses

    from iwsim.experiments.policy_eval import PRESETS, headline, run_policy_eval

    base = PRESETS[args.preset].recipe
    recipe = base if args.demonstrator is None else dataclasses.replace(base, demonstrator=args.demonstrator)
    cfg, out = _study_config(args, PRESETS, "policy_eval", episodes=args.episodes, steps=args.steps, seed=args.seed,
                             demos=args.demos, demo_episodes=args.demo_episodes, small_demos=args.small_demos,
                             recipe=recipe, paired=None if args.paired_episodes is None else
                             numbers("--paired-episodes", args.paired_episodes, int, "counts N,N,..."),
                             holdout_episodes=args.holdout_episodes)
    report = run_policy_eval(cfg, out=out, work=args.work, preset=args.preset, jobs=args.jobs,
                             progress=not args.no_progress)
    print(f"{headline(report)} -> {out}/results.md")
    return 0
