"""Scripted demonstrations recorded through a vector env, in the episode-store layout,
kept only when they succeed (what ``iwsim experiment datagen`` trains policies on).

    stats = record_demos("world-model", "runs/demos/wm.zarr", episodes=50, steps=300, seed=300000,
                         world_model="checkpoints/pusht-64")

The teleoperator is the task's pixel-reading expert (:class:`~iwsim.policies.scripted.ScriptedBatch`
``"expert"``, or the ``demonstrator`` chosen, e.g. T-push's ``"expert-wide"``: what it acts on,
T-push's block pose or pile sweeping's pieces, is read from the frame, exactly what a person
sees). With ``env="world-model"`` it drives the world model's batched vector env from MuJoCo's
initial frames (the same first frame as MuJoCo for the same seed), the motion a person makes
in ``iwsim play``; with ``env`` a task's name (``"pusht"``, ``"pilesweep"``) the same code
drives that task's MuJoCo simulator and gives the simulator demonstrations. The task is the
world model's, or the simulator's. Both go through :func:`iwsim.eval.policy.rollout`, the
loop that evaluates policies.

Acceptance, as a person discards a failed take: a candidate episode is kept when its
pixel score (the task's scorer on the frame, the same in both envs: T-push's IoU of the block
segmented from the frame with the goal, pile sweeping's share of the pieces in the tray;
``accept_iou`` is named after T-push's, the first task) reaches ``accept_iou`` at some step.
Candidate i starts from seed ``seed + i``; candidates are drawn in batches until ``episodes`` are kept or
``max_attempts`` were tried. All candidates of a batch step together; the batch stops
early once every one of them has recorded all it will keep (see Length).

Length: a kept episode ends ``tail`` steps after the first frame that reaches
``accept_iou`` (the success frame and ``tail - 1`` frames after it are stored), as a
teleoperator stops recording once the task is done. The expert succeeds after some 20-140
of a 300-step horizon in MuJoCo and then holds the block in place; kept whole, the
episodes would be mostly that hold, and imitation learning would spend most of its
samples on "stand still once the T is placed", a state the policy rarely reaches before
its horizon ends. ``tail=None`` keeps whole episodes. The same rule applies in both envs.

Takeover (HG-DAgger, Kelly et al. 2019, after DAgger, Ross et al. 2011): with ``takeover``
a trained policy drives candidate i until its handover step ``h_i`` (drawn from its seed in
``takeover_steps``), and the expert, started afresh on the state the policy left, from then
on. Only the expert's part (steps ``h_i`` on) is stored and judged: a take is kept when its
score is below ``accept_iou`` at ``h_i`` (a take that starts solved shows nothing) and
reaches it later, ``tail`` counted from that success. The takes start from the states the
learned policy reaches, which the expert's own takes never visit (Diffusion Policy carries
the T onto the goal turned by 45-90 degrees and never finishes the turn).

Per step (the layout of ``iwsim play``'s recorder and ``iwsim collect``): ``img`` (T, H,
W, 3) uint8, the frame before action t; ``state`` (T, 4) float32, agent_pos (read from the
pixels in the world model); ``action`` (T, 4) float32, the command; ``target`` (T, 4)
float32, the speed-limited setpoints action t executed (``info["target"]``); the frame's
pixel score (T,) float32, named as the world model's ``info`` names it (T-push's ``iou``,
another task's ``score``). Attributes: the task spec (as ``iwsim collect``), the
policy (``world-model-teleop`` or ``expert-pixels``), the demonstrator, the world-model
checkpoint, the acceptance rule and the candidates tried with their scores; with takeover,
the policy's checkpoint, its fingerprint, ``takeover_steps`` and each kept take's
``handover_steps``.

Resuming: the store is appended to under its lock; a rerun with the same arguments (or
more ``episodes`` / ``max_attempts``) continues from the first candidate not yet tried.

The studies record with a :class:`DemoRecipe` (:func:`record_with`); the simulator
expert's demonstrations, which both ``iwsim experiment datagen`` and ``iwsim experiment
policy-eval`` train on, live in one shared store (:func:`simulator_demos`,
``work/demos/sim_expert.zarr``, seeds from :data:`SIM_SEED`; a study of another task than
T-push works in a directory of its own, :func:`iwsim.experiments.common.study_dir`).
"""

from __future__ import annotations

import dataclasses
import logging
import math
import os
import time
from pathlib import Path
from typing import Any

import numpy as np
from tqdm import tqdm

