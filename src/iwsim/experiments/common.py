"""What both studies share: their task, policy trainings run side by side, and closed-loop
evaluations cached on disk, so that rerunning a study's command resumes it.

A study runs on a built-in task with a ground truth (``--task``; T-push by default, whose
shipped world model, evaluation horizon, scorer and success threshold it then uses; pile
sweeping's are its own, and a world model of it must be given): MuJoCo is its reference and
the task's pixel expert its demonstrator. A study of another task than T-push keeps its work
and writes its report in a directory of its own (:func:`study_dir`).

Parallel work goes to spawned processes with one torch thread each: on a small machine,
two single-threaded trainings side by side finish sooner than the same two one after the
other with two threads each (small convolutions do not split well over threads).
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import logging
import multiprocessing as mp
import os
import threading
import time
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import torch
from tqdm import tqdm

from iwsim.core.checkpoint import check_output_dir, load_json, locate, write_json_atomic
from iwsim.core.config import from_dict, to_dict
from iwsim.core.errors import InputError
from iwsim.core.lock import DirLock, LockedError
from iwsim.core.resources import torch_threads
from iwsim.core.trainer import RESUMABLE_CHANGES, data_by_content
from iwsim.data.store import EpisodeStore
from iwsim.data.views import DEFAULT_CAMERA, store_cameras
from iwsim.envs.registry import DEFAULT_TASK, get_task, task_from_config, task_of
from iwsim.envs.task import Task
from iwsim.eval.policy import WORLD_MODEL, sampled_rollout, summarize, trust
from iwsim.eval.records import command_line
from iwsim.eval.trust import PLAUSIBILITY_EVERY, SIGNALS
from iwsim.policies import PRESETS, PolicyStageConfig, config_class
from iwsim.policies.data import Source
from iwsim.policies.factory import checkpoint_dir, load_policy
from iwsim.policies.scripted import ScriptedBatch, ScriptedConfig
from iwsim.policies.train import train_policy
from iwsim.world_model import WorldModel
from iwsim.world_model.env import OBSERVATION_VERSION, STATE_OBSERVATION_VERSION

log = logging.getLogger(__name__)
# The studies' default task, in one place: MuJoCo's T-push, whose success threshold, scorer,
# evaluation horizon and shipped world model the presets are written for.
STUDY = DEFAULT_TASK()
STUDY_TASK = STUDY.kind

TASK_FLAG = {"task": "--task"}  # a study config's task field and its flag (study_command)
PolicySource = str | Path | ScriptedConfig  # a policy run or checkpoint directory, or a scripted policy


@dataclasses.dataclass(frozen=True)
class PolicyRun:
    """One policy training: a run directory ``root / name``."""

    name: str
    policy: str = "dp"  # a registered policy (iwsim.policies.POLICIES)
    data: tuple[tuple[str, int | None], ...] = ()  # (store path, its first N episodes; None: all)
    steps: int | None = None  # None: the preset's
    preset: str | None = None  # None: the policy's name
    checkpoint_every: int | None = None  # None: the preset's
    seed: int = 0

    def stage_config(self) -> PolicyStageConfig:
        preset = self.preset or self.policy
        if preset not in PRESETS:
            raise InputError(f"unknown policy preset {preset!r}; expected one of {', '.join(PRESETS)}.")
        cfg = PRESETS[preset]
        if cfg.policy != self.policy:
            raise InputError(f"preset {preset!r} is a {cfg.policy!r} policy, not {self.policy!r}.")
        train = dataclasses.replace(cfg.train, seed=self.seed, steps=self.steps or cfg.train.steps,
                                    checkpoint_every=self.checkpoint_every or cfg.train.checkpoint_every)
        return dataclasses.replace(cfg, train=train)

    def sources(self) -> list[Source]:
        if not self.data:
            raise InputError(f"policy run {self.name!r} has no data.")
        return [Source(Path(path), n) for path, n in self.data]


def study_command(study: str, preset: str, changed: Sequence[tuple[Any, Any, Mapping[str, str]]],
                  *tail: str) -> str:
    """The command that reproduces a study run from ``preset``: ``iwsim experiment STUDY
    --preset PRESET``, then the flag of each field that differs from the preset's (``changed``:
    (config, the preset's config, field -> flag) triples), then ``tail``."""
    words = ["experiment", study, "--preset", preset]
    for cfg, base, flags in changed:
        for field, flag in flags.items():
            value = getattr(cfg, field)
            if value != getattr(base, field):
                words += [flag, ",".join(map(str, value)) if isinstance(value, tuple) else str(value)]
    return command_line("iwsim", [*words, *tail])


def check_dirs(**dirs: Path) -> None:
    """Each ``--NAME`` directory a study writes (``--out``, ``--work``) is a directory or
    does not exist yet: checked before hours of work, not when the report is written."""
    for flag, path in dirs.items():
        if path.exists() and not path.is_dir():
            raise InputError(f"--{flag} {path} is a file; expected a directory (it is created if missing).")
        if flag == "out":
            check_output_dir(path)


def lock_work(work: Path, study: str) -> DirLock:
    """The lock of a study's work directory, held while the study runs: two studies on one
    work directory would train the same run directories at once."""
    check_dirs(work=work)
    work.mkdir(parents=True, exist_ok=True)
    try:
        return DirLock(work, what=f"running the {study} study")
    except LockedError:
        holder = (work / ".iwsim.lock").read_text(errors="replace").strip() or "another process"
        raise InputError(f"{work} is in use by another study ({holder}); one study per work directory at a "
                         "time: wait for it, or pass another --work.") from None


def study_task(name: str) -> Task:
    """The built-in task ``name`` a study runs on, or one line of error: a study compares
    with the task's simulator and records its expert's demonstrations."""
    task = get_task(name)
    if not task.has_ground_truth or not task.pixel_experts:
        raise InputError(f"task {name!r} has no simulator and expert for a study to compare with.")
    return task


def study_dir(root: str | os.PathLike, task: Task) -> Path:
    """Where a study of ``task`` keeps its work or writes its report under ``root``: ``root``
    itself for the default task (as ever), ``root / task.kind`` for another, so that the
    tasks' demonstrations, policy runs, cached evaluations and reports never meet."""
    return Path(root) if task.kind == STUDY_TASK else Path(root) / task.kind


def on_task(cfg: Any, task: Task) -> Any:
    """A study's preset ``cfg`` (written for the default task; a config with ``task`` and
    ``steps``) on ``task``: its evaluation horizon where the preset evaluates over the
    default task's (a short preset keeps its own). What a run of the study changes is then
    ``--task`` against the preset (:data:`TASK_FLAG`) and the other flags against this."""
    return dataclasses.replace(cfg, task=task.kind, steps=task.horizon if cfg.steps == STUDY.horizon else cfg.steps)


def report_task(report: dict[str, Any]) -> Task:
    """The task of a study's report (reports written before studies took a task: T-push's)."""
    return get_task(report["config"].get("task", STUDY_TASK))


def check_study_model(world_model: str | os.PathLike | None, task: Task = STUDY) -> None:
    """One line unless ``world_model`` is a world-model checkpoint of ``task``: a study
    compares the model with the task's simulator, its ground truth."""
    path = locate(world_model) if world_model is not None else None  # the shipped one from any directory
    if path is None or not (path / "config.json").is_file():
        raise InputError(f"world model {world_model} is not a checkpoint directory (config.json + "
                         "model.safetensors); pass --world-model PATH.")
    config = load_json(path / "config.json")
    kind = config.get("kind") if isinstance(config, dict) else None
    if kind != "world_model":
        example = f" (e.g. {task.checkpoint})" if task.checkpoint else ""
        raise InputError(f"{path} is {'a ' + repr(kind) if kind else 'not a'} checkpoint, not a world model; pass "
                         f"--world-model a world model{example}.")
    own = task_from_config(config, path / "config.json")
    if own.name != task.name:
        raise InputError(f"{path} is a world model of task {own.name!r}; the study compares with MuJoCo's "
                         f"{task.name!r} (--task): give a world model of {task.name!r} (evaluate a policy in any "
                         "world model with iwsim eval policy).")


def model_cameras(world_model: str | os.PathLike) -> tuple[str, ...]:
    """The camera views of a world-model checkpoint (one checked by :func:`check_study_model`),
    read from its config: a study records its simulator demonstrations with them and its
    policies see them, in MuJoCo and in the model."""
    stage2 = load_json(locate(world_model) / "config.json")["stage2"]
    return tuple(stage2.get("cameras") or (DEFAULT_CAMERA,))  # a model from before views: the one camera


def check_views(path: Path, store: EpisodeStore, cameras: tuple[str, ...]) -> None:
    """One line unless the demonstration store ``path`` holds the views ``cameras`` (a
    study's world model's): its policies see the store's views, and run in that model."""
    have = store_cameras(store.attrs, store.keys)
    if max(len(have), len(cameras)) > 1 and have != tuple(cameras):
        raise InputError(f"{path} holds the camera view(s) {','.join(have)}; the world model sees "
                         f"{','.join(cameras)}: the policies train on the model's views (record the "
                         f"demonstrations with iwsim collect --cameras {','.join(cameras)}).")


def views_phrase(cameras: Sequence[str] | None) -> str:
    """A report's words for the camera views a study's policies see: nothing for one view
    (the reports read as ever)."""
    return f", seeing the camera views {', '.join(cameras)}" if cameras and len(cameras) > 1 else ""


def fingerprint(world_model: str | os.PathLike) -> str:
    """A short content hash of a world-model checkpoint (its weights and config; or of a
    policy checkpoint, the same files) and of the environment's
    :data:`~iwsim.world_model.env.OBSERVATION_VERSION`, so that demonstrations and
    evaluations of a retrained model at the same path, or of an environment that observes
    otherwise, are told apart."""
    h = hashlib.sha256(f"observation {OBSERVATION_VERSION}".encode())
    for name in ("config.json", "model.safetensors"):
        path = locate(world_model) / name
        if not path.is_file():
            raise InputError(f"{world_model} is not a checkpoint: it has no {name}.")
        with path.open("rb") as f:
            for block in iter(lambda: f.read(1 << 20), b""):
                h.update(block)
    if _predicts_state(locate(world_model) / "config.json"):
        h.update(f"state observation {STATE_OBSERVATION_VERSION}".encode())
    return h.hexdigest()[:16]


def _predicts_state(config: Path) -> bool:
    """Whether a checkpoint's config is a world model's that predicts the robot's state."""
    stage2 = load_json(config).get("stage2")
    dynamics = stage2.get("dynamics") if isinstance(stage2, dict) else None
    return isinstance(dynamics, dict) and bool(dynamics.get("state_dim"))


def checkpoints(run: Path) -> dict[int, Path]:
    """The kept checkpoints of a policy run: training step -> checkpoint directory."""
    root = Path(run) / "checkpoints"
    found = [d for d in root.iterdir() if d.name.isdigit()] if root.is_dir() else []
    return {int(d.name): d for d in sorted(found) if (d / "model.safetensors").is_file()}


def training_time(run: Path) -> dict[str, Any]:
    """Training steps and seconds (over all resumes) of a policy run's last checkpoint."""
    kept = checkpoints(run)
    if not kept:
        return {"steps": 0, "seconds": 0.0}
    state = load_json(kept[max(kept)] / "training_state" / "state.json")
    return {"steps": int(state["step"]), "seconds": float(state["elapsed_s"])}


def _finished(run: PolicyRun, root: Path) -> bool:
    """Whether ``root / run.name`` holds this very training, trained to its steps (saved
    as often or not: :data:`~iwsim.core.trainer.RESUMABLE_CHANGES`). A run
    directory with another config is not finished: training it then stops with the
    trainer's "different config" error instead of a stale run being reused."""
    cfg = run.stage_config()
    done = checkpoints(root / run.name)
    if not done or max(done) < cfg.train.steps:
        return False
    saved = load_json(root / run.name / "config.json")
    expected = {"policy": cfg.policy, "model": to_dict(from_dict(config_class(cfg.policy), cfg.model)),
                "train": {k: v for k, v in to_dict(cfg.train).items() if k not in RESUMABLE_CHANGES},
                "shift": cfg.shift,
                "data": [{"path": str(s.path), "episodes": s.episodes,
                          "sha256": EpisodeStore.open(s.path).content_hash(s.episodes)} for s in run.sources()]}
    saved = {k: saved.get(k) for k in expected}
    saved["train"] = {k: v for k, v in (saved["train"] or {}).items() if k not in RESUMABLE_CHANGES}
    saved, expected = data_by_content(saved, json.loads(json.dumps(expected)))  # tuples as lists, as read back
    return expected == saved


def _train(run: PolicyRun, root: Path, progress: bool) -> str:
    train_policy(run.stage_config(), run.sources(), root / run.name, device=torch.device("cpu"), progress=progress)
    return run.name


def _one_thread() -> None:
    """A pool worker's set-up: one torch thread, and tqdm's lock a thread lock: its default
    is a multiprocessing one, whose semaphore a worker never releases (Python then warns of
    "leaked semaphore objects" at exit)."""
    torch.set_num_threads(1)
    tqdm.set_lock(threading.RLock())


def _in_parallel(fn: Callable, calls: list[tuple], jobs: int, desc: str, progress: bool) -> list[Any]:
    """``fn(*args)`` for every args of ``calls``, up to ``jobs`` at a time in spawned
    processes with one torch thread each (``jobs`` <= 1: here, one after the other, also on
    one thread: a job's result must not depend on how many ran beside it, and float sums
    differ in their last bits between thread counts). Results in the order of ``calls``."""
    bar = tqdm(total=len(calls), desc=desc, unit="job", disable=not progress)
    results: list[Any] = [None] * len(calls)
    try:
        if jobs <= 1 or len(calls) <= 1:
            with torch_threads(1):
                for i, args in enumerate(calls):
                    results[i] = fn(*args)
                    bar.update()
            return results
        with mp.get_context("spawn").Pool(min(jobs, len(calls)), initializer=_one_thread) as pool:
            pending = [pool.apply_async(fn, args) for args in calls]
            for i, p in enumerate(pending):
                results[i] = p.get()
                bar.update()
            pool.close()  # the workers exit on their own (leaving the with block would kill them)
            pool.join()
        return results
    finally:
        bar.close()


def train_runs(runs: Sequence[PolicyRun], root: Path, *, jobs: int = 1, progress: bool = True) -> dict[str, Path]:
    """Train (or resume) each run into ``root / name``, up to ``jobs`` at a time in spawned
    processes with one torch thread each (``jobs`` = 1: in this process). A run that has
    reached its steps costs nothing. Returns name -> run directory."""
    names = [r.name for r in runs]
    if len(set(names)) != len(names):
        raise InputError(f"policy run names must be unique, got {names}.")
    root = Path(root)
    for r in runs:
        r.sources()  # a run without data fails here, before any training starts
    todo = [r for r in runs if not _finished(r, root)]
    if todo:
        log.info("training %d policies (%s), %d at a time", len(todo), ", ".join(r.name for r in todo), max(jobs, 1))
        inner = progress and (jobs <= 1 or len(todo) == 1)  # one bar per run only when runs do not interleave
        _in_parallel(_train, [(r, root, inner) for r in todo], jobs, "training policies", progress)
    return {r.name: root / r.name for r in runs}


def _describe(source: PolicySource) -> Any:
    """What identifies a policy in a cached evaluation's key: a scripted config, or the
    content of the checkpoint a path names (a run's ``last``, which changes as it trains),
    so that the same weights at another path reuse the evaluation."""
    if isinstance(source, ScriptedConfig):
        return dataclasses.asdict(source)
    return {"sha256": fingerprint(checkpoint_dir(Path(source)))}


def _load(source: PolicySource, task: Task) -> Any:
    return ScriptedBatch(source, task) if isinstance(source, ScriptedConfig) else load_policy(source)


def _evaluate(name: str, source: PolicySource, env: str, seeds: list[int], steps: int, world_model: str | None,
              path: Path, key: dict[str, Any], progress: bool, samples: int = 1) -> dict[str, Any]:
    torch.manual_seed(0)  # the policies' sampling noise: the same evaluation gives the same scores
    wm = None
    if env == WORLD_MODEL:
        assert world_model is not None  # evaluate_policies checks it
        wm = WorldModel.load(world_model)
    policy = _load(source, get_task(env) if wm is None else task_of(wm))
    image_size = wm.image_size if wm is not None else getattr(policy, "image_size", None)
    run, sampled = sampled_rollout(policy, env, seeds, steps, samples=samples, world_model=wm,
                                   image_size=image_size, progress=progress)
    score = run["score_key"]
    result = {"name": name, "key": key, **summarize(run["iou"].max(1), seeds, run["success_score"], score),
              **trust(run, sampled), "seconds": run["seconds"],
              f"{score}_per_step": np.round(run["iou"], 4).tolist()}
    path.parent.mkdir(parents=True, exist_ok=True)
    write_json_atomic(path, result, sort_keys=False)
    return result


def evaluate_policies(policies: Mapping[str, PolicySource], env: str, *, seeds: Sequence[int], steps: int,
                      world_model: str | Path | None, out: Path, jobs: int = 1,
                      progress: bool = True, samples: int = 1) -> dict[str, dict[str, Any]]:
    """Closed-loop evaluation of each named policy in ``env`` (a built-in task's simulator,
    by the task's name, or "world-model"; a scripted policy is that task's, or the world
    model's) from ``seeds``, all episodes of a policy in lockstep
    (:func:`iwsim.eval.policy.rollout`).

    Cached: ``out / env / f"{name}.json"`` holds :func:`iwsim.eval.policy.summarize`'s
    dict, each step's score (E, steps + 1) (T-push's ``iou_per_step``, another task's
    ``score_per_step``), ``seconds`` and a ``key`` (the policy, seeds, steps, world model
    and its weights); a cached result with the same key is reused. Up to
    ``jobs`` policies at once in spawned processes with one torch thread each. In a world
    model a result holds the trust signals (:func:`iwsim.eval.policy.trust`; ``samples``
    samples of the model each). Returns name -> result.
    """
    if env == WORLD_MODEL and world_model is None:
        raise InputError("evaluating inside the world model needs a world-model checkpoint.")
    seeds = [int(s) for s in seeds]
    wm = str(world_model) if env == WORLD_MODEL else None
    wm_sha256 = wm and fingerprint(wm)  # a retrained model at the same path is another model
    results: dict[str, dict[str, Any]] = {}
    calls = []
    for name, source in policies.items():
        path = Path(out) / env / f"{name}.json"
        key = {"policy": _describe(source), "env": env, "seeds": seeds, "steps": steps,
               "world_model_sha256": wm_sha256}  # identities by content: the same files at another path match
        if wm is not None:  # the trust signals a world-model evaluation measures (iwsim.eval.trust)
            key.update(plausibility_every=PLAUSIBILITY_EVERY, samples=samples, signals=list(SIGNALS))
        if path.is_file() and load_json(path).get("key") == key:
            results[name] = load_json(path)
        else:
            calls.append((name, source, env, seeds, steps, wm, path, key, progress and jobs <= 1, samples))
    if calls:
        log.info("evaluating %d policies in %s (%d episodes x %d steps; %d cached)", len(calls), env, len(seeds),
                 steps, len(results))
        t0 = time.perf_counter()
        for result in _in_parallel(_evaluate, calls, jobs, f"evaluating in {env}", progress):
            results[result["name"]] = result
        log.info("evaluated in %.0f s", time.perf_counter() - t0)
    return {name: results[name] for name in policies}
