"""The yardstick's generalisation part: operator families scored in MuJoCo and in a world
model from the same first states, the idle measure and contact-then-rest
(``bench/yardstick.py``'s items 7 and 8; ``bench/pile_families.py`` runs the families on
pile sweeping).

A family is a kind of operator: the pixel expert, the expert through a human-like hand
(:class:`iwsim.policies.scripted.Hand`: a slow lagging hand, a person's pauses, a tremor,
latency, a hand that overshoots, and a person who does all of that a little), expert-like
motions aimed at a displaced block (they miss), random pushing (the play policy), pushers
held still, and learned policies (a zoo of Diffusion Policy / ACT checkpoints, the
episodes shared round-robin among them). Every family runs from the same first states
(MuJoCo seeds from :data:`SEED`, never used for training or by the studies) for the same
steps in both environments; an episode's score is its max pixel IoU.

A family is *seen* by a model when its kind of motion was in the model's training data
(:data:`TRAINING_FAMILIES`: which families each collected policy covers); targets count
only the unseen ones.

The idle measure: from fresh MuJoCo starts the pushers are held still; in each frame of the
model the T is fitted (:func:`iwsim.envs.pusht.pixels.estimate_block_pose`) and compared with
MuJoCo's frame of the same step. A frame keeps the block when the T fits crisply (fit >=
:data:`CRISP`) and in place (<= 1 px, <= 5 degrees).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import torch

from iwsim.core.checkpoint import load_json, write_json_atomic
from iwsim.envs.pusht import pixels
from iwsim.envs.registry import DEFAULT_TASK, get_task
from iwsim.eval.paired import METHOD, TRUST_WEIGHTS, judge_paired
from iwsim.eval.policy import rollout
from iwsim.eval.ranking import agreement
from iwsim.eval.trust import SIGNALS, ErrorPredictor, calibration, spearman
from iwsim.experiments.common import evaluate_policies, fingerprint
from iwsim.experiments.policy_eval import mean_interval
from iwsim.policies.scripted import ScriptedBatch, ScriptedConfig
from iwsim.world_model import WorldModel
from iwsim.world_model.env import score_key

SEED = 700000  # first states of the families: MuJoCo seeds SEED, SEED + 1, ...
# Other first states of the families, in MuJoCo only: the real means that judge the paired
# estimates (iwsim.eval.paired) made from the families' own episodes.
HOLDOUT_SEED = 750000
LEARNED = "learned"
FAMILIES: dict[str, tuple[ScriptedConfig | None, str]] = {
    "expert": (ScriptedConfig("expert"), "the pixel expert"),
    "person": (ScriptedConfig("expert", lag=2, pause=0.03, jitter=0.003),
               "the expert through a person's hand: a little slow, pausing now and then, a slight tremor"),
    "lag3": (ScriptedConfig("expert", lag=3), "a slow hand (time constant 3 steps)"),
    "lag6": (ScriptedConfig("expert", lag=6), "a slower hand (6 steps)"),
    "pause": (ScriptedConfig("expert", pause=0.05), "pauses: the command held 5-20 steps, 5% a step"),
    "jitter": (ScriptedConfig("expert", jitter=0.006), "a tremor of 6 mm (correlated over ~5 steps)"),
    "latency3": (ScriptedConfig("expert", latency=3), "commands executed 3 steps late"),
    "overshoot": (ScriptedConfig("expert", overshoot=2), "a hand leading its motion by 2 steps (overshoots)"),
    "miss": (ScriptedConfig("expert", miss=0.05), "expert-like motions aimed 5 cm (and a turn) off the block"),
    "play": (ScriptedConfig("play"), "random pushing (the play policy)"),
    "still": (ScriptedConfig("still"), "the pushers held still"),
    LEARNED: (None, "learned policies: the zoo's checkpoints, round-robin over the episodes"),
}
# The families whose kind of motion each collected policy (``iwsim collect --policy``) puts
# in a world model's training data.
TRAINING_FAMILIES: dict[str, tuple[str, ...]] = {
    "play": ("play",),
    "expert-noisy": ("expert", "jitter"),  # the expert with smooth command noise of 0-12 mm
    "expert-lagged": ("expert", "jitter", "latency3"),
    # rests, pauses, slow hands (time constants 1.5-5 steps) and tremors over random pushing
    "play-broad": ("play", "still", "pause", "lag3", "lag6", "jitter"),
    # the same, its setpoints run 10-40 mm beyond the asked step in most segments (pressing)
    "play-press": ("play", "still", "pause", "lag3", "lag6", "jitter"),
    # the noisy expert through slow or pausing hands: a person's kind of teleoperation
    "expert-hands": ("expert", "jitter", "lag3", "lag6", "pause", "person"),
    # the expert's motions with a learned policy's imprecision: grips off the grip points,
    # blind carries (counted as covering the misses, conservatively)
    "expert-imprecise": ("expert", "miss"),
    # MuJoCo rollouts of a training zoo of learned policies (iwsim collect --policy RUN),
    # disjoint from the learned family's: other demonstrations, other training seeds
    "learned-zoo": (),
}
IDLE_STEPS = 50
# The contact-then-rest measure: the pixel expert pushes for PUSH_STEPS, the pushers then
# withdraw WITHDRAW_M from the block and hold still; the T is judged REST_STEPS later.
PUSH_STEPS, REST_STEPS, WITHDRAW_M = 40, 20, 0.08
REST_SEED = 720000  # its first states (never used for training, the studies or the families)
MOVED_PX, MOVED_DEG = 1.0, 5.0  # a block the push moved (in MuJoCo)
CRISP = 0.9  # a T fits crisply: just below the shipped codec's reconstructions (bench/results/ablations.md)
IN_PLACE_PX, IN_PLACE_DEG = 1.0, 5.0


def seen_families(policies: list[str]) -> list[str]:
    """The families covered by training data collected with ``policies``."""
    unknown = [p for p in policies if p not in TRAINING_FAMILIES]
    if unknown:
        raise ValueError(f"unknown training policies {unknown}; known: {', '.join(TRAINING_FAMILIES)}.")
    return sorted({f for p in policies for f in TRAINING_FAMILIES[p]})


def zoo_sources(zoo: list[str]) -> list[str]:
    """Policy checkpoint directories of the learned family (``--zoo`` entries, each a
    checkpoint or a run whose ``checkpoints/<step>`` are all taken)."""
    out = []
    for entry in zoo:
        path = Path(entry)
        steps = sorted((d for d in (path / "checkpoints").iterdir() if d.name.isdigit()), key=lambda d: int(d.name)) \
            if (path / "checkpoints").is_dir() else [path]
        out += [str(d) for d in steps]
    return out


def family_scores(model: str | None, work: Path, families: list[str], seeds: int, steps: int,
                  zoo: list[str], jobs: int = 1, task: str = DEFAULT_TASK.kind, samples: int = 1,
                  first_seed: int = SEED) -> tuple[dict[str, list[float]], dict[str, dict[str, list[float]]]]:
    """Per family, the max score (T-push's IoU, ``task``'s score) of each episode (``seeds``
    of them, MuJoCo seeds from ``first_seed``) in ``task``'s MuJoCo (``model`` None) or in the
    world model ``model``, and (in a model) each episode's trust signals
    (:mod:`iwsim.eval.trust`: signal -> family -> per-episode; ``samples`` samples of the
    model for the spread); cached under ``work`` by
    :func:`iwsim.experiments.common.evaluate_policies`, up to ``jobs`` families at a time."""
    env = task if model is None else "world-model"
    best = f"max_{score_key(get_task(task))}"
    all_seeds = [first_seed + i for i in range(seeds)]
    work = work / "families" / ("mujoco" if model is None else fingerprint(model))  # a cache per model
    if first_seed != SEED:
        work = work.with_name(f"{work.name}-from{first_seed}")
    sources: dict[str, Any] = {f: FAMILIES[f][0] for f in families if f != LEARNED}
    results = evaluate_policies(sources, env, seeds=all_seeds, steps=steps, world_model=model, out=work,
                                jobs=jobs, progress=False, samples=samples)
    out = {f: [e[best] for e in r["episodes"]] for f, r in results.items()}
    signals: dict[str, dict[str, list[float]]] = {}
    for f, r in results.items():
        for name in SIGNALS:
            if name in r:
                signals.setdefault(name, {})[f] = r[name]["per_episode"]
    if LEARNED in families:
        policies = zoo_sources(zoo)
        if not policies:
            raise ValueError("the learned family needs policy checkpoints: pass --zoo RUN_OR_CHECKPOINT ...")
        scores = np.zeros(seeds)
        learned: dict[str, np.ndarray] = {}
        for k, path in enumerate(policies):
            mine = all_seeds[k::len(policies)]
            if not mine:
                continue
            name = f"{LEARNED}-{Path(path).parent.parent.name}-{Path(path).name}"
            r = evaluate_policies({name: path}, env, seeds=mine, steps=steps, world_model=model, out=work,
                                  progress=False, samples=samples)[name]
            scores[k::len(policies)] = [e[best] for e in r["episodes"]]
            for signal in SIGNALS:
                if signal in r:
                    learned.setdefault(signal, np.zeros(seeds))[k::len(policies)] = r[signal]["per_episode"]
        out[LEARNED] = scores.tolist()
        for signal, v in learned.items():
            signals.setdefault(signal, {})[LEARNED] = v.tolist()
    return ({f: out[f] for f in families},
            {n: {f: v[f] for f in families} for n, v in signals.items() if set(families) <= set(v)})


def compare(mujoco: dict[str, list[float]], model: dict[str, list[float]], seen: list[str],
            signals: dict[str, dict[str, list[float]]] | None = None) -> dict[str, Any]:
    """Per family: the mean max IoU in both, the offset (model - MuJoCo) with a 95% bootstrap
    interval over episodes, and whether the family is seen; pooled Pearson r, Spearman rho
    and MMRV over all (family, episode) pairs and over the unseen families' alone. With
    ``signals`` (:func:`family_scores`'s): each family's mean of each, and ``trust``
    (:func:`trust_measures`)."""
    rows: dict[str, dict[str, Any]] = {}
    for f in model:
        a, b = np.asarray(mujoco[f]), np.asarray(model[f])
        rows[f] = {"mujoco": float(a.mean()), "model": float(b.mean()), "offset": float((b - a).mean()),
                   "offset_interval": list(mean_interval(b - a)), "seen": f in seen, "episodes": len(a)}
    pooled = {}
    for part, fams in (("all", list(model)), ("unseen", [f for f in model if f not in seen])):
        if not fams:
            continue
        a = np.concatenate([mujoco[f] for f in fams])
        b = np.concatenate([model[f] for f in fams])
        agree = agreement(a.tolist(), b.tolist(), ("MuJoCo", "model"))
        pooled[part] = {"pearson": agree["pearson"], "spearman": agree["spearman"], "mmrv": agree["mmrv"],
                        "max_abs_offset": max(abs(rows[f]["offset"]) for f in fams), "families": fams}
    out: dict[str, Any] = {"families": rows, "pooled": pooled}
    signals = {n: v for n, v in (signals or {}).items() if set(v) == set(model)}
    if signals:
        for name, v in signals.items():
            for f in model:
                rows[f][name] = float(np.mean(v[f]))
        out["trust"] = trust_measures(mujoco, model, seen, signals)
    return out


def trust_measures(mujoco: dict[str, list[float]], model: dict[str, list[float]], seen: list[str],
                   signals: dict[str, dict[str, list[float]]]) -> dict[str, Any]:
    """How well each trust signal ranks the family episodes by their error |model -
    MuJoCo| (Spearman rho over the seen families' episodes, the unseen ones' and all), and
    the error predictor (:class:`~iwsim.eval.trust.ErrorPredictor`: the signals and the
    model's score) fitted on the seen families' episodes and judged on the unseen ones'
    (policies it never saw); the unseen episodes' calibration (:func:`~iwsim.eval.trust.calibration`)."""
    parts = {"seen": [f for f in model if f in seen], "unseen": [f for f in model if f not in seen],
             "all": list(model)}

    def pool(d: dict[str, list[float]], fams: list[str]) -> np.ndarray:
        return np.concatenate([np.asarray(d[f], np.float64) for f in fams]) if fams else np.zeros(0)

    err = {p: np.abs(pool(model, fams) - pool(mujoco, fams)) for p, fams in parts.items()}
    feats = {p: {**{n: pool(v, fams) for n, v in signals.items()}, "score": pool(model, fams)}
             for p, fams in parts.items()}
    out: dict[str, Any] = {"episodes": {p: len(e) for p, e in err.items()},
                           "spearman": {n: {p: spearman(feats[p][n], err[p]) for p in parts} for n in signals},
                           "calibration": {n: calibration(feats["unseen"][n], err["unseen"]) for n in signals}
                           if len(err["unseen"]) else {}}
    if len(err["seen"]) >= 10 and len(err["unseen"]):
        predictor = ErrorPredictor.fit(feats["seen"], err["seen"])
        predicted = predictor.predict(feats["unseen"])
        out["predictor"] = {"weights": predictor.weights(), "spearman_unseen": spearman(predicted, err["unseen"]),
                            "calibration": calibration(predicted, err["unseen"]),
                            "per_episode_unseen": np.round(predicted, 4).tolist()}
    out["error_unseen"] = np.round(err["unseen"], 4).tolist()
    return out


def paired_families(mujoco: dict[str, list[float]], model: dict[str, list[float]],
                    holdout: dict[str, list[float]], ns: list[int],
                    signals: dict[str, dict[str, list[float]]] | None = None) -> dict[str, Any]:
    """Each family treated as a policy to evaluate: its paired estimate of the real mean max
    IoU from the model's episodes and the first n of MuJoCo's of the same first states, for
    each n of ``ns``, judged against MuJoCo's mean over the ``holdout`` first states
    (:func:`iwsim.eval.paired.judge_paired`; also distrusting the model by the trust signals
    of :data:`~iwsim.eval.paired.TRUST_WEIGHTS` found in ``signals``)."""
    fams = [f for f in model if f in holdout]
    weights = {n: v for n, v in (signals or {}).items() if n in TRUST_WEIGHTS and set(fams) <= set(v)}
    out = judge_paired({f: model[f] for f in fams}, mujoco, {f: float(np.mean(holdout[f])) for f in fams}, ns,
                       "mean max IoUs", {n: {f: v[f] for f in fams} for n, v in weights.items()})
    return {"holdout_episodes": min(len(holdout[f]) for f in fams), "holdout_seed": HOLDOUT_SEED,
            "method": METHOD, **out}


def ensemble_trust(mujoco: dict[str, list[float]], model: dict[str, list[float]], partner: dict[str, list[float]]
                   ) -> dict[str, Any]:
    """The ensemble trust signal on the families (:func:`iwsim.eval.policy.disagreement`):
    how well each episode's |model - partner| ranks the episodes by the model's error
    |model - MuJoCo| (Spearman rho over all (family, episode) pairs both models ran), and
    each family's mean disagreement."""
    fams = [f for f in model if f in partner]
    a, b = (np.concatenate([np.asarray(x[f]) for f in fams]) for x in (model, partner))
    err = np.abs(a - np.concatenate([np.asarray(mujoco[f]) for f in fams]))
    gap = np.abs(a - b)
    return {"spearman_error": spearman(gap, err),
            "episodes": len(err), "families": {f: float(np.mean(np.abs(np.subtract(model[f], partner[f]))))
                                              for f in fams}}


def block_state(frames: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per frame (..., H, W, 3): the fitted T's pose (..., 3) (NaN where none) and fit (...)."""
    flat = frames.reshape(-1, *frames.shape[-3:])
    est = [pixels.estimate_block_pose(f) for f in flat]
    pose = np.stack([e.pose for e in est]).reshape(*frames.shape[:-3], 3)
    fit = np.array([e.fit_iou for e in est]).reshape(frames.shape[:-3])
    return pose, fit


def idle(model: str | None, work: Path, episodes: int, steps: int = IDLE_STEPS) -> dict[str, Any]:
    """Pushers held still for ``steps`` from ``episodes`` fresh starts: the T's fit per
    step (mean over episodes) and, against MuJoCo's frames, the share of frames that keep
    the block (crisp and in place). Cached under ``work``."""
    key = {"model": model and fingerprint(model), "episodes": episodes, "steps": steps}
    cached = work / "idle" / f"{'mujoco' if model is None else fingerprint(model)}.json"
    if cached.is_file() and (saved := load_json(cached))["key"] == key and (model or "pose" in saved["result"]):
        return saved["result"]
    seeds = [SEED + i for i in range(episodes)]

    def run(wm: WorldModel | None) -> np.ndarray:
        return rollout(ScriptedBatch("still"), "pusht" if wm is None else "world-model", seeds, steps,
                       world_model=wm, record=episodes, progress=False)["frames"]

    torch.manual_seed(0)
    frames = run(None if model is None else WorldModel.load(model))
    pose, fit = block_state(frames)
    result: dict[str, Any] = {"fit_per_step": np.nanmean(fit, 0).round(4).tolist(),
                              "fit_first": float(np.mean(fit[:, 0]))}
    for s in (10, 20, steps):
        result[f"fit_{s}"] = float(np.mean(fit[:, min(s, steps)]))
    if model is None:  # MuJoCo's poses, the reference of every model's idle run (read, not run again)
        result["pose"] = pose.tolist()
    else:
        ref_pose = np.array(idle(None, work, episodes, steps)["pose"], dtype=np.float64)
        size = frames.shape[-2]
        shift_px = np.linalg.norm(pose[..., :2] - ref_pose[..., :2], axis=-1) / (2 * pixels.VIEW_HALF) * size
        turn = np.degrees(np.abs((pose[..., 2] - ref_pose[..., 2] + np.pi) % (2 * np.pi) - np.pi))
        kept = (fit >= CRISP) & (shift_px <= IN_PLACE_PX) & (turn <= IN_PLACE_DEG)  # NaN compares False
        result.update(kept=float(kept[:, 1:].mean()), kept_per_step=kept.mean(0).round(3).tolist())
    cached.parent.mkdir(parents=True, exist_ok=True)
    write_json_atomic(cached, {"key": key, "result": result})
    return result


class PushThenRest:
    """The pixel expert for ``push`` steps; then each pusher withdraws ``away`` m straight
    from the block's centre (as the frame shows it) and holds still."""

    obs_horizon = n_action_steps = 1

    def __init__(self, push: int = PUSH_STEPS, away: float = WITHDRAW_M) -> None:
        self.expert, self.push, self.away = ScriptedBatch("expert"), push, away
        self.hold: np.ndarray | None = None  # the withdrawn pushers' setpoints (B, A), once the push is over
        self.reset()

    def reset(self) -> None:
        self.expert.reset()
        self.t, self.hold = 0, None

    def predict_action(self, obs: dict) -> np.ndarray:
        self.t += 1
        if self.t <= self.push:
            return self.expert.predict_action(obs)
        if self.hold is None:
            task = get_task("pusht")
            pos = obs["agent_pos"][:, -1].reshape(-1, 2, 2).astype(np.float64)  # (B, pusher, xy)
            centre = np.stack([pixels.estimate_block_pose(f).pose[:2] for f in obs["image"][:, -1]])[:, None]
            away = pos - np.where(np.isfinite(centre), centre, 0.0)
            away /= np.maximum(np.linalg.norm(away, axis=-1, keepdims=True), 1e-6)
            hold = (pos + self.away * away).reshape(len(pos), -1)
            self.hold = np.clip(hold, task.action_low, task.action_high).astype(np.float32)
        return self.hold[:, None]


class Replay:
    """The commands of another run (E, T, A), one per call, whatever the frames show."""

    obs_horizon = n_action_steps = 1

    def __init__(self, actions: np.ndarray) -> None:
        self.actions = np.asarray(actions, np.float32)
        self.reset()

    def reset(self) -> None:
        self.t = 0

    def predict_action(self, obs: dict) -> np.ndarray:
        self.t += 1
        return self.actions[:, self.t - 1:self.t]


def contact_rest(model: str | None, work: Path, episodes: int, push: int = PUSH_STEPS,
                 rest: int = REST_STEPS) -> dict[str, Any]:
    """Contact, then rest: from ``episodes`` fresh starts the pixel expert pushes
    the block in MuJoCo for ``push`` steps, the pushers withdraw and rest (:class:`PushThenRest`);
    the model replays MuJoCo's commands from the same first frame. ``rest`` steps after the
    pushers stopped, over the episodes whose block the push moved (>= 1 px or 5 degrees in
    MuJoCo): the T's outline fit in the model's last frame against the fit of the codec's
    rendering of MuJoCo's last frame (the level a model can reach; within 0.02 counts as
    back), MuJoCo's own fit, and the pose error against MuJoCo's. Cached under ``work``."""
    key = {"model": model and fingerprint(model), "episodes": episodes, "push": push, "rest": rest}
    name = "mujoco" if model is None else fingerprint(model)
    cached = work / "contact_rest" / f"{name}.json"
    if cached.is_file() and (saved := load_json(cached))["key"] == key:
        return saved["result"]
    seeds = [REST_SEED + i for i in range(episodes)]
    steps = push + rest + 8  # 8: the pushers' withdrawal at the speed limit (16 mm a step)
    torch.manual_seed(0)
    real = rollout(PushThenRest(push), "pusht", seeds, steps, record=episodes, progress=False)
    frames = real["frames"]
    pose, fit = block_state(frames[:, [0, -1]])
    size = frames.shape[-2]
    shift = np.linalg.norm(pose[:, 1, :2] - pose[:, 0, :2], axis=-1) / (2 * pixels.VIEW_HALF) * size
    turn = np.degrees(np.abs((pose[:, 1, 2] - pose[:, 0, 2] + np.pi) % (2 * np.pi) - np.pi))
    moved = (shift >= MOVED_PX) | (turn >= MOVED_DEG)
    result: dict[str, Any] = {"episodes": episodes, "moved": int(moved.sum()), "push_steps": push,
                              "rest_steps": rest, "fit_mujoco": float(np.mean(fit[moved, 1])) if moved.any() else None}
    if model is not None and moved.any():
        wm = WorldModel.load(model)
        run = rollout(Replay(real["action"]), "world-model", seeds, steps, world_model=wm, record=episodes,
                      progress=False)
        m_pose, m_fit = block_state(run["frames"][:, -1])
        with torch.inference_mode():
            codec = wm.decode(wm.encode(frames[:, -1]))
        _, c_fit = block_state(codec)
        err_px = np.linalg.norm(m_pose[:, :2] - pose[:, 1, :2], axis=-1) / (2 * pixels.VIEW_HALF) * size
        err_deg = np.degrees(np.abs((m_pose[:, 2] - pose[:, 1, 2] + np.pi) % (2 * np.pi) - np.pi))
        back = m_fit >= c_fit - 0.02
        found = moved & np.isfinite(err_px)  # a frame without a T has no pose to compare

        def median(x: np.ndarray) -> float | None:  # None, not NaN: the cache and report are JSON
            return float(np.median(x[found])) if found.any() else None

        result.update(fit_model=float(np.mean(m_fit[moved])), fit_codec=float(np.mean(c_fit[moved])),
                      back_to_codec=float(np.mean(back[moved])), pose_found=float(np.mean(found[moved])),
                      pose_err_px=median(err_px), pose_err_deg=median(err_deg),
                      crisp_in_place=float(np.mean(((m_fit >= CRISP) & (err_px <= IN_PLACE_PX)
                                                    & (err_deg <= IN_PLACE_DEG))[moved])))
    cached.parent.mkdir(parents=True, exist_ok=True)
    write_json_atomic(cached, {"key": key, "result": result})
    return result
