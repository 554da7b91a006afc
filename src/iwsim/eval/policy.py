"""Closed-loop evaluation of a policy in a task's MuJoCo simulator or inside the world model
(``iwsim eval policy``).

Episode i starts from MuJoCo seed ``seed + i`` in both environments: the world model
starts from MuJoCo's rendering of that seed's initial state (a world model of another
robot's task starts from the first frame of its dataset's episode ``(seed + i) %
episodes``, and without a pixel scorer its episodes report no score). All episodes step together:
inside the world model that is one batched forward pass per step; in MuJoCo the
environments step one after another (Gymnasium's ``SyncVectorEnv``). The score of an episode
is the maximum of the task's pixel score it reaches (T-push's: the IoU, the paper's
T-pushing score; pile sweeping's: the share of the pieces in the tray), success is a score
at or above the task's ``success_score`` (0.9 for both); the success rate comes with a Beta
posterior (uniform prior) and a Clopper-Pearson interval. The results name the score as
the world model's ``info`` does (:func:`iwsim.world_model.env.score_key`): T-push's
``max_iou``, ``mean_max_iou`` and ``iou.json``, as ever; another task's ``max_score``,
``mean_max_score`` and ``score.json``.

A policy of several camera views (``policy.cameras``) runs in MuJoCo rendering those
cameras, and in a world model of the same views only; each step's ``pixels``, {camera:
frame}, are stacked along the channels in the policy's order. Its videos show the views one
above the other.
"""

from __future__ import annotations

import json
import time
from collections import deque
from collections.abc import Callable, Iterator, Mapping
from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np
import torch
from gymnasium import spaces
from gymnasium.vector import SyncVectorEnv, VectorEnv
from tqdm import tqdm

from iwsim.core.checkpoint import check_finite_output, check_output_dir, write_json_atomic
from iwsim.core.errors import InputError
from iwsim.core.resources import require_memory
from iwsim.data.views import first_view, stack_views, tile_views
from iwsim.envs import SMALLEST_FRAME_BYTES
from iwsim.envs.collect import Recorder
from iwsim.envs.registry import DEFAULT_TASK, REGISTRY, get_task, task_of
from iwsim.envs.task import Task
from iwsim.eval.paired import paired_estimate, paired_rate
from iwsim.eval.stats import beta_posterior, clopper_pearson
from iwsim.eval.trust import PLAUSIBILITY_EVERY, SAMPLE_OFFSET, episode_signals
from iwsim.eval.trust import summary as trust_summary
from iwsim.eval.video import upscale, write_video
from iwsim.policies.common import PolicyLike
from iwsim.world_model.env import WorldModelVectorEnv, score_key

WORLD_MODEL = "world-model"
MUJOCO = "mujoco"  # iwsim eval policy --env: the task's simulator
# Where policies are evaluated: each built-in task's simulator (by the task's name), the world model.
ENVS = (*(kind for kind, make in REGISTRY.items() if make().has_ground_truth), WORLD_MODEL)
# An episode whose mean novelty is above this strays from the training data (about 1 for
# steps like the training data's). An out-of-distribution flag, not a trust score: it does
# not rank the episodes by their error (bench/results/ablations.md).
NOVELTY_WARN = 2.0
# An episode whose score differs by more than this between two world models (the ensemble
# trust signal, :func:`disagreement`) is one the models cannot vouch for.
DISAGREE_WARN = 0.2


