"""Policy evaluation in the world model (``iwsim experiment policy-eval``), the paper's
second robot-learning study: does a policy's score inside the world model rank policies
as the simulator (our stand-in for the real robot) does?

The task (``task``, ``--task``): T-push by default, or another built-in task with a
simulator (pile sweeping), whose scripted policies, scorer and horizon the study then uses.

1. A zoo of policies with a wide spread of skill: Diffusion Policy trained on simulator
   expert demonstrations, at several training steps and on a smaller dataset; ACT at two
   training steps; the task's scripted pixel expert, the expert degraded by Gaussian action
   noise or by latency at several levels, and the task's play policy.
2. Every policy evaluated closed-loop from the same seeds (``seed + i``) in MuJoCo and in
   the world model, which starts each episode from MuJoCo's rendering of the same seed
   (identical first frames); all episodes of a policy run in lockstep through the vector
   envs (:func:`iwsim.experiments.common.evaluate_policies`).
3. Agreement of the world model's scores with MuJoCo's over the zoo, for the mean max score
   (T-push: the IoU, the paper's T-pushing score; pile sweeping: the share of the pieces in
   the tray) and for the success rate: Pearson r, Spearman rho and MMRV
   (:mod:`iwsim.eval.ranking`), as in the paper's evaluation figure. The report names the
   scores as the evaluations do (T-push's ``mean_max_iou``, another task's ``mean_max_score``).

Demonstrations: the simulator expert's (``work/demos/sim_expert.zarr``, recorded by
:func:`iwsim.experiments.demos.simulator_demos` with the same recipe as ``iwsim experiment
datagen``, so the two studies share the store), or a store the user brings (``demos``,
e.g. written by ``iwsim collect --policy expert``). Work files (policy runs, cached
evaluations) go under ``work``, so rerunning the command resumes; the report
(``results.json``, ``results.md``, ``scatter.png``) goes to ``out``.
"""

from __future__ import annotations

import dataclasses
import logging
import math
import time
from pathlib import Path
from typing import Any

import numpy as np

from iwsim.core.checkpoint import write_json_atomic, write_text_atomic
from iwsim.core.config import to_dict
from iwsim.core.errors import InputError
from iwsim.data.store import EpisodeStore
from iwsim.envs.registry import foreign_task, get_task
from iwsim.envs.task import Task
from iwsim.eval.figures import pyplot, save_figure
from iwsim.eval.paired import METHOD, TRUST_WEIGHTS, judge_paired, judged_table
from iwsim.eval.policy import WORLD_MODEL, check_args
from iwsim.eval.ranking import agreement
from iwsim.eval.trust import SIGNALS
from iwsim.experiments.common import (
    STUDY,
    STUDY_TASK,
    TASK_FLAG,
    PolicyRun,
    PolicySource,
    check_dirs,
    check_study_model,
    check_views,
    checkpoints,
    evaluate_policies,
    lock_work,
    model_cameras,
    on_task,
    report_task,
    study_command,
    study_dir,
    study_task,
    train_runs,
    training_time,
    views_phrase,
)
from iwsim.experiments.demos import DemoRecipe, simulator_demos
from iwsim.policies.scripted import ScriptedConfig
from iwsim.world_model.env import score_key

log = logging.getLogger(__name__)

BOOTSTRAP = 2000  # resamples of the episodes for the interval of a mean max score
LEVEL = 0.95
# The config fields the command's flags override.
RECIPE_FLAGS = {"demonstrator": "--demonstrator"}  # the recipe fields the command's flags override
SAVE_EVERY = 500  # a study's policy trainings save at least this often (PolicyEvalConfig.runs)
FLAGS = {"world_model": "--world-model", "episodes": "--episodes", "steps": "--steps", "seed": "--seed",
         "demos": "--demos", "demo_episodes": "--demo-episodes", "small_demos": "--small-demos",
         "paired": "--paired-episodes", "holdout_episodes": "--holdout-episodes"}
HOLDOUT_SEED_OFFSET = 10_000  # the held-out MuJoCo first states start this far after the study's own


def envs(task: Task) -> tuple[str, str]:
    """Where the study evaluates: the reference (``task``'s simulator, by its name), then the proxy."""
    return task.kind, WORLD_MODEL


def scores(task: Task) -> dict[str, str]:
    """The scores the study compares, by their key in the evaluations, with their names."""
    return {f"mean_max_{score_key(task)}": f"mean max {task.score_name}", "success_rate": "success rate"}