from iwsim.core.checkpoint import check_finite_output
from iwsim.core.errors import InputError
from iwsim.data.store import EpisodeStore, attrs_mismatch
from iwsim.data.views import IMAGE_KEY, VIEW_PREFIX, first_view, unstack_views, view_keys
from iwsim.envs import IMAGE_SIZES
from iwsim.envs.collect import check_task_cameras, store_attrs
from iwsim.envs.registry import ANY_EXPERTS, REGISTRY, get_task
from iwsim.envs.task import Task
from iwsim.eval.policy import ENVS, MAX_SEED, WORLD_MODEL, check_model_task, rollout, seed_sampling
from iwsim.experiments.common import STUDY, fingerprint
from iwsim.play.engine import episode_keys
from iwsim.policies.common import Policy
from iwsim.policies.factory import checkpoint_dir, load_policy
from iwsim.policies.scripted import ScriptedBatch
from iwsim.world_model import WorldModel
from iwsim.world_model.env import score_key

log = logging.getLogger(__name__)

PUSHT = STUDY  # the studies' default task (the yardstick reads this name: bench/yardstick.py, iwsim.yardstick.codec)
# The store's policy and source: takes in the world model, or in a task's simulator.
POLICY_NAMES = {WORLD_MODEL: "world-model-teleop", "simulator": "expert-pixels"}
SOURCES = {WORLD_MODEL: "world_model", "simulator": "mujoco"}
# Attributes that must agree before a run may append to an existing store.
# The world model and the takeover policy by their content hashes: the same files reached
# by another path (another working directory, a trailing slash, a copy) resume the store.
MATCHING_ATTRS = ("task", "policy", "image_size", "steps", "world_model_sha256", "first_seed",
                  "accept_iou", "tail_steps", "dart_noise", "start", "demonstrator",
                  "takeover_sha256", "takeover_steps", "cameras")
# What stores written before an attribute existed hold.
OLDER_ATTRS = {"dart_noise": 0.0, "start": "random", "demonstrator": "expert", "takeover": None,
               "takeover_sha256": None, "takeover_steps": None, "cameras": ["top"]}
# What a recipe may name, over every registered task (a recording checks its own task's).
ANY_STARTS = tuple(dict.fromkeys(s for make in REGISTRY.values() for s in make().starts))
EXTRA_ATTEMPTS = 4  # default max_attempts: this many candidates per wanted episode
SIM_STORE = "sim_expert.zarr"  # the simulator expert's demonstrations, under work/demos: shared by the studies
SIM_SEED = 0  # the first candidate's seed in SIM_STORE (disjoint from evaluation seeds, 100000+)


@dataclasses.dataclass(frozen=True)
class DemoRecipe:
    """How a study records demonstrations. A store's acceptance rule, horizon and tail are
    in its attributes, so a store is appended to only with the recipe that started it (the
    studies' default recipe is that of the shared ``sim_expert.zarr``)."""

    steps: int = 300  # horizon of a take
    tail: int | None = 10  # a kept take ends this many steps after success (None: whole)
    accept_iou: float = PUSHT.success_score  # a take is kept when its max pixel score reaches this (T-push: IoU)
    attempts_per_demo: float = 2.0  # at most this many candidates per demonstration wanted
    batch: int = 16  # candidates recorded in lockstep
    give_up_after: int | None = 32  # stop when this many candidates were tried and none was kept (None: never)
    dart_noise: float = 0.0  # std (m) of the noise added to the executed commands; the clean ones are recorded
    start: str = "random"  # MuJoCo's initial states (the task's starts): T-push's "goal-turned" records recoveries
    demonstrator: str = "expert"  # the pixel expert that records (the task's pixel_experts): T-push's "expert-wide"
    takeover: str | None = None  # a trained policy (checkpoint or run) that drives until the expert takes over
    takeover_steps: tuple[int, int] = (40, 200)  # the range of steps the expert takes over at (with takeover)

    def __post_init__(self) -> None:
        positive = {"demo_steps": self.steps, "demo_batch": self.batch}
        for name, v in (("demo_tail", self.tail), ("give_up_after", self.give_up_after)):
            if v is not None:
                positive[name] = v
        for name, v in positive.items():
            if not isinstance(v, int) or v < 1:
                raise InputError(f"{name} must be a positive integer, got {v!r}.")
        check_accept_iou(self.accept_iou)
        if not (isinstance(self.attempts_per_demo, (int, float)) and self.attempts_per_demo >= 1):
            raise InputError(f"attempts_per_demo must be >= 1, got {self.attempts_per_demo!r}.")
        _check_noise(self.dart_noise)
        _check_choice("start", self.start, ANY_STARTS)
        _check_choice("demonstrator", self.demonstrator, ANY_EXPERTS)
        if self.takeover is not None:
            _check_takeover(self.takeover_steps, self.steps, self.dart_noise)


