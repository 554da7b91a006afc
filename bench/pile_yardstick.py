"""Issue 45's targets for a pile-sweeping world model: one command, one table row per model.

    MUJOCO_GL=egl python bench/pile_yardstick.py --models pile=runs/pile_dyn

For each model (a world model of pile sweeping; another task's is refused), on one thread
by default, over the task's horizon H (200 steps):

1. Held-out play (``--data``, never trained on): ``--episodes`` episodes open loop from
   their first frame under the recorded executed actions (:func:`iwsim.eval.rollout.open_loop`).
   Pieces kept: the share of frames whose visible piece count (the pixel scorer,
   :func:`~iwsim.envs.pilesweep.pixels.count_pieces`) is within one of the first frame's;
   PSNR over steps 1-H. Beside them, repeating the first frame (it keeps every piece
   trivially, which is why it is shown) and MuJoCo's own frames (the scorer's miscounts).
2. The expert's recorded actions (``--expert-data``), open loop for H steps: the tray count
   error at step H, |the scorer's count in the tray on the model's frame - MuJoCo's exact
   ``n_in_tray``|, mean over episodes; MuJoCo's row holds the scorer's own error on MuJoCo's
   frame, its share of the model's.
3. The pixel expert closed loop in the model from ``--teleop-episodes`` MuJoCo first states
   (seeds from 300000): its mean max share in the tray beside MuJoCo's from the same seeds.
4. Ranking: the policy-evaluation study's scripted policies x ``--rank-episodes`` first
   states (the study's seeds) in MuJoCo and in the model: Pearson r, Spearman rho, MMRV.
5. Speed: single-stream steps/s at ``--threads`` (never time beside a training run).

Results are cached under ``--work`` (per model by its weights and the settings; the
closed-loop evaluations per policy); ``--out`` gets results.json and results.md with every
model measured with the same settings (other settings start a new report).
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np
import torch

from iwsim.core.checkpoint import load_json, named_checkpoints, write_json_atomic, write_text_atomic
from iwsim.core.errors import InputError, check_positive, reporting_errors
from iwsim.core.resources import set_threads
from iwsim.data.store import EpisodeStore
from iwsim.envs.pilesweep.pixels import count_pieces
from iwsim.envs.registry import get_task, task_from_store
from iwsim.eval.policy import WORLD_MODEL, check_model_task
from iwsim.eval.profiling import speed
from iwsim.eval.ranking import agreement
from iwsim.eval.records import command_line, with_command
from iwsim.eval.rollout import frame_scores, open_loop
from iwsim.experiments.common import evaluate_policies, fingerprint
from iwsim.experiments.policy_eval import PolicyEvalConfig
from iwsim.policies.scripted import ScriptedConfig
from iwsim.world_model import WorldModel
from iwsim.world_model.env import score_key

TASK = get_task("pilesweep")
STUDY = PolicyEvalConfig(task=TASK.kind)  # its scripted zoo and seeds are the ranking's
EXPERT = ScriptedConfig("expert")
EXPERT_SEED = 300000
SCORE = f"mean_max_{score_key(TASK)}"


def columns(h: int) -> list[tuple[str, str, str, str]]:
    """(column, key, format, target as text) of the table, for horizon ``h``."""
    return [(f"pieces kept (play, {h})", "pieces_kept", "{:.0%}", ">= 95%"),
            (f"PSNR 1-{h} (play)", "psnr_play", "{:.2f}", "- (beside repeat first)"),
            (f"tray count err @{h} (expert)", "tray_err", "{:.2f}", "<= 1"),
            ("expert closed loop: mean max share (offset)", "expert_score", "{:.3f}", "offset within 0.1"),
            ("rank r", "pearson", "{:.2f}", ">= 0.8"), ("rank rho", "spearman", "{:.2f}", "-"),
            ("MMRV", "mmrv", "{:.3f}", "-"), ("steps/s (1 stream)", "steps_per_s", "{:.0f}", ">= 50")]


def check_store(path: str, episodes: int, horizon: int, need: str | None = None) -> EpisodeStore:
    """The pile-sweeping store at ``path``, or one line of error unless its first ``episodes``
    episodes hold a first frame and ``horizon`` steps (and the array ``need``)."""
    if (task := task_from_store(path)).name != TASK.name:
        raise InputError(f"{path} holds episodes of task {task.name!r}, not {TASK.name!r}.")
    store = EpisodeStore.open(path, "r")
    if store.n_episodes < episodes:
        raise InputError(f"{path} holds {store.n_episodes} episodes; --episodes {episodes} needs as many.")
    if need is not None and need not in store.keys:
        raise InputError(f"{path} has no data/{need}; record it with iwsim collect --task {TASK.kind}.")
    shortest = int(np.diff(store.episode_ends[:episodes], prepend=0).min())
    if shortest < horizon + 1:
        raise InputError(f"{path}: its shortest of the first {episodes} episodes has {shortest} frames, too few for "
                         f"--horizon {horizon} (a first frame and {horizon} steps); use --horizon {shortest - 1}.")
    return store


def frame_index(store: EpisodeStore, episodes: int, step: int) -> np.ndarray:
    """The index of frame ``step`` of each of the first ``episodes`` episodes of ``store``."""
    return np.concatenate([[0], store.episode_ends[:episodes - 1]]) + step


def kept(seen: np.ndarray, first: np.ndarray) -> float:
    """The share of frames whose piece count ``seen`` (E, T) is within one of the first frame's ``first`` (E,)."""
    return float((np.abs(seen - first[:, None]) <= 1).mean())