@dataclasses.dataclass(frozen=True)
class PolicyEvalConfig:
    task: str = STUDY_TASK  # a built-in task with a simulator (the presets are written for T-push: on_task)
    world_model: str = STUDY.checkpoint
    episodes: int = 20  # evaluation episodes per policy and environment
    seed: int = 100000  # episode i starts from MuJoCo seed seed + i in both environments
    steps: int = STUDY.horizon  # steps per evaluation episode (the task's horizon: T-push's 600)
    demos: str | None = None  # a demonstration store; None: the simulator expert's under work/demos
    demo_episodes: int = 100  # demonstrations of the full-data runs (their first N)
    small_demos: int = 25  # demonstrations of the small-data Diffusion Policy run
    policy_preset: str = ""  # prefix of the policies' training presets: "" (dp, act) or "tiny-"
    # Diffusion Policy checkpoints (one run, full data); 3000 steps is where the scaling curve
    # of bench/policy_scaling.py chose to stop at 25 and 100 demonstrations.
    dp_steps: tuple[int, ...] = (500, 1500, 3000)
    dp_small_steps: int = 3000  # Diffusion Policy on small_demos
    act_steps: tuple[int, ...] = (1000, 4000)  # ACT checkpoints (one run, full data)
    # Degradations of the expert that spread its MuJoCo score between the play policy's and
    # its own (measured on 10 seeds x 300 steps, mean max IoU; the expert 0.97, play 0.22):
    # noise 0.004 m 0.97, 0.008 0.94, 0.012 0.65, 0.016 0.44, 0.02 0.21; latency 1-2 steps
    # 0.96, 3 0.92, 4 0.81, 5 0.09 (a cliff: it then misses the block).
    noise: tuple[float, ...] = (0.008, 0.012, 0.016, 0.02)  # the expert with Gaussian action noise (m)
    latency: tuple[int, ...] = (3, 4)  # the expert with latency (steps)
    play: bool = True  # the play policy, a floor
    # Paired estimates (iwsim.eval.paired): for each n, the first n of each policy's first
    # states paired with MuJoCo correct the model's score, judged against MuJoCo on
    # holdout_episodes other first states (seeds from seed + HOLDOUT_SEED_OFFSET). () : none.
    paired: tuple[int, ...] = ()
    holdout_episodes: int = 50
    # How the simulator demonstrations are recorded when missing; the default is datagen's, so
    # the studies share the store (a store's recipe must match to be appended to).
    recipe: DemoRecipe = DemoRecipe()

    def __post_init__(self) -> None:
        study_task(self.task)
        check_args(self.episodes, self.seed, self.steps, 0)
        for name in ("demo_episodes", "small_demos", "dp_small_steps"):
            v = getattr(self, name)
            if not isinstance(v, int) or v < 1:
                raise InputError(f"{FLAGS.get(name, name)} must be a positive integer, got {v!r}.")
        if self.small_demos >= self.demo_episodes:
            raise InputError(f"the small-data run needs fewer demonstrations (--small-demos) than the full-data runs "
                             f"(--demo-episodes {self.demo_episodes}), got {self.small_demos}.")
        for name in ("dp_steps", "act_steps", "latency"):
            v = getattr(self, name)
            if not all(isinstance(s, int) and s >= 1 for s in v):
                raise InputError(f"{name} must be positive integers, got {v!r}.")
        if not all(math.isfinite(n) and n > 0 for n in self.noise):
            raise InputError(f"noise levels must be finite and positive, got {self.noise!r}.")
        if not all(isinstance(n, int) and 2 <= n <= self.episodes for n in self.paired):
            raise InputError(f"--paired-episodes must be counts in 2..{self.episodes} (--episodes), got "
                             f"{self.paired!r}.")
        if not isinstance(self.holdout_episodes, int) or self.holdout_episodes < 2:
            raise InputError(f"--holdout-episodes must be an integer >= 2, got {self.holdout_episodes!r}.")
        if self.paired:
            check_args(self.holdout_episodes, self.seed + HOLDOUT_SEED_OFFSET, self.steps, 0)
        if len(self.policy_names()) < 3:
            raise InputError(f"the study needs at least 3 policies to correlate, got {self.policy_names()}.")

    def scripted(self) -> dict[str, ScriptedConfig]:
        """The scripted policies by name: the expert, its degradations, the play policy."""
        cfgs = [ScriptedConfig("expert"), *(ScriptedConfig("expert", noise=n) for n in self.noise),
                *(ScriptedConfig("expert", latency=k) for k in self.latency)]
        if self.play:
            cfgs.append(ScriptedConfig("play"))
        return {c.name: c for c in cfgs}

    def runs(self, demos: str) -> list[tuple[PolicyRun, tuple[int, ...]]]:
        """The trainings, each with the training steps of the checkpoints evaluated (every
        one of them kept: checkpoints every gcd of those steps and :data:`SAVE_EVERY`, so
        that an interrupted session loses at most that many steps of a run)."""
        plan = [("dp", self.demo_episodes, self.dp_steps), ("dp", self.small_demos, (self.dp_small_steps,)),
                ("act", self.demo_episodes, self.act_steps)]
        return [(PolicyRun(f"{policy}-{n}demos", policy, ((demos, n),), steps=max(steps),
                           preset=f"{self.policy_preset}{policy}", checkpoint_every=math.gcd(*steps, SAVE_EVERY)),
                 tuple(sorted(set(steps)))) for policy, n, steps in plan if steps]

    def policy_names(self) -> list[str]:
        learned = [f"{run.name}-{s}steps" for run, steps in self.runs("") for s in steps]
        return learned + list(self.scripted())