def make_vector_env(env: str, n: int, steps: int, *, world_model: Any = None, image_size: int | None = None,
                    start: str = "random", cameras: tuple[str, ...] | None = None
                    ) -> SyncVectorEnv | WorldModelVectorEnv:
    """``n`` environments in lockstep as a Gymnasium vector env: task ``env``'s simulator
    in a :class:`~gymnasium.vector.SyncVectorEnv` (its initial states from the distribution
    ``start``, one of the task's ``starts``), or for ``env="world-model"`` the world model's
    batched :class:`~iwsim.world_model.env.WorldModelVectorEnv` (one forward pass per step).
    ``image_size``: the policy's frame size, which the environment must render (None: the
    environment's own, the task's frame size in MuJoCo, the world model's). ``cameras``: the
    views the policy sees; with several, MuJoCo renders them and a world model must be a
    model of them (None or one view: the environment's one view)."""
    several: tuple[str, ...] | None = tuple(cameras) if cameras is not None and len(cameras) > 1 else None
    if env not in ENVS:
        raise InputError(f"unknown environment {env!r}; expected one of {', '.join(ENVS)}.")
    if env != WORLD_MODEL:
        task = get_task(env)

        def simulator() -> gym.Env:  # (a start the task has not fails as the first one is made)
            sim = task.ground_truth_env(image_size, start) if several is None else \
                task.ground_truth_env(image_size, start, cameras=several)
            assert sim is not None  # ENVS names the tasks with a simulator
            return sim

        return SyncVectorEnv([simulator] * n)
    if start != "random":
        raise InputError(f"the world model starts from MuJoCo's random initial states only, not start={start!r}.")
    if world_model is None:
        raise InputError("evaluating inside the world model needs --world-model CHECKPOINT.")
    own = tuple(getattr(world_model, "cameras", ("top",)))
    if cameras is not None and (several is not None or len(own) > 1) and own != tuple(cameras):
        raise InputError(f"the policy sees the camera views {', '.join(cameras)}; the world model sees "
                         f"{', '.join(own)}: evaluate it in a world model of the policy's views.")
    if image_size is not None and world_model.image_size != image_size:
        raise InputError(f"the policy was trained on {image_size}x{image_size} frames; the world model "
                         f"renders {world_model.image_size}x{world_model.image_size}.")
    # the task's own starts: for a task with a simulator its rendering of each seed, for
    # another robot's task the first frame of its dataset's episode seed % episodes
    return WorldModelVectorEnv(n, model=world_model, max_episode_steps=steps + 1)


def choose_task(env: str, task: str | None, recorded: Task | None) -> tuple[str, Task | None]:
    """Where ``iwsim eval policy`` evaluates, and on which task, from its flags: ``env``
    ("mujoco"; a built-in task's name, the same for that task; or "world-model"), ``task``
    (--task, a built-in task's name) and the task the policy's checkpoint records
    (``recorded``; None for a policy trained before policies recorded one). Returns the
    environment of :func:`evaluate` (a task's name, or "world-model") and the task (in
    MuJoCo T-push when nothing names one; in the world model None: the model's own). A
    built-in task other than the one the policy was trained on, or a task without a
    simulator in MuJoCo, is one line of error."""
    named = None if task is None else get_task(task)
    if env not in (MUJOCO, WORLD_MODEL):  # a task's name: its simulator
        by_env = get_task(env)
        if named is not None and named.name != by_env.name:
            raise InputError(f"--env {env} is the simulator of task {env!r}, not of --task {task}; use --env {MUJOCO}.")
        named, env = by_env, MUJOCO
    if named is not None and recorded is not None and recorded.kind in REGISTRY and recorded.name != named.name:
        raise InputError(f"the policy was trained on episodes of task {recorded.name!r} (its checkpoint records it), "
                         f"not {named.name!r}; evaluate it on {recorded.name!r}.")
    chosen = named or recorded
    if env == WORLD_MODEL:
        return env, chosen
    chosen = chosen or DEFAULT_TASK()
    if not chosen.has_ground_truth:
        raise InputError(f"task {chosen.name!r} has no simulator to evaluate in; evaluate inside its world model "
                         f"(--env {WORLD_MODEL} --world-model CHECKPOINT), or name a built-in task with --task.")
    return chosen.kind, chosen


def check_model_task(model: Any, task: Task | None, what: str) -> Task:
    """The task of the world model ``model`` (``what`` names it in the error), which must be
    ``task`` when one is given: a policy of one task is not evaluated in a model of another."""
    own = task_of(model)
    if task is not None and own.name != task.name:
        raise InputError(f"{what} is a world model of task {own.name!r}, not {task.name!r}; give a world model of "
                         f"{task.name!r}.")
    return own


def env_task(venv: VectorEnv, env: str) -> Task:
    """The task of an environment of :func:`make_vector_env`."""
    return venv.task if isinstance(venv, WorldModelVectorEnv) else get_task(env)