def reference(args: argparse.Namespace, play: EpisodeStore, expert: EpisodeStore) -> tuple[dict, dict, np.ndarray]:
    """MuJoCo's own frames and repeating the first frame, measured as the models are (items
    1-2); and the pieces the scorer sees on each play episode's first frame (E,)."""
    frames = np.stack([play.episode(e)["img"][:args.horizon + 1] for e in range(args.episodes)])
    _, seen = count_pieces(frames)  # (E, H + 1)
    first = seen[:, 0]
    psnr_first, _ = frame_scores(frames[:, 1:], np.broadcast_to(frames[:, :1], frames[:, 1:].shape))
    last = frame_index(expert, args.episodes, args.horizon)
    tray, _ = count_pieces(expert.array("img").oindex[last])
    exact = expert.array("n_in_tray").oindex[last]
    mujoco = {"pieces_kept": kept(seen[:, 1:], first), "tray_err": float(np.abs(tray - exact).mean()),
              "n_in_tray": exact.tolist()}
    repeat = {"pieces_kept": kept(np.broadcast_to(first[:, None], seen[:, 1:].shape), first),
              "psnr_play": float(psnr_first.mean())}
    return mujoco, repeat, first


def closed_loop(name: str, ckpt: str | None, args: argparse.Namespace, work: Path) -> dict:
    """Items 3-4 in the model (MuJoCo when ``ckpt`` is None): each scripted policy's mean
    max score and the expert's from its own seeds (its mean final score too)."""
    env = TASK.kind if ckpt is None else WORLD_MODEL
    rank = evaluate_policies(STUDY.scripted(), env, seeds=range(STUDY.seed, STUDY.seed + args.rank_episodes),
                             steps=args.horizon, world_model=ckpt, out=work / "rank" / name)
    expert = evaluate_policies({EXPERT.name: EXPERT}, env, seeds=range(EXPERT_SEED, EXPERT_SEED + args.teleop_episodes),
                               steps=args.horizon, world_model=ckpt, out=work / "expert" / name)[EXPERT.name]
    final = np.array(expert[f"{score_key(TASK)}_per_step"])[:, -1]
    return {"ranking": {n: r[SCORE] for n, r in rank.items()}, "expert_score": expert[SCORE],
            "expert_final_score": float(final.mean())}


