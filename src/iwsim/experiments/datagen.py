"""Demonstrations generated in the world model (``iwsim experiment datagen``), the paper's
first robot-learning study: do policies trained on demonstrations recorded inside the
world model perform, in the real task, like policies trained on real ones?

The task (``task``, ``--task``): T-push by default, or another built-in task with a
simulator (pile sweeping), whose expert, scorer and horizon the study then uses.

1. Demonstrations (:func:`iwsim.experiments.demos.record_with` a
   :class:`~iwsim.experiments.demos.DemoRecipe`): the task's pixel-reading expert drives MuJoCo
   (simulator demonstrations, seeds from 0, the store shared with ``iwsim experiment
   policy-eval``) and the world model from
   MuJoCo's initial frames (seeds from 300000); only successful takes are kept. Seeds of
   both are disjoint from evaluation (100000+) and validation (200000+) seeds.
2. Policies (Diffusion Policy by default) trained on mixtures at a fixed total (0, 50,
   100% world model) and on simulator datasets of several sizes; a run shared by the two
   sweeps is trained once.
3. Every policy and the expert itself evaluated in MuJoCo on seeds from 100000: the
   paper's score (the max pixel score within the horizon: T-push's IoU, pile sweeping's
   share in the tray) and success (a score >= the task's 0.9), with Beta-posterior and
   Clopper-Pearson intervals, and the parity ratio score(100% world model) / score(100%
   simulator) with a paired bootstrap interval over the evaluation seeds. The report names
   the scores as the evaluations do (T-push's ``mean_max_iou``, another task's ``mean_max_score``).

Work files (demonstration stores, policy runs, cached evaluations) go under ``work``, so
rerunning the command resumes; the report (``results.json``, ``results.md``,
``datagen.png``) goes to ``out``.
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
from iwsim.core.errors import InputError
from iwsim.envs.registry import get_task
from iwsim.envs.task import Task
from iwsim.eval.figures import pyplot, save_figure
from iwsim.eval.policy import WORLD_MODEL
from iwsim.experiments.common import (
    STUDY,
    STUDY_TASK,
    TASK_FLAG,
    PolicyRun,
    check_dirs,
    check_study_model,
    evaluate_policies,
    fingerprint,
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
from iwsim.experiments.demos import DemoRecipe, DemoStats, record_with, simulator_demos, simulator_store
from iwsim.policies import policy_type
from iwsim.policies.scripted import ScriptedConfig
from iwsim.world_model.env import score_key

log = logging.getLogger(__name__)

BOOTSTRAP = 2000  # resamples of the evaluation episodes for the parity ratio's interval
# The config fields the command's flags override, and the recipe fields.
FLAGS = {"world_model": "--world-model", "policy": "--policy", "total": "--total", "wm_fractions": "--fractions",
         "sim_sizes": "--sizes", "wm_sizes": "--wm-sizes", "train_steps": "--train-steps", "episodes": "--episodes",
         "steps": "--steps"}
RECIPE_FLAGS = {"accept_iou": "--accept-iou", "steps": "--demo-steps", "demonstrator": "--demonstrator"}


@dataclasses.dataclass(frozen=True)
class DatagenConfig:
    task: str = STUDY_TASK  # a built-in task with a simulator (the presets are written for T-push: on_task)
    world_model: str = STUDY.checkpoint
    policy: str = "dp"  # a registered policy (iwsim.policies.POLICIES)
    policy_preset: str = ""  # prefix of the policy's preset: "" (dp, act) or "tiny-"
    train_steps: int | None = None  # None: the preset's
    checkpoint_every: int | None = None  # None: the preset's
    total: int = 50  # demonstrations per run of the mixture sweep
    wm_fractions: tuple[float, ...] = (0.0, 0.5, 1.0)  # world-model share of the mixtures
    sim_sizes: tuple[int, ...] = (25, 50, 100)  # simulator-only datasets of the size sweep
    wm_sizes: tuple[int, ...] = ()  # world-model-only datasets of the size sweep
    recipe: DemoRecipe = DemoRecipe()  # how demonstrations are recorded, in both envs
    wm_seed: int = 300000  # the first world-model candidate's seed (the simulator's: demos.SIM_SEED)
    episodes: int = 50  # evaluation episodes per policy
    eval_seed: int = 100000
    steps: int = 300  # evaluation steps per episode

    def __post_init__(self) -> None:
        study_task(self.task)
        policy_type(self.policy)  # a registered policy (else its one-line InputError)
        for name in ("total", "episodes", "steps"):
            v = getattr(self, name)
            if not isinstance(v, int) or v < 1:
                raise InputError(f"{name} must be a positive integer, got {v!r}.")
        for name in ("train_steps", "checkpoint_every"):
            v = getattr(self, name)
            if v is not None and (not isinstance(v, int) or v < 1):
                raise InputError(f"{name} must be a positive integer, got {v!r}.")
        if not all(0 <= f <= 1 for f in self.wm_fractions):
            raise InputError(f"world-model fractions must be in [0, 1], got {self.wm_fractions}.")
        if not all(isinstance(n, int) and n >= 1 for n in (*self.sim_sizes, *self.wm_sizes)):
            raise InputError(f"dataset sizes must be positive integers, got {self.sim_sizes} and {self.wm_sizes}.")
        if not self.wm_fractions and not self.sim_sizes and not self.wm_sizes:
            raise InputError("the study has no runs: give world-model fractions or dataset sizes.")

    @property
    def preset(self) -> str:
        """The policy training preset (``dp``, ``tiny-act``, ...)."""
        return f"{self.policy_preset}{self.policy}"


PRESETS: dict[str, DatagenConfig] = {
    # The paper's protocol for Diffusion Policy, sized for <= 3 h on a 2-core CPU with two
    # jobs (the recorded report gives each part's time): nine trainings of 3000 steps (the
    # step the scaling curve of bench/policy_scaling.py chose), ten evaluations of 50 x 600
    # steps. Sizes 5, 25, 100 (not also 50) keep it within the budget.
    "default": DatagenConfig(train_steps=3000, checkpoint_every=1000, total=100,
                             wm_fractions=(0.0, 0.25, 0.5, 0.75, 1.0), sim_sizes=(5, 25, 100),
                             wm_sizes=(5, 25, 100), steps=STUDY.horizon),
    # ACT on the same demonstrations, the mixtures only (its scaling curve is flat over 25-100
    # demonstrations, bench/results/policies/scaling.md): five trainings of 4000 steps (the
    # step chosen at 100 demonstrations; measured 21-27 min each on one thread beside another
    # job) ~65 min two at a time, five evaluations of ~4 min; about 1 h 15 min.
    "act": DatagenConfig(policy="act", train_steps=4000, checkpoint_every=1000, total=100,
                         wm_fractions=(0.0, 0.25, 0.5, 0.75, 1.0), sim_sizes=(), steps=STUDY.horizon),
    # Seconds, for tests: tiny policies, a few short takes, every take kept (a random tiny
    # world model never places the T).
    "tiny": DatagenConfig(policy_preset="tiny-", train_steps=4, checkpoint_every=2, total=2, sim_sizes=(1, 2),
                          recipe=DemoRecipe(steps=8, tail=4, accept_iou=0.0, batch=2), episodes=2, steps=6),
}


@dataclasses.dataclass(frozen=True)
class Run:
    """A policy training of the study: its data mixture and the sweeps it belongs to."""

    n_wm: int
    n_sim: int
    sweeps: tuple[str, ...]

    @property
    def total(self) -> int:
        return self.n_wm + self.n_sim

    @property
    def wm_fraction(self) -> float:
        return self.n_wm / self.total

    def name(self, preset: str, wm_tag: str) -> str:
        """``dp-wm25-sim25-<wm_tag>``: runs on world-model demonstrations name the model
        (a retrained one at the same path gets new runs, not the old ones)."""
        return f"{preset}-wm{self.n_wm}-sim{self.n_sim}" + (f"-{wm_tag}" if self.n_wm else "")


def plan(cfg: DatagenConfig) -> list[Run]:
    """The study's trainings, each mixture once (a run of both sweeps is shared)."""
    runs: dict[tuple[int, int], list[str]] = {}
    for f in cfg.wm_fractions:
        n_wm = round(f * cfg.total)
        runs.setdefault((n_wm, cfg.total - n_wm), []).append("mixture")
    for n in cfg.sim_sizes:
        runs.setdefault((0, n), []).append("size")
    for n in cfg.wm_sizes:
        runs.setdefault((n, 0), []).append("size")
    return [Run(w, s, tuple(dict.fromkeys(sweeps))) for (w, s), sweeps in runs.items()]