PRESETS: dict[str, PolicyEvalConfig] = {
    # <= 3 h on a 2-core CPU with --jobs 2; measured 1 h 22 min with the demonstrations reused
    # (recording them takes ~5 min): three trainings (62 min of one core; the last one runs
    # alone, 21 min), 14 policies x 20 episodes x 600 steps in MuJoCo (36 min of one core) and
    # in the world model (42 min), two jobs at a time (README, Experiments).
    "default": PolicyEvalConfig(),
    # Seconds, for tests: tiny policies trained a few steps, 2 short episodes.
    "tiny": PolicyEvalConfig(episodes=2, steps=6, demo_episodes=2, small_demos=1, policy_preset="tiny-",
                             dp_steps=(2, 4), dp_small_steps=2, act_steps=(2,), noise=(0.01,), latency=(2,),
                             recipe=DemoRecipe(steps=12, tail=None, accept_iou=0.0)),
}

def command(cfg: PolicyEvalConfig, preset: str, out: Path, work: Path, jobs: int) -> str:
    """The command that reproduces this study (the flags that differ from the preset)."""
    base = PRESETS[preset]
    changed = [(cfg, base, TASK_FLAG), (cfg, on_task(base, get_task(cfg.task)), FLAGS),
               (cfg.recipe, base.recipe, RECIPE_FLAGS)]
    return study_command("policy-eval", preset, changed, "--jobs", str(jobs), "--out", str(out), "--work", str(work))


def _store_tag(path: Path, episodes: int) -> str:
    """A directory name for the runs trained on the first ``episodes`` of a store: its name
    and a hash of what they hold (a copy of the store at another path trains no runs again)."""
    return f"{path.stem}-{EpisodeStore.open(path).content_hash(episodes)[:8]}"


def _demos(cfg: PolicyEvalConfig, work: Path, progress: bool) -> tuple[Path, dict[str, Any]]:
    """The demonstration store the policies train on, checked (or recorded) before any
    training starts, and what it holds."""
    need, task, cameras = cfg.demo_episodes, get_task(cfg.task), model_cameras(cfg.world_model)
    if cfg.demos is not None:
        path = Path(cfg.demos)
        store = EpisodeStore.open(path, "r")
        check_views(path, store, cameras)
        if store.n_episodes < need:
            raise InputError(f"{path} holds {store.n_episodes} demonstrations; the study trains on the first {need} "
                             "(lower --demo-episodes or bring a bigger store).")
        other = foreign_task(path, task)
        if other is not None:
            raise InputError(f"{path} holds episodes of task {other!r}; the study runs on {task.name!r} "
                             "(--task): bring demonstrations of it.")
        return path, {"path": str(path), "episodes": store.n_episodes, "policy": store.attrs.get("policy"),
                      "given": True, "cameras": list(cameras)}
    path, stats = simulator_demos(work, need, cfg.recipe, progress, task, cameras)
    if stats.episodes < need:
        raise InputError(f"{path} holds {stats.episodes} of the {need} simulator demonstrations the study needs "
                         f"after {stats.candidates} candidates (acceptance {100 * stats.acceptance_rate:.0f}%).")
    return path, {"path": str(path), "episodes": stats.episodes, "policy": EpisodeStore.open(path).attrs["policy"],
                  "given": False, "cameras": list(cameras), "first_seed": stats.first_seed,
                  "candidates": stats.candidates, "acceptance_rate": stats.acceptance_rate,
                  "record_seconds": stats.seconds, "added_now": stats.added}