@dataclasses.dataclass(frozen=True)
class DemoStats:
    """A demonstration store after a run: totals over every run that wrote it, and what
    this run added."""

    env: str
    path: str
    accept_iou: float  # a candidate is kept when its max pixel score (T-push: IoU) reaches this
    first_seed: int  # candidate i starts from seed first_seed + i
    wanted: int  # accepted episodes asked for
    episodes: int  # accepted episodes the store holds
    candidates: int  # candidates tried (all runs)
    acceptance_rate: float  # episodes / candidates (nan before any candidate)
    mean_candidate_max_iou: float  # mean over candidates of the max pixel score (nan before any)
    frames: int  # frames the store holds
    mean_length: float  # steps per kept episode
    seconds: float  # recording time (all runs)
    seconds_per_candidate: float
    added: int  # episodes this run added
    tried: int  # candidates this run tried

    @property
    def complete(self) -> bool:
        return self.episodes >= self.wanted

    def summary(self) -> str:
        return (f"{self.path}: {self.episodes}/{self.wanted} episodes kept of {self.candidates} candidates "
                f"(acceptance {100 * self.acceptance_rate:.1f}%, mean max pixel score "
                f"{self.mean_candidate_max_iou:.3f}, {self.mean_length:.0f} steps per episode, "
                f"{self.seconds_per_candidate:.1f} s per candidate); this run added {self.added} of {self.tried} tried")


def demo_attrs(env: str, steps: int, image_size: int, world_model: str | None, seed: int, accept_iou: float,
               tail: int | None, dart_noise: float = 0.0, start: str = "random",
               demonstrator: str = "expert", task: Task = PUSHT, takeover: str | None = None,
               takeover_steps: tuple[int, int] = (40, 200), cameras: tuple[str, ...] = ("top",)) -> dict[str, Any]:
    """Root attributes of a demonstration store of ``task``: ``iwsim collect``'s (the task
    spec, policy, steps, ...) plus the teleoperator, the source and the acceptance rule (and
    with ``takeover`` the policy that drives first, its fingerprint and ``takeover_steps``)."""
    where = WORLD_MODEL if env == WORLD_MODEL else "simulator"
    return {**store_attrs(task.kind, POLICY_NAMES[where], steps, image_size, cameras), "source": SOURCES[where],
            "world_model": world_model, "world_model_sha256": None if world_model is None else fingerprint(world_model),
            "teleoperator": f"{demonstrator} ({task.pixel_reading} from pixels)", "demonstrator": demonstrator,
            "keys": list(episode_keys(task)), "first_seed": seed, "accept_iou": accept_iou, "tail_steps": tail,
            "dart_noise": dart_noise, "start": start,
            "takeover": takeover,
            "takeover_sha256": None if takeover is None else fingerprint(checkpoint_dir(takeover)),
            "takeover_steps": None if takeover is None else list(takeover_steps),
            **({} if takeover is None else {"handover_steps": []}),
            "candidates_tried": 0, "candidate_max_iou": [], "acceptance_rate": None, "record_seconds": 0.0}


