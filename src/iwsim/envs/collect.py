"""Collect episodes of a MuJoCo task into an episode store (``iwsim collect``): under one of
the task's scripted policies (:meth:`~iwsim.envs.task.Task.record_episode`), or under any
other controller given as a ``recorder`` (a learned policy's: :func:`iwsim.eval.policy.recorder`).

A tool over the task registry (:mod:`iwsim.envs.registry`): it sits in the layer above it
(:data:`iwsim.core.layers.LAYERS`), so nothing in ``data/`` or the registry imports it.

Episode i is recorded with seed ``seed + i``, so a command gives the same data whatever the
number of workers, and re-running it with more episodes appends only the missing ones.
"""

from __future__ import annotations

import dataclasses
import functools
import logging
import multiprocessing as mp
import os
import signal
import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import numpy as np
from tqdm import tqdm

import iwsim
from iwsim.core.errors import InputError
from iwsim.core.resources import require_memory
from iwsim.data.store import EpisodeStore, attrs_mismatch
from iwsim.data.views import DEFAULT_CAMERA, check_cameras
from iwsim.envs import IMAGE_SIZES, check_task
from iwsim.envs.registry import DEFAULT_TASK, get_task

log = logging.getLogger(__name__)

STEP_LOWDIM_BYTES = 256  # per step besides the frame: state, action, poses, IoU, contacts (generous)
# Attributes that must agree before a run may append to an existing store (a store written
# before the cameras attribute existed, or with one camera, has the top view only).
MATCHING_ATTRS = ("task", "policy", "image_size", "steps", "cameras")
ABSENT_ATTRS = {"cameras": [DEFAULT_CAMERA]}
# Records the episodes of the given seeds, in order, each in the store's layout
# (:meth:`iwsim.envs.task.Task.record_episode`'s): a controller that is not a scripted policy.
Recorder = Callable[[list[int]], Iterator[dict[str, np.ndarray]]]


@dataclasses.dataclass(frozen=True)
class CollectStats:
    """What one ``collect`` run added; rates are over the added episodes only."""

    episodes_added: int
    episodes_total: int
    frames_added: int
    seconds: float
    frames_per_second: float
    contact_fraction: float  # fraction of steps with a pusher touching the task's objects
    mean_max_score: float  # mean over episodes of the maximum score reached (T-push: IoU)
    success_rate: float  # fraction of episodes whose maximum score reached the task's success score
    score_name: str = "score"

    def summary(self) -> str:
        return (
            f"added {self.episodes_added} episodes ({self.frames_added} frames) in {self.seconds:.1f} s: "
            f"{self.frames_per_second:.0f} frames/s; pusher contact in {100 * self.contact_fraction:.1f}% "
            f"of steps; mean max {self.score_name} {self.mean_max_score:.3f}; success {100 * self.success_rate:.1f}%"
        )


def store_attrs(task: str, policy: str, steps: int, image_size: int,
                cameras: tuple[str, ...] = (DEFAULT_CAMERA,)) -> dict[str, Any]:
    """Root attributes of a collected store: the task spec (fps, action bounds and names,
    goal pose, ...) plus how the episodes were made, and its views (``cameras``)."""
    return {**get_task(task).store_attrs(), "image_size": image_size, "policy": policy, "steps": steps,
            "cameras": list(cameras), "iwsim_version": iwsim.__version__}