def demo_paths(cfg: DatagenConfig, work: Path, wm_tag: str) -> dict[str, Path]:
    """The demonstration stores: ``sim`` (stable, shared with other studies) and ``wm``
    (named after the world-model checkpoint and its fingerprint), each the recipe's
    demonstrator's (another than the expert's: its name in the store's)."""
    who = "" if cfg.recipe.demonstrator == "expert" else f"_{cfg.recipe.demonstrator}"
    return {"sim": simulator_store(work, cfg.recipe.demonstrator, model_cameras(cfg.world_model)),
            "wm": work / "demos" / f"wm_teleop_{Path(cfg.world_model).name}_{wm_tag}{who}.zarr"}


def command(cfg: DatagenConfig, preset: str, out: Path, work: Path) -> str:
    """The command that reproduces this study (the flags that differ from the preset)."""
    base = PRESETS[preset]
    changed = [(cfg, base, TASK_FLAG), (cfg, on_task(base, get_task(cfg.task)), FLAGS),
               (cfg.recipe, base.recipe, RECIPE_FLAGS)]
    return study_command("datagen", preset, changed, "--out", str(out), "--work", str(work))


def run_datagen(cfg: DatagenConfig, *, out: str | Path, work: str | Path, preset: str = "default", jobs: int = 1,
                progress: bool = True) -> dict[str, Any]:
    """Run (or resume) the study; write ``results.json``, ``results.md`` and
    ``datagen.png`` to ``out``. Returns the results. Its work goes to
    :func:`~iwsim.experiments.common.study_dir` of ``work`` (``work`` itself for T-push)."""
    task = study_task(cfg.task)
    out = Path(out)
    if jobs < 1:
        raise InputError(f"jobs must be a positive integer, got {jobs}.")
    check_study_model(cfg.world_model, task)
    check_dirs(out=out)
    reproduce = command(cfg, preset, out, Path(work))
    work = study_dir(work, task)
    with lock_work(work, "datagen"):
        return _run_datagen(cfg, task, out, work, reproduce, preset, jobs, progress)