def record_demos(env: str, out: str | os.PathLike, episodes: int, steps: int, seed: int, *,
                 world_model: str | os.PathLike | None = None, accept_iou: float | None = None,
                 tail: int | None = 10,
                 batch: int = 16, max_attempts: int | None = None, give_up_after: int | None = None,
                 dart_noise: float = 0.0, start: str = "random", demonstrator: str = "expert",
                 takeover: str | os.PathLike | None = None, takeover_steps: tuple[int, int] = (40, 200),
                 image_size: int | None = None, progress: bool = True,
                 wait_for_lock: bool = False, model_task: Task | None = None,
                 cameras: tuple[str, ...] | None = None) -> DemoStats:
    """Record scripted demonstrations into the store ``out`` until it holds ``episodes``
    accepted ones or ``max_attempts`` candidates (default ``4 * episodes``) were tried
    (see the module docstring), or, with ``give_up_after``, until the store holds nothing
    after that many candidates: a teleoperator who has kept none of 32 takes concludes
    that the task cannot be done in this model (the acceptance rate's 95% Clopper-Pearson
    upper bound is then 11%) instead of spending the rest of the budget. ``env``: a
    built-in task's name (its MuJoCo simulator; frames of ``image_size``, None: the task's
    own) or "world-model" (needs the checkpoint ``world_model``; the task is the model's,
    which must be ``model_task`` when that is given). ``accept_iou`` None: the task's
    ``success_score``. ``dart_noise`` > 0 records as DART does (Laskey et al. 2017):
    every executed command gets Gaussian noise of that std
    (metres, per coordinate, seeded by the candidate's seed), and the store holds the
    expert's clean commands as the actions, so imitation sees how the expert recovers from
    the small errors a learned policy makes. ``start``
    chooses MuJoCo's initial states (the task's ``starts``; T-push's "goal-turned": the
    block on the goal's position but turned, so the takes show the turn a policy that only
    carries is missing; MuJoCo only). ``demonstrator``: the pixel expert that records (the
    task's ``pixel_experts``; a store holds one demonstrator's takes). ``takeover``: a
    trained policy (checkpoint or run, of the store's frame size) drives each candidate
    until a step drawn from its seed in ``takeover_steps`` (lo, hi; 0 <= lo <= hi < steps),
    then the demonstrator takes over and only its part is stored (HG-DAgger, Kelly et al.
    2019; see the module docstring): takes from the states a learned policy reaches.
    ``cameras``: MuJoCo's views to record (None: the task's first; a world model records
    its own views, and a takeover policy must see these). Returns the store's :class:`DemoStats`."""
    max_attempts = EXTRA_ATTEMPTS * episodes if max_attempts is None else max_attempts
    _check_args(env, episodes, steps, seed, world_model, accept_iou, tail, batch, max_attempts, give_up_after,
                image_size)
    _check_noise(dart_noise)
    if takeover is not None:
        _check_takeover(takeover_steps, steps, dart_noise)
    if env == WORLD_MODEL and start != "random":
        raise InputError(f"start={start!r} chooses MuJoCo's initial states; the world model starts from random ones.")
    model = None
    if env == WORLD_MODEL:
        assert world_model is not None  # _check_args checks it
        model = WorldModel.load(world_model)
        task, image_size = check_model_task(model, model_task, f"world model {world_model}"), model.image_size
        if cameras is not None and tuple(cameras) != tuple(model.cameras):
            raise InputError(f"--cameras {','.join(cameras)}: a world model records its own views, "
                             f"{','.join(model.cameras)}.")
        cameras = tuple(model.cameras)
    else:
        task = get_task(env)
        image_size = image_size or task.image_size
        _check_choice("start", start, task.starts)
        cameras = check_task_cameras(env, cameras or task.cameras[:1])
    _check_choice("demonstrator", demonstrator, task.pixel_experts)
    accept_iou = task.success_score if accept_iou is None else accept_iou
    if accept_iou is None:
        raise InputError(f"task {task.name!r} has no success score; give accept_iou.")
    assert image_size is not None  # a task with a simulator has a frame size
    policy = None if takeover is None else _takeover_policy(takeover, task, image_size)
    if policy is not None and max(len(policy.cameras), len(cameras)) > 1 and tuple(policy.cameras) != cameras:
        raise InputError(f"--takeover {takeover} sees the views {','.join(policy.cameras)}; the takes record "
                         f"{','.join(cameras)}: the policy must see the views it hands over.")
    wm_name = None if world_model is None or env != WORLD_MODEL else os.fspath(world_model)
    attrs = demo_attrs(env, steps, image_size, wm_name, seed, float(accept_iou), tail, float(dart_noise), start,
                       demonstrator, task, None if takeover is None else os.fspath(takeover), takeover_steps,
                       cameras)
    with EpisodeStore.open_or_create(Path(out), attrs, check=lambda s: _check_existing(s, attrs, task),
                                     blank=lambda s: not s.attrs.get("candidates_tried"),
                                     wait=wait_for_lock) as store:
        return _record_into(store, env, model, task, episodes, steps, seed, accept_iou, tail, batch, max_attempts,
                            give_up_after, float(dart_noise), start, demonstrator, policy, takeover_steps, progress,
                            cameras)


def _takeover_policy(path: str | os.PathLike, task: Task, image_size: int) -> Policy:
    """The trained policy at ``path``, which must act on ``task``'s frames of ``image_size``."""
    policy = load_policy(Path(path))
    if policy.task is not None and policy.task.name != task.name:
        raise InputError(f"takeover policy {os.fspath(path)} was trained on task {policy.task.name!r}, not "
                         f"{task.name!r}.")
    if policy.image_size != image_size:
        raise InputError(f"takeover policy {os.fspath(path)} was trained on {policy.image_size}x{policy.image_size} "
                         f"frames; the store holds {image_size}x{image_size} ones.")
    return policy