def policy_frames(pixels: Any, cameras: tuple[str, ...] | None, name: str = "the policy") -> np.ndarray:
    """An observation's ``pixels`` (a frame, or {camera: frame}) as the policy named ``name``
    sees them: one view the frame itself, several stacked along the channels in the order of
    its ``cameras`` (:func:`~iwsim.data.views.stack_views`). A policy without cameras (a
    scripted one) sees the first view, as the task's pixel scorer."""
    if cameras is None:
        return first_view(pixels)
    if isinstance(pixels, Mapping):
        have = tuple(pixels)
        if len(cameras) == 1 or not set(cameras) <= set(have):
            raise InputError(f"{name} sees the camera view(s) {', '.join(cameras)}; the environment gives the views "
                             f"{', '.join(have)}.")
        return stack_views([np.asarray(pixels[c]) for c in cameras])
    if len(cameras) > 1:
        raise InputError(f"{name} sees the camera views {', '.join(cameras)}; the environment gives one view.")
    return pixels


def rollout(policy: PolicyLike, env: str, seeds: list[int], steps: int, *, world_model: Any = None,
            image_size: int | None = None, record: int = 0, progress: bool = True,
            stop: Callable[[dict[str, np.ndarray]], bool] | None = None, start: str = "random",
            keep: tuple[str, ...] = (), plausibility_every: int = 0, noise_offset: int = 0) -> dict[str, Any]:
    """Run ``policy`` for ``steps`` steps from each seed, all episodes together in ``env``
    (a built-in task's simulator, by the task's name, or "world-model"). Returns the task's
    per-step pixel score ``iou`` (E, T + 1) (whatever the task's score is, T-push's IoU or
    pile sweeping's share in the tray; None when the task has no scorer; its name in
    ``scorer``, the task's name in ``task``), ``agent_pos`` (E, T + 1, A) (a tabletop's: the
    pushers' positions), the commanded ``action`` and executed ``target`` (info["target"],
    for T-push the speed-limited setpoints) of every step (E, T, A) and the frames
    ``frames`` (E', T + 1, H, W, 3V) of the first ``record`` episodes, as the policy sees
    them (:func:`policy_frames`: its V camera views stacked along the channels); step t's action
    follows frame t. T = ``steps``, or fewer when ``stop(obs)``, called with each step's
    new observations, returns True. ``image_size`` (the policy's frames) and ``start``
    (MuJoCo's initial-state distribution): as in :func:`make_vector_env`. ``novelty`` (E, T):
    in a world model with a trust signal, how unlike its training data each step's inputs
    are (:mod:`iwsim.world_model.novelty`), else None.
    ``info``: the environment's per-step info arrays named in ``keep`` (E, T + 1, ...), from the reset on.
    ``plausibility`` (E, K): with ``plausibility_every`` > 0, the task's
    :meth:`~iwsim.envs.task.Task.plausibility` of every such step's frames from the first
    on, else (or for a task that cannot tell) None. ``command_lead`` (E, T): in a world
    model, how far each command runs ahead of the robot the policy saw
    (:meth:`~iwsim.envs.task.Task.command_lead`), else (or for a task that cannot tell) None.
    ``noise_offset``: in a world model, another sample of the same episodes (the model's
    noise seeds shifted by it)."""
    if noise_offset and env != WORLD_MODEL:
        raise InputError("another sample (noise_offset) applies to a world model; MuJoCo has one outcome.")
    cameras = getattr(policy, "cameras", None)  # a learned policy's views (a scripted one has none)
    venv = make_vector_env(env, len(seeds), steps, world_model=world_model, image_size=image_size, start=start,
                           cameras=cameras)
    task = env_task(venv, env)
    key = score_key(task)
    want = {"action": getattr(policy, "action_dim", task.action_dim), "state": getattr(policy, "state_dim", None)}
    space = venv.single_observation_space
    assert isinstance(space, spaces.Dict) and isinstance(space["agent_pos"], spaces.Box)  # see Task.spaces
    have = {"action": task.action_dim, "state": space["agent_pos"].shape[0]}
    for what in ("action", "state"):
        if want[what] is not None and want[what] != have[what]:
            venv.close()
            raise InputError(f"the policy takes {want[what]}-D {what}s; task {task.name!r} in {env} has "
                             f"{have[what]}-D ones.")
    try:
        name = getattr(policy, "name", "the policy")

        def seen(o: dict[str, Any]) -> dict[str, Any]:  # what the policy observes of o
            return {"pixels": policy_frames(o["pixels"], cameras, name), "agent_pos": o["agent_pos"]}

        raw, info = venv.reset(seed=list(seeds), options={"noise_offset": noise_offset} if noise_offset else None)
        obs = seen(raw)
        iou = info[key]
        plausible: list[np.ndarray] = []
        first = task.plausibility(first_view(raw["pixels"])) if plausibility_every > 0 else None
        judge = first is not None
        if first is not None:
            plausible.append(first)
        history: deque[dict[str, np.ndarray]] = deque([obs] * policy.obs_horizon, maxlen=policy.obs_horizon)
        ious, frames, positions, actions, targets = [iou], [obs["pixels"][:record]], [obs["agent_pos"]], [], []
        kept = {k: [info[k]] for k in keep}
        novelty: list[np.ndarray] = []
        policy.reset()
        queue: list[np.ndarray] = []
        bar = tqdm(total=steps, desc=f"eval in {env}", unit="step", disable=not progress)
        t0 = time.perf_counter()
        for _ in range(steps):
            if not queue:
                stacked = {"image": np.stack([h["pixels"] for h in history], 1),
                           "agent_pos": np.stack([h["agent_pos"] for h in history], 1)}
                chunk = policy.predict_action(stacked)  # (E, Ta, A)
                check_finite_output(chunk, getattr(policy, "name", "the policy"), "its actions")
                queue = list(chunk.transpose(1, 0, 2))
            actions.append(queue.pop(0).astype(np.float32))
            raw, _, _, _, info = venv.step(actions[-1])
            obs = seen(raw)
            history.append(obs)
            ious.append(info[key])
            frames.append(obs["pixels"][:record])
            positions.append(obs["agent_pos"])
            targets.append(info["target"])
            for k in keep:
                kept[k].append(info[k])
            if "novelty" in info:
                novelty.append(info["novelty"])
            if (judge and len(actions) % plausibility_every == 0
                    and (p := task.plausibility(first_view(raw["pixels"]))) is not None):
                plausible.append(p)
            bar.update()
            if stop is not None and stop(raw):
                break
        bar.close()
        seconds = time.perf_counter() - t0
    finally:
        venv.close()
    # each command against the pushers the policy saw when it gave it
    lead = task.command_lead(np.stack(actions, 1), np.stack(positions[:-1], 1)) \
        if env == WORLD_MODEL and actions else None
    return {"iou": None if task.score_name is None else np.stack(ious, 1), "scorer": task.score_name,
            "score_key": key, "task": task.name, "success_score": task.success_score,
            "frames": np.stack(frames, 1) if record else None,
            "agent_pos": np.stack(positions, 1), "action": np.stack(actions, 1), "target": np.stack(targets, 1),
            "novelty": np.stack(novelty, 1) if novelty else None,
            "plausibility": np.stack(plausible, 1) if plausible else None, "command_lead": lead,
            "info": {k: np.stack(v, 1) for k, v in kept.items()},
            "seconds": seconds}