def _run_datagen(cfg: DatagenConfig, task: Task, out: Path, work: Path, reproduce: str, preset: str, jobs: int,
                 progress: bool) -> dict[str, Any]:
    t0 = time.perf_counter()
    runs = plan(cfg)
    tag = fingerprint(cfg.world_model)[:8]
    paths = demo_paths(cfg, work, tag)
    names = {r: r.name(cfg.preset, tag) for r in runs}
    need = {"sim": max((r.n_sim for r in runs), default=0), "wm": max((r.n_wm for r in runs), default=0)}
    cameras = model_cameras(cfg.world_model)  # the simulator's takes are seen by the model's views
    demos: dict[str, DemoStats] = {}
    if need["sim"]:
        _, demos["sim"] = simulator_demos(work, need["sim"], cfg.recipe, progress, task, cameras)
    if need["wm"]:
        demos["wm"] = record_with(WORLD_MODEL, paths["wm"], need["wm"], cfg.wm_seed, cfg.recipe,
                                  world_model=cfg.world_model, progress=progress)
    trainable, skipped = [], {}
    for r in runs:
        short = _shortfall(r, demos, task)
        if short:
            skipped[names[r]] = short
            log.warning("not training %s: %s", names[r], short)
        else:
            trainable.append(r)
    policy_runs = [PolicyRun(names[r], cfg.policy, data=_data(r, paths), steps=cfg.train_steps,
                             preset=cfg.preset, checkpoint_every=cfg.checkpoint_every) for r in trainable]
    run_dirs = train_runs(policy_runs, work / "datagen" / "runs", jobs=jobs, progress=progress)
    seeds = list(range(cfg.eval_seed, cfg.eval_seed + cfg.episodes))
    sources: dict[str, Any] = {**run_dirs, "expert": ScriptedConfig("expert")}
    scores = evaluate_policies(sources, task.kind, seeds=seeds, steps=cfg.steps, world_model=None,
                               out=work / "datagen" / "eval", jobs=jobs, progress=progress)
    key = score_key(task)
    results: dict[str, Any] = {
        "command": reproduce,
        "config": dataclasses.asdict(cfg),
        "preset": preset,
        "scale": {"demonstrations": need, "cameras": list(cameras), "runs": len(runs), "trained": len(trainable),
                  "train_steps": policy_runs[0].stage_config().train.steps if policy_runs else None,
                  "eval_episodes": cfg.episodes, "eval_steps": cfg.steps, "eval_seeds": [seeds[0], seeds[-1]]},
        "demos": {k: {**dataclasses.asdict(s), "complete": s.complete} for k, s in demos.items()},
        "expert": _score(scores["expert"], key),
        "runs": [_run_result(r, names[r], paths, run_dirs, scores, skipped, key) for r in runs],
        "parity": parity(cfg, names, scores, task),
    }
    results["time"] = {  # seconds of each phase, over every invocation that did its part
        "demos": sum(d.seconds for d in demos.values()),
        "training": sum(run["training"]["seconds"] for run in results["runs"] if "training" in run),
        "evaluation": sum(score.get("seconds", 0.0) for score in scores.values()),
        "this_invocation": time.perf_counter() - t0,
    }
    out.mkdir(parents=True, exist_ok=True)
    write_json_atomic(out / "results.json", results, sort_keys=False)
    write_text_atomic(out / "results.md", markdown(results))
    figure(results, out / "datagen.png")
    log.info("%s", headline(results))
    return results