def mean_interval(values: np.ndarray, level: float = LEVEL, resamples: int = BOOTSTRAP,
                  seed: int = 0) -> tuple[float, float]:
    """A percentile bootstrap ``level`` interval of the mean of ``values`` (E,), resampling
    episodes (seeded: the same scores give the same interval)."""
    values = np.asarray(values, dtype=np.float64)
    idx = np.random.default_rng(seed).integers(0, len(values), (resamples, len(values)))
    lo, hi = np.quantile(values[idx].mean(axis=1), [(1 - level) / 2, (1 + level) / 2])
    return float(lo), float(hi)


def _scores(result: dict[str, Any], key: str) -> dict[str, Any]:
    """One policy's scores in one environment, for the report (the score named ``key``: the
    task's :func:`~iwsim.world_model.env.score_key`)."""
    best = np.array([e[f"max_{key}"] for e in result["episodes"]])
    return {f"mean_max_{key}": result[f"mean_max_{key}"], f"mean_max_{key}_interval": list(mean_interval(best)),
            f"std_max_{key}": result[f"std_max_{key}"], "success_rate": result["success_rate"],
            "successes": int(sum(e["success"] for e in result["episodes"])),
            "success_clopper_pearson": result["success_clopper_pearson"],
            "success_beta_posterior": result["success_beta_posterior"], "seconds": result["seconds"],
            f"max_{key}": [round(float(m), 4) for m in best],
            "trust": {n: result[n]["mean"] for n in SIGNALS if n in result}}  # a world model's (iwsim.eval.trust)


def run_policy_eval(cfg: PolicyEvalConfig, *, out: str | Path, work: str | Path, preset: str = "default",
                    jobs: int = 1, progress: bool = True) -> dict[str, Any]:
    """Run (or resume) the study; write ``results.json``, ``results.md`` and
    ``scatter.png`` to ``out``. Returns the results. Its work goes to
    :func:`~iwsim.experiments.common.study_dir` of ``work`` (``work`` itself for T-push)."""
    task = study_task(cfg.task)
    out = Path(out)
    if not isinstance(jobs, int) or jobs < 1:
        raise InputError(f"--jobs must be a positive integer, got {jobs}.")
    check_study_model(cfg.world_model, task)
    check_dirs(out=out)
    reproduce = command(cfg, preset, out, Path(work), jobs)
    work = study_dir(work, task)
    with lock_work(work, "policy-eval"):
        return _run_policy_eval(cfg, task, out, work, reproduce, jobs, progress, preset)