def handover_step(seed: int, takeover_steps: tuple[int, int]) -> int:
    """The step at which the expert takes over candidate ``seed``: uniform in
    ``takeover_steps`` (lo, hi), drawn from the seed (so a rerun hands over where it did)."""
    lo, hi = takeover_steps
    return int(np.random.default_rng([seed, 44]).integers(lo, hi + 1))


class _NoisyExecution:
    """The pixel ``demonstrator`` whose commands are executed with Gaussian noise (std
    ``noise`` m, candidate ``seeds[i]`` drawing its own), keeping the clean commands in ``clean``."""

    obs_horizon = n_action_steps = 1

    def __init__(self, noise: float, seeds: list[int], demonstrator: str, task: Task,
                 cameras: tuple[str, ...] | None = None) -> None:
        self.expert, self.noise, self.seeds, self.task = ScriptedBatch(demonstrator, task, cameras), noise, seeds, task
        self.cameras = cameras

    def reset(self) -> None:
        self.expert.reset()
        self.rngs = [np.random.default_rng([s, 25]) for s in self.seeds]
        self.clean: list[np.ndarray] = []

    def predict_action(self, obs: dict) -> np.ndarray:
        clean = self.expert.predict_action(obs)  # (B, 1, A)
        self.clean.append(clean[:, 0])
        noise = np.stack([rng.normal(0.0, self.noise, clean.shape[2]) for rng in self.rngs])[:, None]
        return np.clip(clean + noise, self.task.action_low, self.task.action_high).astype(np.float32)


class _Takeover:
    """A learned ``policy`` drives candidate ``seeds[i]`` until its :func:`handover_step`
    ``handover[i]``, the pixel ``demonstrator`` from then on, made afresh at the handover so
    its manoeuvre starts from the state the policy left. Queried every step (one action per
    call), it keeps the policy's chunks as :func:`~iwsim.eval.policy.rollout` would."""

    n_action_steps = 1

    def __init__(self, policy: Policy, seeds: list[int], takeover_steps: tuple[int, int], demonstrator: str,
                 task: Task) -> None:
        self.policy, self.demonstrator, self.task = policy, demonstrator, task
        self.cameras = policy.cameras if policy.views > 1 else None  # the views the policy and the experts see
        self.obs_horizon = policy.obs_horizon
        self.handover = np.array([handover_step(s, takeover_steps) for s in seeds])

    def reset(self) -> None:
        self.policy.reset()
        self.t = 0
        self.queue: list[np.ndarray] = []
        self.experts: list[ScriptedBatch | None] = [None] * len(self.handover)

    def predict_action(self, obs: dict) -> np.ndarray:
        """obs: image (B, To, H, W, 3) uint8, agent_pos (B, To, S) -> actions (B, 1, A)."""
        action = np.zeros((len(self.handover), self.task.action_dim), np.float32)
        if self.t < self.handover.max():  # the policy still drives some candidate
            if not self.queue:
                chunk = self.policy.predict_action(obs)
                check_finite_output(chunk, f"takeover {getattr(self.policy, 'name', 'policy')}", "its actions")
                self.queue = list(chunk.transpose(1, 0, 2))  # (B, Ta, A) -> Ta x (B, A)
            action[:] = self.queue.pop(0)
        for i in np.flatnonzero(self.handover <= self.t):
            expert = self.experts[i]
            if expert is None:
                expert = self.experts[i] = ScriptedBatch(self.demonstrator, self.task, self.cameras)
            now = {"image": obs["image"][i:i + 1, -1:], "agent_pos": obs["agent_pos"][i:i + 1, -1:]}
            action[i] = expert.predict_action(now)[0, 0]
        self.t += 1
        return action[:, None]


def record_with(env: str, out: str | os.PathLike, episodes: int, seed: int, recipe: DemoRecipe, *,
                world_model: str | os.PathLike | None = None, image_size: int | None = None,
                progress: bool = True, cameras: tuple[str, ...] | None = None) -> DemoStats:
    """:func:`record_demos` with ``recipe``: at most ``ceil(attempts_per_demo * episodes)``
    candidates, frames of ``image_size`` and views ``cameras`` (MuJoCo only, None: the
    task's; a world model renders its own)."""
    return record_demos(env, out, episodes, recipe.steps, seed, world_model=world_model, image_size=image_size,
                        accept_iou=recipe.accept_iou,
                        tail=recipe.tail, batch=recipe.batch,
                        max_attempts=math.ceil(recipe.attempts_per_demo * episodes),
                        give_up_after=recipe.give_up_after, dart_noise=recipe.dart_noise, start=recipe.start,
                        demonstrator=recipe.demonstrator, takeover=recipe.takeover,
                        takeover_steps=recipe.takeover_steps, progress=progress, cameras=cameras)