def evaluate(name: str, ckpt: str, args: argparse.Namespace, work: Path, settings: dict, mujoco: dict,
             first: np.ndarray) -> dict:
    """Items 1-5 for one model (cached under ``work`` by its weights and ``settings``)."""
    key = {"model": fingerprint(ckpt), **settings}
    cached = work / "models" / f"{name}.json"
    if cached.is_file() and (saved := load_json(cached))["key"] == key:
        result = saved["result"]
        if args.respeed:  # the other items stand; the speed is taken again (on cores nothing else uses)
            frame = EpisodeStore.open(args.data, "r").episode(0)["img"][1]  # play.truth[0, 0]
            result.update(speed(WorldModel.load(ckpt), frame, n=args.speed_calls))
            write_json_atomic(cached, {"key": key, "result": result})
        return result
    t0 = time.perf_counter()
    wm = WorldModel.load(ckpt)
    episodes = list(range(args.episodes))
    print(f"{name}: open loop on {args.data} and {args.expert_data}", flush=True)
    play = open_loop(wm, EpisodeStore.open(args.data, "r"), episodes, args.horizon, progress=True)
    _, seen = count_pieces(play.pred)
    expert = open_loop(wm, EpisodeStore.open(args.expert_data, "r"), episodes, args.horizon, progress=True)
    tray, _ = count_pieces(expert.pred[:, -1])
    print(f"{name}: closed loop", flush=True)
    scores = closed_loop(name, ckpt, args, work)
    names = list(mujoco["ranking"])
    agree = agreement([mujoco["ranking"][n] for n in names], [scores["ranking"][n] for n in names],
                      ("MuJoCo", name))
    result = {"checkpoint": ckpt, "pieces_kept": kept(seen, first), "psnr_play": float(play.psnr.mean()),
              "psnr_expert": float(expert.psnr.mean()),
              "tray_err": float(np.abs(tray - np.array(mujoco["n_in_tray"])).mean()), **scores,
              "expert_offset": scores["expert_score"] - mujoco["expert_score"],
              **{k: agree[k] for k in ("pearson", "spearman", "mmrv")}, "rank_undefined": agree["undefined"],
              **speed(wm, play.truth[0, 0], n=args.speed_calls), "threads": args.threads}
    result["minutes"] = (time.perf_counter() - t0) / 60
    cached.parent.mkdir(parents=True, exist_ok=True)
    write_json_atomic(cached, {"key": key, "result": result})
    return result


def cell(r: dict, key: str, fmt: str) -> str:
    """A table cell: "-" for a measure a row has not, "undefined" for a statistic without value."""
    if key not in r:
        return "-"
    if (v := r[key]) is None:
        return "undefined"
    text = fmt.format(v)
    if key == "expert_score" and "expert_offset" in r:
        text += f" ({r['expert_offset']:+.3f})"
    return text