def collect(
    task: str,
    policy: str,
    episodes: int,
    *,
    out: str | os.PathLike,
    steps: int = 200,
    image_size: int = DEFAULT_TASK.image_size,
    workers: int = 1,
    seed: int = 0,
    progress: bool = True,
    wait_for_lock: bool = False,
    recorder: Recorder | None = None,
    cameras: tuple[str, ...] = (DEFAULT_CAMERA,),
) -> CollectStats:
    """Record episodes ``0..episodes-1`` (seeds ``seed + i``) into the store at ``out``.

    Creates the store, or appends the episodes it lacks to one made by the same command
    with fewer episodes. Everything is checked before the store is created or touched.
    ``workers`` > 1 records in spawned processes (MuJoCo's EGL contexts must not be forked);
    episodes are appended in order as they finish. The store's lock is held throughout: a
    second writer is refused (a StoreLockedError naming it) or, with ``wait_for_lock``,
    waited for, after which only the episodes still missing are recorded.

    ``recorder`` records the episodes instead of the scripted policy's workers; ``policy``
    is then only the store's label of it (its ``policy`` attribute). ``cameras``: the
    simulator's views to record (the first in ``data/img``, :mod:`iwsim.data.views`).
    """
    _check_args(task, policy, episodes, steps, image_size, workers, seed, scripted=recorder is None)
    cameras = check_task_cameras(task, cameras, recorder is None)
    out = Path(out)
    attrs = store_attrs(task, policy, steps, image_size, cameras)
    if out.exists():
        if not os.access(out, os.W_OK | os.X_OK):
            raise InputError(f"cannot append to {out}: the directory is not writable.")
    else:
        _check_creatable(out)
    with EpisodeStore.open_or_create(out, attrs, check=lambda s: _check_existing(s, attrs, seed),
                                     wait=wait_for_lock) as store:
        start = store.n_episodes
        if start >= episodes:
            log.info("%s already holds %d episodes (>= %d requested); nothing to do", out, start, episodes)
            return CollectStats(0, start, 0, 0.0, 0.0, float("nan"), float("nan"), float("nan"))
        if recorder is None:
            recorder = functools.partial(_record_scripted, task, policy, steps, image_size, cameras, workers)
        return _collect_into(store, task, policy, start, episodes, steps, image_size, seed, progress, recorder)


def _collect_into(store: EpisodeStore, task: str, policy: str, start: int, episodes: int, steps: int,
                  image_size: int, seed: int, progress: bool, recorder: Recorder) -> CollectStats:
    """Record episodes ``start..episodes-1`` and append them to ``store``, in order."""
    out, n_new, kind = store.path, episodes - start, get_task(task)
    log.info(
        f"collecting {n_new} episodes (seeds {seed + start}..{seed + episodes - 1}) of {task}/{policy}: "
        f"{steps} steps at {image_size}x{image_size} -> {out}"
    )
    seeds = [seed + i for i in range(start, episodes)]
    frames = contact_steps = 0
    max_scores: list[float] = []
    t0 = time.perf_counter()
    with tqdm(total=n_new, unit="ep", desc=f"collect {out.name}", disable=not progress) as bar:
        for s, ep in zip(seeds, recorder(seeds), strict=True):
            if len(ep["img"]) != steps:
                raise RuntimeError(f"the recorder gave an episode of {len(ep['img'])} steps for seed {s}, not {steps}.")
            store.append(ep, seed=s)
            frames += len(ep["img"])
            contact_steps += int(np.count_nonzero(ep["n_contacts"] > 0))
            max_scores.append(float(np.max(ep[kind.episode_score or "score"])))
            bar.update()
            bar.set_postfix_str(f"{frames / (time.perf_counter() - t0):.0f} frames/s")
    seconds = time.perf_counter() - t0
    best = np.asarray(max_scores)
    stats = CollectStats(
        episodes_added=n_new,
        episodes_total=store.n_episodes,
        frames_added=frames,
        seconds=seconds,
        frames_per_second=frames / seconds,
        contact_fraction=contact_steps / frames,
        mean_max_score=float(best.mean()),
        success_rate=float(np.mean(best >= (kind.success_score if kind.success_score is not None else np.inf))),
        score_name=kind.score_name or "score",
    )
    log.info("%s; store now holds %d episodes", stats.summary(), stats.episodes_total)
    return stats


def _check_args(task: str, policy: str, episodes: int, steps: int, image_size: int, workers: int, seed: int,
                scripted: bool = True) -> None:
    check_task(task)
    policies = get_task(task).scripted_policies  # its Task: the attributes its stores carry, its policies
    if scripted and policy not in policies:
        raise InputError(f"unknown policy {policy!r} for task {task!r}; expected one of {list(policies)}.")
    if image_size not in IMAGE_SIZES:
        raise InputError(f"image size must be one of {list(IMAGE_SIZES)}, got {image_size!r}.")
    for name, value in (("episodes", episodes), ("steps", steps), ("workers", workers)):
        if not isinstance(value, int) or value < 1:
            raise InputError(f"{name} must be a positive integer, got {value!r}.")
    if not isinstance(seed, int) or seed < 0:
        raise InputError(f"seed must be a non-negative integer, got {seed!r}.")
    # An episode is held in memory until appended, in each worker and again in this process.
    step_bytes = image_size * image_size * 3 + STEP_LOWDIM_BYTES
    require_memory(2 * min(workers, episodes) * steps * step_bytes,
                   f"episodes of {steps} steps at {image_size}x{image_size} with {min(workers, episodes)} worker(s)")