def simulator_store(work: str | os.PathLike, demonstrator: str = "expert",
                    cameras: tuple[str, ...] = ("top",)) -> Path:
    """The simulator expert's demonstration store of a work directory (shared by the
    studies); another ``demonstrator``'s takes go beside it (``sim_expert-wide.zarr``), and
    so do takes seen by several ``cameras`` (``sim_expert_top_side.zarr``: the same
    candidates, every view recorded)."""
    name = SIM_STORE if demonstrator == "expert" else f"sim_{demonstrator}.zarr"
    if len(cameras) > 1:
        name = name.replace(".zarr", "_" + "_".join(cameras) + ".zarr")
    return Path(work) / "demos" / name


def simulator_demos(work: str | os.PathLike, episodes: int, recipe: DemoRecipe,
                    progress: bool = True, task: Task = PUSHT,
                    cameras: tuple[str, ...] = ("top",)) -> tuple[Path, DemoStats]:
    """Record (or resume) the simulator expert's demonstrations of ``task`` in
    :func:`simulator_store` until it holds ``episodes`` (or the recipe's attempts are
    spent), candidates from seed :data:`SIM_SEED`, seen by MuJoCo's ``cameras`` (a study's:
    its world model's views). Returns the store's path and its :class:`DemoStats`."""
    path = simulator_store(work, recipe.demonstrator, cameras)
    several = tuple(cameras) if len(cameras) > 1 else None  # one view: the task's own camera, as ever
    return path, record_with(task.kind, path, episodes, SIM_SEED, recipe, progress=progress, cameras=several)


def _record_into(store: EpisodeStore, env: str, model: WorldModel | None, task: Task, episodes: int, steps: int,
                 seed: int,
                 accept_iou: float, tail: int | None, batch: int, max_attempts: int, give_up_after: int | None,
                 dart_noise: float, start: str, demonstrator: str, takeover: Policy | None,
                 takeover_steps: tuple[int, int], progress: bool, cameras: tuple[str, ...]) -> DemoStats:
    a = store.attrs
    # The candidates whose scores the store records. A run killed between an append and the
    # attribute update below kept takes of candidates it did not record: those are tried
    # again (deterministic, so they score as before), counted and scored, not appended twice.
    tried = min(int(a["candidates_tried"]), len(a["candidate_max_iou"]))
    max_ious = list(a["candidate_max_iou"])[:tried]
    kept_seeds = {s for s in a["seeds"] if s is not None}
    last_kept = max((s - seed + 1 for s in kept_seeds), default=0)
    seconds = float(a["record_seconds"])
    tried0, kept0 = tried, store.n_episodes
    if store.n_episodes < episodes and tried < max_attempts:
        log.info("recording %s demonstrations into %s: %d of %d kept, candidates from seed %d (of at most %d)",
                 env, store.path, store.n_episodes, episodes, seed + tried, max_attempts)
    bar = tqdm(total=episodes, initial=min(store.n_episodes, episodes), unit="ep", desc=f"demos {store.path.name}",
               disable=not progress)
    while (store.n_episodes < episodes and tried < max_attempts) or tried < last_kept:
        if give_up_after is not None and store.n_episodes == 0 and tried >= give_up_after:
            log.warning("%s: none of %d candidates reached pixel %s %g; giving up", store.path, tried,
                        task.score_name, accept_iou)
            break
        # enough candidates for the episodes still missing at the rate so far (Laplace's rule)
        kept = sum(s - seed < tried for s in kept_seeds)  # of the candidates tried
        rate = (kept + 1) / (tried + 2)
        n = min(batch, max_attempts - tried, math.ceil((episodes - kept) / rate))
        if tried < last_kept:  # candidates kept but not recorded come first
            n = max(n, min(batch, last_kept - tried))
        seeds = [seed + tried + i for i in range(n)]
        t0 = time.perf_counter()
        expert: ScriptedBatch | _NoisyExecution | _Takeover
        views = cameras if len(cameras) > 1 else None  # every view is recorded
        if takeover is not None:
            expert = _Takeover(takeover, seeds, takeover_steps, demonstrator, task)
            seed_sampling(seeds)  # the policy's sampling noise: a rerun records the same takes
        elif dart_noise:
            expert = _NoisyExecution(dart_noise, seeds, demonstrator, task, views)
        else:
            expert = ScriptedBatch(demonstrator, task, views)
        handover = expert.handover if isinstance(expert, _Takeover) else np.zeros(n, int)
        scores = _Scores(task, handover, accept_iou, tail)
        run = rollout(expert, env, seeds, steps, world_model=model,
                      image_size=store.attrs["image_size"], record=n, progress=progress, stop=scores, start=start)
        if isinstance(expert, _NoisyExecution):  # dart_noise
            run["action"] = np.stack(expert.clean, 1)  # the labels: what the expert meant
        ious = np.stack([_pixel_score(task, run["frames"][:, 0, ..., :3]), *scores.ious], 1).astype(np.float32)
        for i, s in enumerate(seeds):
            tried += 1
            take = ious[i, handover[i]:]  # the expert's part; a take that starts solved shows nothing
            max_ious.append(round(float(take.max()), 4))
            if take.max() >= accept_iou and (takeover is None or take[0] < accept_iou):
                if s not in kept_seeds:
                    store.append(_episode(run, ious, i, accept_iou, tail, score_key(task), handover[i],
                                          views or ("top",)), seed=s)
                    kept_seeds.add(s)
                    bar.update()
                if store.n_episodes >= episodes and tried >= last_kept:
                    break
        seconds += time.perf_counter() - t0
        handovers = {} if takeover is None else {
            "handover_steps": [handover_step(s, takeover_steps) for s in store.seeds if s is not None]}
        store.update_attrs({"candidates_tried": tried, "candidate_max_iou": max_ious, "record_seconds": seconds,
                            "acceptance_rate": store.n_episodes / tried, **handovers})
        bar.set_postfix_str(f"{tried} tried, {100 * store.n_episodes / tried:.0f}% kept")
    bar.close()
    lengths = np.diff(store.episode_ends, prepend=0)
    stats = DemoStats(
        env=env, path=str(store.path), accept_iou=accept_iou, first_seed=seed, wanted=episodes,
        episodes=store.n_episodes, candidates=tried,
        acceptance_rate=store.n_episodes / tried if tried else float("nan"),
        mean_candidate_max_iou=float(np.mean(max_ious)) if max_ious else float("nan"),
        frames=store.n_frames, mean_length=float(lengths.mean()) if len(lengths) else float("nan"),
        seconds=seconds, seconds_per_candidate=seconds / tried if tried else float("nan"),
        added=store.n_episodes - kept0, tried=tried - tried0)
    log.info("%s", stats.summary())
    if not stats.complete:
        log.warning("%s holds %d of the %d demonstrations asked for: %d candidates tried (the most allowed is %d), "
                    "%.1f%% reached pixel %s %g", store.path, stats.episodes, episodes, tried, max_attempts,
                    100 * stats.acceptance_rate, task.score_name, accept_iou)
    return stats