def _shortfall(r: Run, demos: dict[str, DemoStats], task: Task) -> str | None:
    """Why ``r`` cannot be trained (its stores hold too few demonstrations), or None."""
    short = []
    for key, label, n in (("wm", "world-model", r.n_wm), ("sim", "simulator", r.n_sim)):
        if n and n > demos[key].episodes:
            d = demos[key]
            short.append(f"{n} {label} demonstrations, only {d.episodes} were kept ({d.candidates} candidates, "
                         f"acceptance {100 * d.acceptance_rate:.0f}% at pixel {task.score_name} >= {d.accept_iou})")
    return "needs " + "; ".join(short) if short else None


def _data(r: Run, paths: dict[str, Path]) -> tuple[tuple[str, int], ...]:
    return tuple((str(paths[k]), n) for k, n in (("wm", r.n_wm), ("sim", r.n_sim)) if n)


def _score(result: dict[str, Any], key: str) -> dict[str, Any]:
    """The statistics of an evaluation (without its per-step scores), the score named ``key``."""
    keep = (f"mean_max_{key}", f"std_max_{key}", "success_rate", "success_beta_posterior", "success_clopper_pearson",
            "seconds", "episodes")
    return {k: result[k] for k in keep if k in result}


def _run_result(r: Run, name: str, paths: dict[str, Path], run_dirs: dict[str, Path], scores: dict[str, dict],
                skipped: dict[str, str], key: str) -> dict[str, Any]:
    row: dict[str, Any] = {"name": name, "sweeps": list(r.sweeps), "n_wm": r.n_wm, "n_sim": r.n_sim,
                           "wm_fraction": r.wm_fraction,
                           "data": [{"store": s, "episodes": n} for s, n in _data(r, paths)]}
    if name in skipped:
        return {**row, "skipped": skipped[name]}
    return {**row, "run": str(run_dirs[name]), "training": training_time(run_dirs[name]),
            **_score(scores[name], key)}


def parity(cfg: DatagenConfig, names: dict[Run, str], scores: dict[str, dict], task: Task = STUDY) -> dict[str, Any]:
    """score(100% world model) / score(100% simulator) at the mixture total, for ``task``'s
    mean max score (T-push: IoU) and success rate, with a 95% paired bootstrap interval over
    the evaluation seeds."""
    by_data = {(r.n_wm, r.n_sim): name for r, name in names.items()}
    wm, sim = by_data.get((cfg.total, 0)), by_data.get((0, cfg.total))
    if wm is None or sim is None:
        return {"note": "the mixture sweep lacks 0% or 100% world model"}
    if wm not in scores or sim not in scores:
        return {"note": f"{wm if wm not in scores else sim} was not trained (too few demonstrations)"}
    key = score_key(task)
    a = np.array([e[f"max_{key}"] for e in scores[wm]["episodes"]])
    b = np.array([e[f"max_{key}"] for e in scores[sim]["episodes"]])
    rng = np.random.default_rng(0)
    idx = rng.integers(len(a), size=(BOOTSTRAP, len(a)))
    out: dict[str, Any] = {"world_model": wm, "simulator": sim}
    success = task.success_score
    for metric, fa, fb in ((f"mean_max_{key}", a, b), ("success_rate", a >= success, b >= success)):
        den = fb.mean()
        ratio = float(fa.mean() / den) if den > 0 else None
        boot_a, boot_b = fa[idx].mean(1), fb[idx].mean(1)
        ok = boot_b > 0
        lo, hi = (np.quantile(boot_a[ok] / boot_b[ok], [0.025, 0.975]).tolist() if ok.mean() > 0.5 else
                  [None, None])
        out[metric] = {"ratio": ratio, "bootstrap_95": [lo, hi]}
    return out