def _check_creatable(out: Path) -> None:
    """Raise if ``out`` (which does not exist) cannot be created: its nearest existing
    ancestor must be a writable directory."""
    ancestor = out.absolute().parent
    while not ancestor.exists():
        ancestor = ancestor.parent
    if not ancestor.is_dir():
        raise InputError(f"cannot create {out}: {ancestor} is not a directory.")
    if not os.access(ancestor, os.W_OK | os.X_OK):
        raise InputError(f"cannot create {out}: {ancestor} is not writable.")


def _check_existing(store: EpisodeStore, attrs: dict[str, Any], seed: int) -> None:
    """Raise unless this run may append to ``store`` (same command, same seeds)."""
    out = store.path
    stored = store.attrs
    mismatch = attrs_mismatch(store, attrs, MATCHING_ATTRS, ABSENT_ATTRS)
    if mismatch:
        raise InputError(f"{out} holds episodes with {mismatch}; choose another --out.")
    expected = [seed + i for i in range(store.n_episodes)]
    if store.seeds != expected:
        first = next(s for s, e in zip(store.seeds, expected, strict=True) if s != e)
        raise InputError(
            f"{out} holds an episode with seed {first}, which --seed {seed} would not give "
            f"(episode i uses seed {seed} + i); rerun with the store's original --seed or choose another --out."
        )
    if stored.get("iwsim_version") != attrs["iwsim_version"]:
        log.warning(
            "%s was written by iwsim %s; appending episodes from iwsim %s",
            out,
            stored.get("iwsim_version"),
            attrs["iwsim_version"],
        )


def _record(job: Job) -> dict[str, np.ndarray]:
    task, policy, seed, steps, image_size, cameras = job
    return get_task(task).record_episode(policy, seed, steps, image_size, cameras)


def check_task_cameras(task: str, cameras: tuple[str, ...], scripted: bool = True) -> tuple[str, ...]:
    """``cameras`` checked against the task's simulator (``scripted`` False: a recorder of
    its own, which records what it records)."""
    names = check_cameras(cameras, "--cameras")
    have = get_task(task).cameras
    if scripted and names != (DEFAULT_CAMERA,):
        unknown = [c for c in names if c not in have]
        if unknown:
            raise InputError(f"--cameras: task {task!r} has no camera {unknown[0]!r}; it has "
                             f"{', '.join(have) or 'none'}.")
        if names[0] != have[0]:
            raise InputError(f"--cameras: the first camera must be {have[0]!r} (the view the task's scores are "
                             f"read from), got {','.join(names)}.")
    return names


def _record_scripted(task: str, policy: str, steps: int, image_size: int, cameras: tuple[str, ...], workers: int,
                     seeds: list[int]) -> Iterator[dict[str, np.ndarray]]:
    """The scripted policy's episodes of ``seeds``, in order, recorded by ``workers`` processes."""
    return _record_all([(task, policy, s, steps, image_size, cameras) for s in seeds], workers)


Job = tuple[str, str, int, int, int, tuple[str, ...]]  # task, policy, seed, steps, image size, cameras


def _record_all(jobs: list[Job], workers: int) -> Iterator[dict[str, np.ndarray]]:
    """Episodes of ``jobs``, in order; in this process when ``workers`` is 1."""
    if workers == 1 or len(jobs) == 1:
        yield from map(_record, jobs)
        return
    ctx = mp.get_context("spawn")
    with ctx.Pool(min(workers, len(jobs)), initializer=_worker_init, initargs=(os.getpid(),)) as pool:
        yield from pool.imap(_record, jobs)


def _worker_init(parent_pid: int) -> None:
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # Ctrl-C is the parent's to handle

    # A pool worker outlives a SIGKILLed parent (it holds both ends of the task pipe);
    # exit when re-parented instead of idling forever.
    def watch() -> None:
        while os.getppid() == parent_pid:
            time.sleep(1.0)
        os._exit(1)

    threading.Thread(target=watch, name="parent-watch", daemon=True).start()