RECORD_BATCH = 16  # episodes a learned policy records in lockstep (one batched forward pass per query)


def seed_sampling(seeds: list[int]) -> None:
    """Seed a learned policy's sampling noise (torch's global generator) for the batch of
    episodes ``seeds`` from its first seed, so the same batch records the same episodes."""
    torch.manual_seed(seeds[0])


def recorder(policy: PolicyLike, task: str, steps: int, *, image_size: int | None = None,
             batch: int = RECORD_BATCH) -> Recorder:
    """``policy``'s episodes in MuJoCo, as :func:`iwsim.envs.collect.collect` records them
    (``iwsim collect --policy RUN``): the seeds ``batch`` at a time in lockstep, each batch's
    sampling noise seeded by its first seed: the same command records the same store, and a
    store extended in whole batches holds the episodes one recorded at once holds.
    Step t holds the observation before action t, as a scripted episode does
    (:func:`iwsim.envs.pusht.scripted.record_episode`). Frames of ``image_size`` (None: the task's size)."""

    kind = get_task(task)  # its episodes' own arrays: the objects' state, contacts, the score
    keep, score = (*kind.state_keys, "n_contacts"), kind.episode_score or "score"

    def record(seeds: list[int]) -> Iterator[dict[str, np.ndarray]]:
        for i in range(0, len(seeds), batch):
            chunk = seeds[i:i + batch]
            seed_sampling(chunk)
            run = rollout(policy, task, chunk, steps, image_size=image_size, record=len(chunk), progress=False,
                          keep=keep)
            for e in range(len(chunk)):
                # the first view, the one a store of a learned policy's episodes holds (iwsim collect)
                yield {"img": run["frames"][e, :steps, ..., :3],
                       "state": run["agent_pos"][e, :steps].astype(np.float32),
                       "action": run["action"][e], "target": run["target"][e].astype(np.float32),
                       score: run["iou"][e, :steps].astype(np.float32),
                       **{k: v[e, :steps] for k, v in run["info"].items()}}

    return record