def _pixel_score(task: Task, frames: np.ndarray) -> np.ndarray:
    """The task's pixel score (B,) of frames (B, H, W, 3) (a task with a simulator has a scorer)."""
    scores = task.score(frames)
    assert scores is not None
    return scores


class _Scores:
    """The rollout's ``stop``: scores each step's frames (``task``'s pixel score) and ends the
    batch once every episode has run ``tail`` steps past its first frame from its ``handover``
    step on that reaches ``accept_iou`` (no episode of the batch would record more; never
    with ``tail=None``)."""

    def __init__(self, task: Task, handover: np.ndarray, accept_iou: float, tail: int | None) -> None:
        self.task, self.handover, self.accept_iou, self.tail = task, handover, accept_iou, tail
        self.ious: list[np.ndarray] = []  # (n,) per step, from step 1
        self.first = np.full(len(handover), np.inf)  # first step from the handover whose frame reached accept_iou

    def __call__(self, obs: dict[str, np.ndarray]) -> bool:
        self.ious.append(np.atleast_1d(_pixel_score(self.task, first_view(obs["pixels"]))))  # the scorer's view
        t = len(self.ious)
        reached = (self.ious[-1] >= self.accept_iou) & (t >= self.handover)
        self.first = np.where(np.isinf(self.first) & reached, t, self.first)
        return self.tail is not None and bool(np.all(self.first + self.tail <= t))