def _run_policy_eval(cfg: PolicyEvalConfig, task: Task, out: Path, work: Path, reproduce: str, jobs: int,
                     progress: bool, preset: str) -> dict[str, Any]:
    t0, timings = time.perf_counter(), {}

    log.info("policy-eval 1/4: demonstrations")
    demos, demo_info = _demos(cfg, work, progress)
    timings["demos_s"] = time.perf_counter() - t0

    plan = cfg.runs(str(demos))
    log.info("policy-eval 2/4: training %d policy runs on %s", len(plan), demos)
    t = time.perf_counter()
    runs_dir = work / "policy_eval" / "runs" / _store_tag(demos, cfg.demo_episodes)
    run_dirs = train_runs([r for r, _ in plan], runs_dir, jobs=jobs, progress=progress)
    timings["training_s"] = time.perf_counter() - t
    timings["training_measured_s"] = sum(training_time(d)["seconds"] for d in run_dirs.values())
    zoo: dict[str, dict[str, Any]] = {}
    sources: dict[str, PolicySource] = {}
    for run, steps in plan:
        kept = checkpoints(run_dirs[run.name])
        for s in steps:
            if s not in kept:
                raise InputError(f"{run_dirs[run.name]} kept no checkpoint at step {s} (it has {sorted(kept)}).")
            name = f"{run.name}-{s}steps"
            sources[name] = kept[s]
            zoo[name] = {"kind": run.policy, "source": str(kept[s]), "train_steps": s, "demos": run.data[0][1]}
    for name, sc in cfg.scripted().items():
        sources[name] = sc
        zoo[name] = {"kind": "scripted", "source": to_dict(sc), "train_steps": None, "demos": None}

    seeds = [cfg.seed + i for i in range(cfg.episodes)]
    results: dict[str, dict[str, dict[str, Any]]] = {}
    for k, env in enumerate(envs(task)):
        log.info("policy-eval %d/4: evaluating %d policies in %s (%d episodes x %d steps)", 3 + k, len(sources), env,
                 cfg.episodes, cfg.steps)
        t = time.perf_counter()
        results[env] = evaluate_policies(sources, env, seeds=seeds, steps=cfg.steps,
                                         world_model=cfg.world_model if env == WORLD_MODEL else None,
                                         out=work / "policy_eval" / "eval", jobs=jobs, progress=progress)
        timings[f"eval_{env.replace('-', '_')}_s"] = time.perf_counter() - t
        timings[f"eval_{env.replace('-', '_')}_measured_s"] = sum(r["seconds"] for r in results[env].values())
    holdout = None
    if cfg.paired:
        held = [cfg.seed + HOLDOUT_SEED_OFFSET + i for i in range(cfg.holdout_episodes)]
        log.info("policy-eval: the paired estimates' truth, %d policies x %d held-out first states in %s",
                 len(sources), len(held), task.kind)
        t = time.perf_counter()
        holdout = evaluate_policies(sources, task.kind, seeds=held, steps=cfg.steps, world_model=None,
                                    out=work / "policy_eval" / "eval_holdout", jobs=jobs, progress=progress)
        timings["eval_holdout_s"] = time.perf_counter() - t
    timings["total_s"] = time.perf_counter() - t0

    policies = [{"name": name, **info, **{env: _scores(results[env][name], score_key(task)) for env in envs(task)}}
                for name, info in zoo.items()]
    report: dict[str, Any] = {
        "command": reproduce,
        "study": "policy-eval",
        "preset": preset,
        "config": to_dict(cfg),
        "scale": {"policies": len(policies), "episodes": cfg.episodes, "steps": cfg.steps,
                  "seeds": [seeds[0], seeds[-1]], "world_model": cfg.world_model, "demos": demo_info,
                  "jobs": jobs, "groups": {g: len(m) for g, m in _groups(policies).items()}},
        "policies": policies,
        "agreement": _agreement(policies, task),
        # the same within the scripted and the learned policies: a world model can order
        # each group well yet be biased for one of them, which the pooled figures hide
        "agreement_within": {group: _agreement(members, task) for group, members in _groups(policies).items()},
        **({} if holdout is None else {"paired": paired_report(cfg, results, holdout, task)}),
        "timings": {k: round(v, 1) for k, v in timings.items()},
        "note": ("timings are this invocation's, so a rerun that reuses cached work shows less; the *_measured_s "
                 "entries sum the trainings' and evaluations' own times (one process each), whenever they ran."),
    }
    out.mkdir(parents=True, exist_ok=True)
    write_json_atomic(out / "results.json", report, sort_keys=False)
    scatter(report, out / "scatter.png")
    if holdout is not None:
        paired_figure(report, out / "paired.png")
    write_text_atomic(out / "results.md", markdown(report))
    log.info("policy-eval: %s -> %s", headline(report), out)
    return report


def paired_report(cfg: PolicyEvalConfig, results: dict[str, dict[str, dict[str, Any]]],
                  holdout: dict[str, dict[str, Any]], task: Task) -> dict[str, Any]:
    """For each n of ``cfg.paired``: every policy's paired estimate of its real mean max
    score (the model's episodes, MuJoCo's first n of the same first states), judged against
    MuJoCo's mean over the held-out first states: whether the interval covers it, its
    half-width against n MuJoCo episodes alone (Student t), and the ranking of the estimates
    against the held-out means (r, rho, MMRV)."""
    key = score_key(task)
    reference, proxy = envs(task)
    names = list(results[proxy])
    out: dict[str, Any] = {"holdout_episodes": cfg.holdout_episodes,
                           "holdout_seeds": [cfg.seed + HOLDOUT_SEED_OFFSET, cfg.seed + HOLDOUT_SEED_OFFSET
                                             + cfg.holdout_episodes - 1], "method": METHOD}
    truth = {name: float(holdout[name][f"mean_max_{key}"]) for name in names}
    model = {name: [e[f"max_{key}"] for e in results[proxy][name]["episodes"]] for name in names}
    real = {name: [e[f"max_{key}"] for e in results[reference][name]["episodes"]] for name in names}
    signals = {signal: {name: results[proxy][name][signal]["per_episode"] for name in names}
               for signal in TRUST_WEIGHTS if all(signal in results[proxy][name] for name in names)}
    return {**out, **judge_paired(model, real, truth, cfg.paired, f"mean max {task.score_name}s", signals)}