def summarize(max_score: np.ndarray, seeds: list[int], success_score: float, key: str = "iou") -> dict[str, Any]:
    """Per-episode scores and the statistics over episodes, the score named ``key`` (the
    task's :func:`~iwsim.world_model.env.score_key`: ``max_iou``, ``mean_max_iou``, ... for T-push)."""
    success = max_score >= success_score
    k, n = int(success.sum()), len(success)
    return {
        "episodes": [{"seed": s, f"max_{key}": float(m), "success": bool(ok)}
                     for s, m, ok in zip(seeds, max_score, success)],
        f"mean_max_{key}": float(max_score.mean()),
        f"std_max_{key}": float(max_score.std()),
        "success_rate": k / n,
        "success_beta_posterior": beta_posterior(k, n),
        "success_clopper_pearson": list(clopper_pearson(k, n)),
    }


def trust(run: dict[str, Any], sample_max_scores: list[np.ndarray] | None = None) -> dict[str, Any]:
    """The trust signals of a world-model evaluation (:mod:`iwsim.eval.trust`) from a
    :func:`rollout` (and the max scores of its other samples, :func:`sampled_rollout`):
    per signal each episode's value, their mean and the share of episodes above its warning
    level (``novelty``'s :data:`NOVELTY_WARN`); nothing for MuJoCo."""
    out = trust_summary(episode_signals(run["plausibility"], sample_max_scores, run.get("command_lead")))
    if run["novelty"] is not None:
        per_episode = run["novelty"].mean(1)
        out["novelty"] = {"per_episode": np.round(per_episode, 3).tolist(), "mean": float(per_episode.mean()),
                          "above_warn": float((per_episode > NOVELTY_WARN).mean()), "warn": NOVELTY_WARN}
    return out


def check_samples(samples: int, env: str) -> None:
    """One line unless ``samples`` (of the model per first state) can run in ``env``."""
    if samples < 1:
        raise InputError(f"--samples must be >= 1, got {samples}.")
    if samples > 1 and env != WORLD_MODEL:
        raise InputError("--samples applies to --env world-model (MuJoCo has one outcome per first state).")


def sampled_rollout(policy: PolicyLike, env: str, seeds: list[int], steps: int, *, samples: int = 1,
                    **kwargs: Any) -> tuple[dict[str, Any], list[np.ndarray] | None]:
    """:func:`rollout` (its frames' plausibility measured in a world model), and with
    ``samples`` > 1 the max scores (E,) of that many samples of the world model (the first
    this rollout's, the others the same episodes with other noise); else None."""
    check_samples(samples, env)
    every = PLAUSIBILITY_EVERY if env == WORLD_MODEL else 0
    run = rollout(policy, env, seeds, steps, plausibility_every=every, **kwargs)
    if samples == 1 or run["iou"] is None:
        return run, None
    kwargs = {**kwargs, "record": 0}
    others = [rollout(policy, env, seeds, steps, noise_offset=k * SAMPLE_OFFSET, **kwargs)["iou"].max(1)
              for k in range(1, samples)]
    return run, [run["iou"].max(1), *others]


def no_score(seeds: list[int], key: str = "score") -> dict[str, Any]:
    """The scores of episodes of a task without a scorer: none, said as such (never a fake number)."""
    return {"episodes": [{"seed": s} for s in seeds], f"mean_max_{key}": None, f"std_max_{key}": None,
            "success_rate": None, "note": "no scorer: the task has no pixel scorer, so episodes have no score."}


MAX_SEED = 2**32 - 1  # numpy's SeedSequence, behind gymnasium's reset(seed=), takes 32-bit seeds here


MUJOCO_ENV_BYTES = 38 << 20  # one MuJoCo environment with its renderer (measured: 38 MB at 64 px)
STEP_RECORD_BYTES = 64  # what evaluation keeps of each step of an episode (score, positions, actions)