def headline(r: dict[str, Any]) -> str:
    p = r["parity"]
    if "note" in p:
        return f"parity ratio unavailable: {p['note']}."
    task = report_task(r)

    def fmt(metric: str) -> str:
        ratio, (lo, hi) = p[metric]["ratio"], p[metric]["bootstrap_95"]
        return "n/a" if ratio is None else f"{ratio:.2f} [{_num(lo)}, {_num(hi)}]"

    return (f"parity ratio score(100% world model) / score(100% simulator) with {r['config']['total']} "
            f"demonstrations: {fmt(f'mean_max_{score_key(task)}')} on mean max {task.score_name}, "
            f"{fmt('success_rate')} on success rate "
            f"(95% paired bootstrap intervals).")


def _num(x: float | None, digits: int = 2) -> str:
    return "n/a" if x is None or not math.isfinite(x) else f"{x:.{digits}f}"


def _interval(iv: list[float] | None) -> str:
    return "" if not iv else f"[{iv[0]:.2f}, {iv[1]:.2f}]"


def markdown(r: dict[str, Any]) -> str:
    """The report: scale, demonstrations, the two sweeps and the parity ratio."""
    c, s, t = r["config"], r["scale"], r["time"]
    recipe = c["recipe"]
    task = report_task(r)
    name, key = task.score_name, score_key(task)
    lines = [
        "# Demonstrations generated in the world model",
        "",
        "```",
        r["command"],
        "```",
        "",
        f"**{headline(r)}**",
        "",
        f"Policy: {c['policy']} (preset `{c['policy_preset']}{c['policy']}`, {s['train_steps']} training steps); "
        f"world model `{c['world_model']}`{views_phrase(s.get('cameras'))}. Evaluation in MuJoCo: "
        f"{s['eval_episodes']} episodes of "
        f"{s['eval_steps']} steps (seeds {s['eval_seeds'][0]}..{s['eval_seeds'][1]}); score = max {name} within the "
        f"horizon, success = {name} >= {task.success_score}.",
        "",
        f"Compute (one thread per job, summed over jobs and over the invocations that did the work): "
        f"demonstrations {t['demos'] / 60:.1f} min, training {t['training'] / 60:.1f} min, evaluation "
        f"{t['evaluation'] / 60:.1f} min; this invocation {t['this_invocation'] / 60:.1f} min.",
        "",
        "## Demonstrations",
        "",
        f"The pixel-reading expert; a take is kept when its max pixel {name} reaches "
        f"{recipe['accept_iou']} and ends {recipe['tail']} steps after that (horizon {recipe['steps']} steps).",
        "",
        f"| source | kept / wanted | candidates | acceptance | mean max pixel {name} | steps per demo | "
        "s per candidate |",
        "|---|---|---|---|---|---|---|",
    ]
    for k, d in r["demos"].items():
        lines.append(f"| {'world model' if k == 'wm' else 'simulator'} | {d['episodes']} / {d['wanted']} | "
                     f"{d['candidates']} | {100 * d['acceptance_rate']:.1f}% | {d['mean_candidate_max_iou']:.3f} | "
                     f"{_num(d['mean_length'], 0)} | {d['seconds_per_candidate']:.1f} |")
    e = r["expert"]
    lines += [
        "",
        "## Policies",
        "",
        f"Mean max {name} (95% normal interval), success rate with its Beta-posterior mean and Clopper-Pearson 95% "
        "interval.",
        "",
        f"| run | sweeps | world model / simulator demos | training (steps, min) | mean max {name} | success | "
        "Beta mean | Clopper-Pearson |",
        "|---|---|---|---|---|---|---|---|",
        f"| expert (reference) | | | | {e[f'mean_max_{key}']:.3f} {_mean_interval(e, s['eval_episodes'], key)} | "
        f"{100 * e['success_rate']:.0f}% | {e['success_beta_posterior']['mean']:.2f} | "
        f"{_interval(e['success_clopper_pearson'])} |",
    ]
    for run in r["runs"]:
        head = f"| {run['name']} | {', '.join(run['sweeps'])} | {run['n_wm']} / {run['n_sim']} |"
        if "skipped" in run:
            lines.append(f"{head} not trained: {run['skipped']} | | | | |")
            continue
        t = run["training"]
        lines.append(f"{head} {t['steps']}, {t['seconds'] / 60:.1f} | {run[f'mean_max_{key}']:.3f} "
                     f"{_mean_interval(run, s['eval_episodes'], key)} | {100 * run['success_rate']:.0f}% | "
                     f"{run['success_beta_posterior']['mean']:.2f} | {_interval(run['success_clopper_pearson'])} |")
    lines += ["", "![score against world-model share and dataset size](datagen.png)", ""]
    return "\n".join(lines)