def _agreement(policies: list[dict[str, Any]], task: Task) -> dict[str, dict[str, Any]]:
    """Per score: :func:`agreement` of the world model's scores with MuJoCo's, and the mean
    offset (world model minus MuJoCo)."""
    out = {}
    reference, proxy = envs(task)
    for score, label in scores(task).items():
        real = [p[reference][score] for p in policies]
        sim = [p[proxy][score] for p in policies]
        out[score] = {**agreement(real, sim, labels=(f"MuJoCo {label}s", f"world-model {label}s")),
                      "mean_offset": float(np.mean(np.subtract(sim, real)))}
    return out


def _groups(policies: list[dict[str, Any]]) -> dict[str, list[dict[str, Any]]]:
    """The scripted and the learned policies, each when it has at least three."""
    groups = {"scripted": [p for p in policies if p["kind"] == "scripted"],
              "learned": [p for p in policies if p["kind"] != "scripted"]}
    return {k: v for k, v in groups.items() if len(v) >= 3}


def _fmt(v: float | None, digits: int = 3) -> str:
    return "undefined" if v is None else f"{v:.{digits}f}"


def headline(report: dict[str, Any]) -> str:
    """One line per score: the three agreement statistics."""
    lines = []
    for score, label in scores(report_task(report)).items():
        a = report["agreement"][score]
        lines.append(f"{label}: Pearson r {_fmt(a['pearson'])}, Spearman rho {_fmt(a['spearman'])}, "
                     f"MMRV {_fmt(a['mmrv'])}")
    return "; ".join(lines)