def markdown(report: dict) -> str:
    """results.md: the commands, the settings, a row per model beside the target, MuJoCo and
    repeating the first frame, then the scripted policies' scores."""
    s, m = report["settings"], report["mujoco"]
    cols = columns(s["horizon"])
    lines = ["# Pile sweeping's yardstick (`bench/pile_yardstick.py`, issue 45)", "",
             "Commands, in the order they were run:", "", *(f"    {c}" for c in report["commands"]), "",
             f"Horizon {s['horizon']} steps. Held-out play: {s['episodes']} episodes of `{s['data']}` open loop; a "
             "frame keeps the pieces when the pixel scorer sees the first frame's number within one. Tray count: "
             f"{s['episodes']} episodes of `{s['expert_data']}` open loop, the scorer on the last frame against "
             "MuJoCo's exact count (MuJoCo's row: the scorer on MuJoCo's frame). Expert closed loop: the pixel expert "
             f"from {s['teleop_episodes']} MuJoCo first states (seeds from {EXPERT_SEED}); offset: model - MuJoCo. "
             f"Ranking: {len(m['ranking'])} scripted policies x {s['rank_episodes']} first states (seeds from "
             f"{STUDY.seed}), mean max share in the tray. Speed at the thread count in brackets.", "",
             "| model | " + " | ".join(c for c, *_ in cols) + " | minutes |", "|---" * (len(cols) + 2) + "|",
             "| target | " + " | ".join(t for *_, t in cols) + " | - |"]
    rows = {"MuJoCo": {**m, "pearson": 1.0, "spearman": 1.0, "mmrv": 0.0},
            "repeat first frame": report["repeat_first"], **report["models"]}
    for name, r in rows.items():
        row = [cell(r, k, f) + (f" ({r['threads']})" if k == "steps_per_s" and "threads" in r else "")
               for _, k, f, _ in cols]
        minutes = f"{r['minutes']:.0f}" if "minutes" in r else "-"
        lines.append(f"| {name} | " + " | ".join(row) + f" | {minutes} |")
    models = report["models"]
    lines += ["", "Scripted policies' mean max share in the tray (MuJoCo, then each model):", "",
              "| policy | MuJoCo | " + " | ".join(models) + " |", "|---" * (len(models) + 2) + "|"]
    for n in sorted(m["ranking"], key=lambda n: -m["ranking"][n]):
        lines.append(f"| {n} | {m['ranking'][n]:.3f} | " + " | ".join(f"{r['ranking'][n]:.3f}" for r in models.values())
                     + " |")
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--models", nargs="+", required=True, help="NAME=CHECKPOINT_OR_RUN world models of pile sweeping")
    p.add_argument("--data", default="data/pile_play_eval.zarr", help="held-out play store (default: %(default)s)")
    p.add_argument("--expert-data", default="data/pile_expert_eval.zarr",
                   help="held-out expert store (default: %(default)s)")
    p.add_argument("--episodes", type=int, default=20, help="open-loop episodes of each store (default: %(default)s)")
    p.add_argument("--horizon", type=int, default=TASK.horizon, help="steps of every rollout (default: the task's, "
                   "%(default)s)")
    p.add_argument("--rank-episodes", type=int, default=20, help="first states per scripted policy "
                   "(default: %(default)s)")
    p.add_argument("--teleop-episodes", type=int, default=32, help="first states of the expert closed loop "
                   "(default: %(default)s)")
    p.add_argument("--speed-calls", type=int, default=100, help="timed steps of the speed test (default: %(default)s)")
    p.add_argument("--threads", type=int, default=1, help="torch threads (default: %(default)s)")
    p.add_argument("--respeed", action="store_true", help="measure the speed again for models already measured "
                   "(when the first measurement shared the cores with other work)")
    p.add_argument("--work", default="runs/pile_yardstick", help="cache (default: %(default)s)")
    p.add_argument("--out", default="bench/results/pilesweep/yardstick", help="report directory (default: %(default)s)")
    args = p.parse_args(argv)
    check_positive(args, "episodes", "horizon", "rank_episodes", "teleop_episodes", "speed_calls", "threads")
    models = named_checkpoints(args.models)
    for name, ckpt in models.items():
        check_model_task(WorldModel.load(ckpt), TASK, f"--models {name}={ckpt}")
    play = check_store(args.data, args.episodes, args.horizon)
    expert = check_store(args.expert_data, args.episodes, args.horizon, need="n_in_tray")
    set_threads(args.threads)
    torch.manual_seed(0)
    work, out = Path(args.work), Path(args.out)
    settings = {k: getattr(args, k) for k in ("data", "expert_data", "episodes", "horizon", "rank_episodes",
                                              "teleop_episodes", "speed_calls", "threads")}
    out.mkdir(parents=True, exist_ok=True)
    report_path = out / "results.json"
    report = load_json(report_path) if report_path.is_file() else {}
    if report.get("settings") != settings:  # rows measured otherwise do not compare: a new report
        report = {"commands": [], "settings": settings, "models": {}}
    command = command_line(__file__, argv)
    report["commands"] = [c for c in report["commands"] if c != command] + [command]
    print("MuJoCo: the stores' frames, then closed loop", flush=True)
    mujoco, report["repeat_first"], first = reference(args, play, expert)
    report["mujoco"] = {**mujoco, **closed_loop("mujoco", None, args, work)}
    for name, ckpt in models.items():
        r = report["models"][name] = evaluate(name, ckpt, args, work, settings, report["mujoco"], first)
        print(f"{name}: " + ", ".join(f"{c} {cell(r, k, f)}" for c, k, f, _ in columns(args.horizon)), flush=True)
        write_json_atomic(report_path, with_command(" && ".join(report["commands"]), report, sort_keys=True),
                          sort_keys=False)
    write_text_atomic(out / "results.md", markdown(report))
    print((out / "results.md").read_text())
    return 0


if __name__ == "__main__":
    raise SystemExit(reporting_errors("pile_yardstick.py", main))