def _mean_interval(score: dict[str, Any], n: int, key: str) -> str:
    half = 1.96 * score[f"std_max_{key}"] / math.sqrt(n)
    return f"± {half:.3f}"


def figure(r: dict[str, Any], path: Path) -> None:
    """Score against the world-model share of the mixtures, and against dataset size (a
    panel per sweep the study ran), each panel with its legend below it."""
    plt = pyplot()
    n = r["scale"]["eval_episodes"]
    task = report_task(r)
    name, key = task.score_name, score_key(task)
    trained = [run for run in r["runs"] if "skipped" not in run]
    sweeps = [("mixture", "world-model share of the demonstrations", [("mixture", trained)]),
              ("size", "demonstrations", [("simulator", [t for t in trained if t["n_wm"] == 0]),
                                          ("world model", [t for t in trained if t["n_sim"] == 0])])]
    sweeps = [s for s in sweeps if any(s[0] in t["sweeps"] for t in trained)] or sweeps[:1]
    fig, axes = plt.subplots(1, len(sweeps), figsize=(6 * len(sweeps), 4.6), sharey=True, squeeze=False)
    for ax, (sweep, xlabel, series) in zip(axes[0], sweeps):
        def x_of(t: dict[str, Any], sweep: str = sweep) -> float:
            return t["wm_fraction"] if sweep == "mixture" else t["n_wm"] + t["n_sim"]

        for label, rows in series:
            rows = sorted((t for t in rows if sweep in t["sweeps"]), key=x_of)
            if not rows:
                continue
            x = np.array([x_of(t) for t in rows])
            best = np.array([t[f"mean_max_{key}"] for t in rows])
            half = np.array([1.96 * t[f"std_max_{key}"] / math.sqrt(n) for t in rows])
            succ = np.array([t["success_rate"] for t in rows])
            cp = np.array([t["success_clopper_pearson"] for t in rows])
            suffix = "" if sweep == "mixture" else f" ({label})"
            ax.errorbar(x, best, yerr=half, marker="o", capsize=3, label=f"mean max {name}{suffix}")
            ax.errorbar(x, succ, yerr=[succ - cp[:, 0], cp[:, 1] - succ], marker="s", capsize=3, linestyle="--",
                        label=f"success rate{suffix}")
        e = r["expert"]
        ax.axhline(e[f"mean_max_{key}"], color="grey", linewidth=0.8, label=f"expert: mean max {name}")
        ax.axhline(e["success_rate"], color="grey", linewidth=0.8, linestyle=":", label="expert: success rate")
        ax.set_xlabel(xlabel)
        ax.set_ylim(-0.02, 1.02)
        ax.grid(alpha=0.3)
        if sweep == "mixture":
            ax.set_xlim(-0.05, 1.05)  # the whole range of shares, also when runs of it were not trained
            ax.set_xticks([0, 0.25, 0.5, 0.75, 1])
            ax.set_title(f"mixtures of {r['config']['total']} demonstrations")
        else:
            sizes = sorted({x_of(t) for t in trained if "size" in t["sweeps"]})
            ax.set_xscale("log")
            ax.set_xticks(sizes, [str(k) for k in sizes])
            ax.minorticks_off()
            ax.set_title("dataset size")
        ax.legend(fontsize=7, loc="upper center", bbox_to_anchor=(0.5, -0.16), ncol=2)
    axes[0][0].set_ylabel("score in MuJoCo (95% intervals)")
    fig.tight_layout()
    save_figure(fig, path)