def markdown(report: dict[str, Any]) -> str:
    """``results.md``: the command, the scale, the headline figures and a row per policy."""
    s = report["scale"]
    lo, hi = s["seeds"]
    demos = s["demos"]
    task = report_task(report)
    name, key, (reference, proxy) = task.score_name, score_key(task), envs(task)
    lines = [
        "# Policy evaluation in the world model: does it rank policies like MuJoCo?",
        "",
        f"`{report['command']}`",
        "",
        f"{s['policies']} policies, each evaluated from the same {s['episodes']} initial states (MuJoCo seeds "
        f"{lo}-{hi}) for {s['steps']} steps in MuJoCo and in the world model `{s['world_model']}` (which starts from "
        f"MuJoCo's rendering of the same seed). Score: the maximum {name} an episode reaches; success: {name} >= "
        f"{task.success_score:g}. "
        f"Learned policies trained on the first N (the demos column) of the {demos['episodes']} demonstrations "
        f"in `{demos['path']}` (policy `{demos['policy']}`){views_phrase(demos.get('cameras'))}. Intervals: 95%; "
        f"mean max {name} by a bootstrap over episodes, success by Clopper-Pearson.",
        "",
        "## Agreement (world model against MuJoCo)",
        "",
        "| score | Pearson r | Spearman rho | MMRV |",
        "|---|---|---|---|",
    ]
    notes = []
    for score, label in scores(task).items():
        a = report["agreement"][score]
        lines.append(f"| {label} | {_fmt(a['pearson'])} | {_fmt(a['spearman'])} | {_fmt(a['mmrv'])} |")
        notes += [f"- {label}, {k}: {why}" for k, why in a["undefined"].items()]
    if notes:
        lines += ["", "Undefined statistics:", "", *notes]
    within = report.get("agreement_within", {})
    if within:
        lines += ["", "Within each group of policies (the pooled figures above also compare across groups):", "",
                  "| group | policies | score | Pearson r | Spearman rho | MMRV | mean offset (world model - MuJoCo) |",
                  "|---|---|---|---|---|---|---|"]
        sizes = report["scale"].get("groups", {})
        for group, by_score in within.items():
            for score, label in scores(task).items():
                a = by_score[score]
                lines.append(f"| {group} | {sizes.get(group, '')} | {label} | {_fmt(a['pearson'])} | "
                             f"{_fmt(a['spearman'])} | {_fmt(a['mmrv'])} | {a['mean_offset']:+.3f} |")
    lines += [
        "",
        "MMRV (mean maximum rank violation, SIMPLER): for each policy, the largest MuJoCo-score gap to a policy the "
        "world model orders the other way, averaged over policies (0 = the same ranking).",
        "",
        "## Policies",
        "",
        f"| policy | kind | train steps | demos | MuJoCo max {name} | world model max {name} | MuJoCo success | "
        "world model success | world model: trust signals (mean) |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for p in sorted(report["policies"], key=lambda p: -p[reference][f"mean_max_{key}"]):
        cells = [p["name"], p["kind"], p["train_steps"] or "-", p["demos"] or "-"]
        for env in (reference, proxy):
            r = p[env]
            lo_, hi_ = r[f"mean_max_{key}_interval"]
            cells.append(f"{r[f'mean_max_{key}']:.3f} ({lo_:.2f}-{hi_:.2f})")
        for env in (reference, proxy):
            r = p[env]
            lo_, hi_ = r["success_clopper_pearson"]
            cells.append(f"{r['success_rate']:.2f} ({lo_:.2f}-{hi_:.2f})")
        cells.append(", ".join(f"{n} {v:.3f}" for n, v in p[proxy].get("trust", {}).items()) or "-")
        lines.append("| " + " | ".join(map(str, cells)) + " |")
    lines += _paired_markdown(report.get("paired"), name)
    t = report["timings"]
    lines += ["", "## Time", ""]
    lines += [f"- {k.removesuffix('_s').replace('_', ' ')}: {v / 60:.1f} min" for k, v in t.items()]
    plots = "`scatter.png`" + (", the paired estimates `paired.png`" if report.get("paired") else "")
    lines += ["", f"({report['note']})", "", f"Plots: {plots}.", ""]
    return "\n".join(lines)


def _paired_markdown(paired: dict[str, Any] | None, name: str | None) -> list[str]:
    """The paired estimates' section of ``results.md`` (none without them)."""
    if not paired:
        return []
    lo, hi = paired["holdout_seeds"]
    lines = ["", "## Paired estimates (the model corrected by n MuJoCo episodes of the same first states)", "",
             f"Judged against MuJoCo's mean max {name} over {paired['holdout_episodes']} held-out first states "
             f"(seeds {lo}-{hi}). {paired['method']}.", "", *PAIRED_HEADER, *_paired_table(paired["by_n"])]
    for signal, t in paired.get("trust_weighted", {}).items():
        warned = np.mean(list(t["warned_share"].values()))
        lines += ["", f"Distrusted where `{signal}` > {t['warn']:g} ({warned:.0%} of the model's episodes): the "
                  "model's episode scores there replaced by their mean over those episodes (still unbiased):", "",
                  *PAIRED_HEADER, *_paired_table(t["by_n"])]
    lines += ["", "Per policy (95% intervals; * : the interval misses the held-out mean):", "",
              *judged_table(paired["by_n"], "policy")]
    return lines


PAIRED_HEADER = ("| n | coverage of the 95% intervals (n MuJoCo alone) | median half-width | against n MuJoCo "
                 "episodes alone | Pearson r (n MuJoCo alone) | Spearman rho | MMRV (n MuJoCo alone) |",
                 "|---|---|---|---|---|---|---|")


def _paired_table(by_n: dict[str, Any]) -> list[str]:
    lines = []
    for n, r in by_n.items():
        a, alone, ratio = r["agreement"], r["agreement_real_alone"], r["median_half_width_ratio"]
        lines.append(f"| {n} | {r['coverage']:.0%} ({r['coverage_real_alone']:.0%}) | {r['median_half_width']:.3f} | "
                     f"{'-' if ratio is None else f'{ratio:.2f}x'} | {_fmt(a['pearson'])} ({_fmt(alone['pearson'])}) | "
                     f"{_fmt(a['spearman'])} | {_fmt(a['mmrv'])} ({_fmt(alone['mmrv'])}) |")
    return lines


COLORS = {"dp": "tab:blue", "act": "tab:orange", "scripted": "tab:green"}


def scatter(report: dict[str, Any], path: Path) -> None:
    """World-model score against MuJoCo score per policy, for the mean max score (T-push:
    IoU; bootstrap intervals) and success rate (Clopper-Pearson intervals), with the y = x
    line and the agreement statistics in each title."""
    plt = pyplot()
    fig, axes = plt.subplots(1, 2, figsize=(12, 5.8))
    policies = report["policies"]
    task = report_task(report)
    mean, (ref, proxy) = f"mean_max_{score_key(task)}", envs(task)
    for ax, (score, label) in zip(axes, scores(task).items()):
        interval = f"{mean}_interval" if score == mean else "success_clopper_pearson"
        for kind, color in COLORS.items():
            group = [p for p in policies if p["kind"] == kind]
            if not group:
                continue
            x = np.array([p[ref][score] for p in group])
            y = np.array([p[proxy][score] for p in group])
            xe = np.array([[x_ - p[ref][interval][0], p[ref][interval][1] - x_] for x_, p in zip(x, group)]).T
            ye = np.array([[y_ - p[proxy][interval][0], p[proxy][interval][1] - y_] for y_, p in zip(y, group)]).T
            ax.errorbar(x, y, xerr=np.maximum(xe, 0), yerr=np.maximum(ye, 0), fmt="o", color=color, ms=5,
                        elinewidth=0.8, capsize=2, alpha=0.85, label=kind)
        placed: list[tuple[float, float]] = []
        for p in sorted(policies, key=lambda p: (p[ref][score], p[proxy][score])):
            xy = (p[ref][score], p[proxy][score])
            # labels of nearby points are stacked upwards instead of drawn over each other
            near = sum(abs(xy[0] - a) < 0.12 and abs(xy[1] - b) < 0.03 for a, b in placed)
            placed.append(xy)
            ax.annotate(p["name"], xy, textcoords="offset points", xytext=(4, 3 + 7 * near), fontsize=6,
                        color=COLORS.get(p["kind"], "black"))
        ax.plot([0, 1], [0, 1], color="grey", lw=0.8, ls="--", label="y = x")
        ax.set_xlim(-0.03, 1.03)
        ax.set_ylim(-0.03, 1.03)
        ax.set_aspect("equal")
        ax.set_xlabel(f"MuJoCo {label}")
        ax.set_ylabel(f"world model {label}")
        a = report["agreement"][score]
        ax.set_title(f"{label}: r = {_fmt(a['pearson'], 2)}, rho = {_fmt(a['spearman'], 2)}, "
                     f"MMRV = {_fmt(a['mmrv'], 3)}", fontsize=10)
        ax.legend(fontsize=7, loc="upper left")
    s = report["scale"]
    fig.suptitle(f"{s['policies']} policies x {s['episodes']} episodes x {s['steps']} steps; 95% intervals "
                 f"(max {task.score_name}: bootstrap; success: Clopper-Pearson)", fontsize=9)
    fig.tight_layout()
    save_figure(fig, path)


def paired_figure(report: dict[str, Any], path: Path) -> None:
    """One panel per n of the paired estimates: each policy's estimate of its real mean max
    score with its 95% interval against MuJoCo's mean over the held-out first states (a
    hollow marker: the interval misses it), the model's own score beside it (grey), the
    y = x line, and the coverage, half-width and ranking in the title."""
    plt = pyplot()
    paired, task = report["paired"], report_task(report)
    by_n = paired["by_n"]
    proxy = envs(task)[1]
    kinds = {p["name"]: p["kind"] for p in report["policies"]}
    own = {p["name"]: p[proxy][f"mean_max_{score_key(task)}"] for p in report["policies"]}
    fig, axes = plt.subplots(1, len(by_n), figsize=(5.2 * len(by_n), 5.4), squeeze=False)
    for ax, (n, r) in zip(axes[0], by_n.items()):
        for name, row in r["policies"].items():
            color = COLORS.get(kinds.get(name, ""), "black")
            lo, hi = row["interval"]
            x, y = row["truth"], row["estimate"]
            ax.plot([x, x], [own[name], y], color="grey", lw=0.5, alpha=0.6)
            ax.plot(x, own[name], "x", color="grey", ms=4)
            ax.errorbar(x, y, yerr=[[max(y - lo, 0)], [max(hi - y, 0)]], fmt="o", color=color, ms=5,
                        mfc=color if row["covered"] else "white", elinewidth=0.9, capsize=2)
        for kind, color in COLORS.items():
            if kind in kinds.values():
                ax.plot([], [], "o", color=color, label=kind)
        ax.plot([], [], "x", color="grey", label="the model's own score")
        ax.plot([], [], "o", color="black", mfc="white", label="interval misses the held-out mean")
        ax.plot([0, 1], [0, 1], color="grey", lw=0.8, ls="--")
        ax.set_xlim(-0.03, 1.03)
        ax.set_ylim(-0.03, 1.03)
        ax.set_aspect("equal")
        ax.set_xlabel(f"MuJoCo mean max {task.score_name}, {paired['holdout_episodes']} held-out first states")
        ax.set_ylabel(f"paired estimate (n = {n}), 95% interval")
        a, ratio = r["agreement"], r["median_half_width_ratio"]
        ax.set_title(f"n = {n}: coverage {r['coverage']:.0%}, half-width {r['median_half_width']:.3f}"
                     f"{'' if ratio is None else f' ({ratio:.2f}x MuJoCo alone)'}\nr = {_fmt(a['pearson'], 2)}, "
                     f"rho = {_fmt(a['spearman'], 2)}, MMRV = {_fmt(a['mmrv'], 3)}", fontsize=9)
        ax.legend(fontsize=7, loc="upper left")
    fig.suptitle(f"{len(kinds)} policies: the model's score corrected by n paired MuJoCo episodes "
                 "(prediction-powered, Student t)", fontsize=9)
    fig.tight_layout()
    save_figure(fig, path)