def check_args(episodes: int, seed: int, steps: int, videos: int, env: str = "world-model") -> None:
    """Raise ValueError for evaluation flags that cannot work (before anything is loaded),
    and a ResourceError for episodes (run together) or videos that cannot fit in memory: a
    lower bound of an environment each (a simulator's, unless ``env`` is the world model),
    two observed frames (uint8 and the policy's float copy) and a record of every step,
    counted at the smallest frame size."""
    for name, v in (("episodes", episodes), ("steps", steps)):
        if v < 1:
            raise InputError(f"--{name} must be a positive integer, got {v}.")
    if videos < 0:
        raise InputError(f"--videos must be 0 or more, got {videos}.")
    if not 0 <= seed <= MAX_SEED - episodes + 1:  # episode i uses the MuJoCo seed seed + i
        raise InputError(f"--seed must be in 0..{MAX_SEED - episodes + 1} for {episodes} episodes (MuJoCo seeds "
                         f"are 0..2**32-1), got {seed}.")
    frame = SMALLEST_FRAME_BYTES
    kept = steps * min(videos, episodes)
    require_memory(kept * frame, f"--steps {steps} with --videos {videos} (at least {kept} frames in memory)")
    per_episode = (0 if env == "world-model" else MUJOCO_ENV_BYTES) + 2 * frame * 5 + steps * STEP_RECORD_BYTES
    require_memory(episodes * per_episode, f"--episodes {episodes} of {steps} steps in {env}, run together")


def disagreement(scores: np.ndarray, partner_scores: np.ndarray) -> dict[str, Any]:
    """The ensemble trust signal: each episode's |score - the partner model's score| (E,)
    for the same policy from the same first state, their mean, and the share of episodes
    above :data:`DISAGREE_WARN`. Two world models trained differently agree where the data
    pins the outcome down and part where it does not (measured on the yardstick:
    :mod:`iwsim.yardstick.families`)."""
    gap = np.abs(np.asarray(scores, np.float64) - np.asarray(partner_scores, np.float64))
    return {"per_episode": np.round(gap, 4).tolist(), "mean": float(gap.mean()),
            "above_warn": float((gap > DISAGREE_WARN).mean()), "warn": DISAGREE_WARN}


def check_paired(real: dict[str, Any], task: Task, seeds: list[int], steps: int, policy_sha256: str,
                 n_action_steps: int | None, where: str) -> None:
    """One line unless ``real`` (a ``results.json`` of :func:`evaluate`, read from ``where``)
    is the same policy (by its weights' hash, and executed alike) in ``task``'s simulator
    over ``steps`` steps, from at least 2 of ``seeds``: the pairs of a paired estimate."""
    if not isinstance(real, dict) or not isinstance(real.get("episodes"), list):
        raise InputError(f"--paired {where} is not the results.json of iwsim eval policy.")
    if real.get("env") != task.kind or real.get("task") != task.name:
        raise InputError(f"--paired {where} is an evaluation in {real.get('env')!r} of task {real.get('task')!r}; "
                         f"pair with one in the simulator of {task.name!r} (--env {task.kind}).")
    if "policy_sha256" not in real:
        raise InputError(f"--paired {where} does not record the policy's weights (written before iwsim recorded "
                         "them); evaluate the policy in MuJoCo again.")
    if real["policy_sha256"] != policy_sha256 or real.get("n_action_steps") != n_action_steps:
        raise InputError(f"--paired {where} evaluated another policy ({real.get('checkpoint')}, "
                         f"{real.get('n_action_steps')} actions per query) than this one; pair with the same "
                         "checkpoint and --action-steps.")
    if real.get("steps") != steps:
        raise InputError(f"--paired {where} ran {real.get('steps')} steps per episode, this evaluation {steps}.")
    theirs = [e.get("seed") for e in real["episodes"]]
    outside = sorted(set(theirs) - set(seeds))
    if outside:
        raise InputError(f"--paired {where} holds seeds {outside[:5]} outside this evaluation's {seeds[0]}.."
                         f"{seeds[-1]}: the real episodes must start from the model's first states.")
    if len(set(theirs)) < 2:
        raise InputError(f"--paired {where} holds {len(set(theirs))} episode(s); a paired estimate needs at least 2.")