def _episode(run: dict[str, Any], ious: np.ndarray, i: int, accept_iou: float, tail: int | None,
             key: str, handover: int = 0, cameras: tuple[str, ...] = ("top",)) -> dict[str, np.ndarray]:
    """Episode ``i`` of a rollout in the store's layout (its pixel scores ``ious`` under
    ``key``) from step ``handover``, cut ``tail`` steps after its first frame from there
    scoring >= ``accept_iou`` (to the end with ``tail=None``)."""
    first = handover + int(np.argmax(ious[i, handover:] >= accept_iou))
    steps = run["action"].shape[1]  # the steps run (a batch stops once no episode needs more)
    t = steps if tail is None else min(first + tail, steps)
    frames = run["frames"][i, handover:t]
    views = unstack_views(frames, frames.shape[-1] // 3)  # several views: img, then img_<camera> (their order)
    return {**dict(zip([IMAGE_KEY, *(f"{VIEW_PREFIX}{c}" for c in cameras[1:])], views, strict=True)),
            "state": run["agent_pos"][i, handover:t].astype(np.float32),
            "action": run["action"][i, handover:t].astype(np.float32),
            "target": run["target"][i, handover:t].astype(np.float32), key: ious[i, handover:t]}


def check_accept_iou(value: Any) -> None:
    """A take's acceptance score is a task's score, in [0, 1] (T-push's IoU, the pile's share
    in the tray): above 1 no take is ever kept, and the whole budget is spent for nothing."""
    if not (isinstance(value, (int, float)) and math.isfinite(value) and 0 <= value <= 1):
        raise InputError(f"accept_iou must be a score in [0, 1], got {value!r}.")


def _check_args(env: str, episodes: int, steps: int, seed: int, world_model: Any, accept_iou: float | None,
                tail: int | None, batch: int, max_attempts: int, give_up_after: int | None,
                image_size: int | None) -> None:
    if env not in ENVS:
        raise InputError(f"unknown environment {env!r}; expected one of {', '.join(ENVS)}.")
    if env == WORLD_MODEL and world_model is None:
        raise InputError("demonstrations in the world model need a world-model checkpoint.")
    for name, value in (("episodes", episodes), ("steps", steps), ("batch", batch), ("max_attempts", max_attempts)):
        if not isinstance(value, int) or value < 1:
            raise InputError(f"{name} must be a positive integer, got {value!r}.")
    if tail is not None and (not isinstance(tail, int) or tail < 1):
        raise InputError(f"tail must be a positive number of steps or None (whole episodes), got {tail!r}.")
    if give_up_after is not None and (not isinstance(give_up_after, int) or give_up_after < 1):
        raise InputError(f"give_up_after must be a positive integer or None (never), got {give_up_after!r}.")
    if accept_iou is not None:
        check_accept_iou(accept_iou)
    if not isinstance(seed, int) or not 0 <= seed <= MAX_SEED - max_attempts + 1:
        raise InputError(f"seed must be in 0..{MAX_SEED - max_attempts + 1} for {max_attempts} candidates, "
                         f"got {seed!r}.")
    if env != WORLD_MODEL and image_size is not None and image_size not in IMAGE_SIZES:
        raise InputError(f"image size must be one of {list(IMAGE_SIZES)}, got {image_size!r}.")


def _check_noise(noise: float) -> None:
    if not (isinstance(noise, (int, float)) and math.isfinite(noise) and noise >= 0):
        raise InputError(f"dart_noise must be a finite number of metres >= 0, got {noise!r}.")


def _check_takeover(takeover_steps: Any, steps: int, dart_noise: float) -> None:
    lo, hi = takeover_steps if isinstance(takeover_steps, (tuple, list)) and len(takeover_steps) == 2 else (None, None)
    if not (isinstance(lo, int) and isinstance(hi, int) and 0 <= lo <= hi < steps):
        raise InputError(f"takeover_steps must be two steps lo, hi with 0 <= lo <= hi < steps ({steps}), "
                         f"got {takeover_steps!r}.")
    if dart_noise:
        raise InputError(f"takeover does not combine with dart_noise; got dart_noise={dart_noise!r}, expected 0.")


def _check_choice(name: str, value: str, choices: tuple[str, ...]) -> None:
    if value not in choices:
        raise InputError(f"{name} must be one of {', '.join(choices)}, got {value!r}.")


def _check_existing(store: EpisodeStore, attrs: dict[str, Any], task: Task) -> None:
    """Raise unless this run may append to ``store`` (the same demonstrations)."""
    stored, keys = {**OLDER_ATTRS, **store.attrs}, []
    for key in MATCHING_ATTRS:
        if key.endswith("_sha256") and stored.get(key) != attrs[key]:
            keys.append(key.removesuffix("_sha256"))  # a model or policy of other content is named by its path too
        keys.append(key)
    mismatch = attrs_mismatch(store, attrs, keys, absent=OLDER_ATTRS)
    if mismatch:
        raise InputError(f"{store.path} holds demonstrations with {mismatch}; choose another store.")
    arrays = (*episode_keys(task), *list(view_keys(tuple(attrs["cameras"])).values())[1:])
    if store.n_episodes and set(store.keys) != set(arrays):
        raise InputError(f"{store.path} holds arrays {store.keys}, not the recorded {sorted(arrays)}; "
                         "choose another store.")