def paired_scores(model: dict[str, Any], real: dict[str, Any], key: str) -> dict[str, Any]:
    """The prediction-powered estimates of the real mean max score and success rate from
    this evaluation's episodes (``model``) and the real ones of the same seeds (``real``)."""
    index = {e["seed"]: i for i, e in enumerate(model["episodes"])}
    pairs = {e["seed"]: e for e in real["episodes"]}  # one real episode per seed
    idx = [index[s] for s in pairs]
    score = paired_estimate([e[f"max_{key}"] for e in model["episodes"]],
                            [pairs[s][f"max_{key}"] for s in pairs], idx, bounds=(0.0, 1.0))  # scores in [0, 1]
    success = paired_rate([e["success"] for e in model["episodes"]], [pairs[s]["success"] for s in pairs], idx)
    return {f"mean_max_{key}": score, "success_rate": success, "seeds": sorted(pairs)}


def evaluate(policy: PolicyLike, env: str, *, episodes: int, seed: int, steps: int, world_model: Any = None,
             image_size: int | None = None, out: str | Path | None = None, videos: int = 4, progress: bool = True,
             meta: dict[str, Any] | None = None, partner: Any = None, command: str | None = None,
             paired: dict[str, Any] | None = None, samples: int = 1) -> dict[str, Any]:
    """Evaluate ``policy`` in ``env`` (a built-in task's simulator, by the task's name, or
    "world-model") on ``episodes`` seeds ``seed, seed+1, ...``; with ``out``, write
    ``results.json`` (and each step's score: T-push's ``iou.json``, another task's
    ``score.json``) and videos of the first ``videos`` episodes; with ``command`` too (the
    command line that ran this, from :func:`iwsim.eval.records.command_line`), both JSON
    files begin with it. With ``partner``
    (a second world model, for ``env="world-model"``), the policy also runs in it from the
    same seeds and the result gains ``disagreement`` (:func:`disagreement`). ``image_size``:
    the policy's frame size (None: the environment's, as in :func:`make_vector_env`).
    ``paired``: the results of the same policy in the task's simulator from some of these
    seeds (checked by :func:`check_paired`); the result gains ``paired``, the
    prediction-powered estimates of the real score and success rate
    (:mod:`iwsim.eval.paired`). In a world model the result holds the trust signals of
    :func:`trust` (``samples``: how many samples of the model, for ``sample_spread``)."""
    check_args(episodes, seed, steps, videos, env)
    if out is not None:
        check_output_dir(out)
    if partner is not None and env != "world-model":
        raise InputError("a partner world model (--trust-model) applies to evaluations inside a world model.")
    seeds = [seed + i for i in range(episodes)]
    run, sampled = sampled_rollout(policy, env, seeds, steps, samples=samples, world_model=world_model,
                                   image_size=image_size, record=min(videos, episodes) if out is not None else 0,
                                   progress=progress)
    key = run["score_key"]
    result = {"env": env, "steps": steps, **(meta or {}), "task": run["task"], "scorer": run["scorer"],
              **(no_score(seeds, key) if run["iou"] is None else
                 summarize(run["iou"].max(1), seeds, run["success_score"], key)),
              **trust(run, sampled), "seconds": run["seconds"], "env_steps_per_s": episodes * steps / run["seconds"]}
    if partner is not None and run["iou"] is not None:
        other = rollout(policy, env, seeds, steps, world_model=partner, image_size=image_size, progress=progress)
        result["disagreement"] = disagreement(run["iou"].max(1), other["iou"].max(1))
    if paired is not None and run["iou"] is not None:
        result["paired"] = paired_scores(result, paired, key)
    if out is not None:
        out = Path(out)
        out.mkdir(parents=True, exist_ok=True)
        head = {} if command is None else {"command": command}
        write_json_atomic(out / "results.json", {**head, **result}, sort_keys=False)
        for i in range(0 if run["frames"] is None else len(run["frames"])):
            frames = run["frames"][i]  # several views: one above the other
            write_video(out / f"episode_{seeds[i]}.mp4", upscale(frames if frames.shape[-1] == 3 else
                                                                 tile_views(frames), 4), fps=10)
        if run["iou"] is not None:
            (out / f"{key}.json").write_text(json.dumps({**head, "seeds": seeds,
                                                         f"{key}_per_step": run["iou"].round(4).tolist()}))
    return result
