"""The world model's fixed yardstick (issue 23): what users do with a model, one table row per model.

    MUJOCO_GL=egl python bench/yardstick.py --models shipped=checkpoints/pusht-64 \\
        scale750=runs/scale/checkpoints/00000750

For each model, on one thread by default (about 20 minutes a model on this CPU):

1. Held-out play episodes (``--data``, never trained on), open loop from their first
   frame for 192 steps under the recorded actions (:func:`iwsim.yardstick.fidelity.score`): a T fits
   the block (share of frames), pushers visible and their median error at step 32, the
   action gap at step 5 (another episode's actions over the true ones: 1 means ignored),
   PSNR over steps 1-192 beside repeating the first frame.
2. Teleoperation: the pixel expert drives the model from 32 MuJoCo first frames (the
   datagen study's candidates); takes kept at pixel IoU 0.9 and the mean max IoU, beside
   MuJoCo's.
3. Ranking: the policy-eval study's 8 scripted policies from the same seeds in MuJoCo and
   in the model; Pearson r, Spearman rho, MMRV and the spread of the model's scores.
4. Stability: a 2000-step play run under MuJoCo's executed targets; share of decoded
   frames (every 10th) in which a T is detected.
5. Speed: single-stream steps/s and frames/s at batch 64, at the run's thread count (the
   targets are stated at 2 threads; never time beside a training run).
6. The codec's ceiling: the frames of MuJoCo's kept takes that score as a success (pixel
   IoU >= 0.9), encoded and decoded; the share whose reconstruction still scores >= 0.9.
   A take in the model can only be kept if its frames can be, so this bounds item 2.
7. Generalisation (issue 41, :mod:`iwsim.yardstick.families`): operator families from first states
   never used for training, scored in MuJoCo and in the model; per family the offset
   (model - MuJoCo) with its 95% interval, marked seen when the model's training data
   held its kind of motion (``--trained-on``); pooled r and MMRV over all (family,
   episode) pairs and over the unseen families'. And the idle measure: the pushers held
   still, the share of frames that keep the block crisp and in place.
8. Contact, then rest (issue 64, :func:`iwsim.yardstick.families.contact_rest`): the expert
   pushes the block in MuJoCo, the pushers withdraw and rest; the model replays MuJoCo's
   commands. Over the episodes whose block moved: the T's fit in the model's last frame
   against the codec's rendering of MuJoCo's (the share back within 0.02 of it), and the
   pose error.

With ``--paired-episodes N,N,...`` the families part also judges the paired estimates
(:mod:`iwsim.eval.paired`): each family is a policy whose real mean max IoU is estimated
from the model's episodes and MuJoCo's first N of the same first states, against MuJoCo's
mean over ``--paired-holdout`` other first states (seeds from
:data:`iwsim.yardstick.families.HOLDOUT_SEED`): the intervals' coverage, their width
against N MuJoCo episodes alone, and the ranking of the estimates.

``--parts`` picks which of these to run (``families,idle`` alone: about 20 minutes a
model); a model's row keeps the parts measured before.

Results are cached per model under ``--work`` (keyed by the model's weights), so adding a
model evaluates only that one; ``--out`` gets results.json and results.md with every
model evaluated so far, the targets and the trivial baselines, and expert_strip.png: the
pixel expert's first 100 steps from seed 100000, a frame every 10 steps, one row per model
in the order of the table, then MuJoCo.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np
import torch

from iwsim.commands.common import numbers
from iwsim.core.checkpoint import load_json, named_checkpoints, write_json_atomic, write_text_atomic
from iwsim.core.errors import InputError, check_positive, reporting_errors
from iwsim.core.resources import set_threads
from iwsim.eval.paired import judged_table
from iwsim.eval.policy import check_model_task
from iwsim.eval.profiling import speed, stability, strip_steps, write_run_strip
from iwsim.eval.ranking import agreement
from iwsim.eval.records import command_line, with_command
from iwsim.eval.trust import calibration_figure
from iwsim.experiments.common import evaluate_policies, fingerprint
from iwsim.experiments.demos import PUSHT
from iwsim.experiments.policy_eval import PolicyEvalConfig
from iwsim.world_model import WorldModel
from iwsim.yardstick import families as fam
from iwsim.yardstick.codec import codec_ceiling, goal_frames
from iwsim.yardstick.fidelity import Episodes, score
from iwsim.yardstick.studies import TELEOP_SEED, strip, teleop

RANK_SEED = 100000
STABILITY_EVERY = 10
# (column, key, format, target as text)
COLUMNS = [
    ("T kept (play, 192)", "t_found", "{:.0%}", ">= 95%"),
    ("pushers visible", "pusher_visible", "{:.0%}", ">= 95%"),
    ("pusher err px @32", "pusher_err_32", "{:.1f}", "<= 2"),
    ("action gap @5", "action_gap_5", "{:.2f}", "> 1"),
    ("PSNR 1-192 (repeat first)", "psnr_play", "{:.2f}", "first + 4"),
    ("teleop kept", "teleop_kept", "{}", ">= 26/32"),
    ("teleop mean max IoU", "teleop_iou", "{:.3f}", "-"),
    ("rank r", "pearson", "{:.2f}", ">= 0.9"),
    ("rank rho", "spearman", "{:.2f}", "-"),
    ("MMRV", "mmrv", "{:.3f}", "<= 0.05"),
    ("spread", "spread", "{:.2f}", ">= 0.5"),
    ("T kept (2000 steps)", "stable_t", "{:.0%}", ">= 90%"),
    ("goal frames kept by the codec", "codec_goal", "{:.0%}", "-"),
    ("steps/s (1 stream)", "steps_per_s", "{:.0f}", ">= 50 @2 threads"),
    ("frames/s (batch 64)", "frames_per_s_batch64", "{:.0f}", ">= 100 @2 threads"),
]


def ranking(name: str, ckpt: str | None, work: Path, episodes: int, steps: int) -> dict[str, float]:
    """Mean max IoU of each scripted policy in the model (MuJoCo when ``ckpt`` is None)."""
    seeds = list(range(RANK_SEED, RANK_SEED + episodes))
    res = evaluate_policies(PolicyEvalConfig().scripted(), "pusht" if ckpt is None else "world-model", seeds=seeds,
                            steps=steps, world_model=ckpt, out=work / "eval" / name, progress=False)
    return {n: r["mean_max_iou"] for n, r in res.items()}


PARTS = ("core", "families", "idle", "rest")  # core: items 1-6 of the docstring; rest: item 8


def generalisation(name: str, ckpt: str, args: argparse.Namespace, work: Path, mujoco: dict, seen: list[str]
                   ) -> dict:
    """Item 7 for one model: its families beside MuJoCo's (:func:`families.compare`)."""
    t0 = time.perf_counter()
    scores, signals = fam.family_scores(ckpt, work, args.families, args.family_seeds, args.steps, args.zoo,
                                        args.jobs, samples=args.trust_samples)
    result = fam.compare(mujoco["families"], scores, seen, signals)
    result.update(seen=seen, scores=scores, signals=signals, minutes=(time.perf_counter() - t0) / 60)
    if args.paired_episodes:
        result["paired"] = fam.paired_families(mujoco["families"], scores, mujoco["families_holdout"],
                                               args.paired_episodes, signals)
    return result


def evaluate(name: str, ckpt: str, args: argparse.Namespace, work: Path, mujoco: dict,
             goals: np.ndarray | None) -> dict:
    """Items 1-6 for one model (cached under ``work`` by its weights); ``goals``: the
    success frames of MuJoCo's takes (:func:`goal_frames`)."""
    key = {"model": fingerprint(ckpt), "data": args.data, "episodes": args.episodes, "steps": args.steps,
           "horizon": args.horizon, "speed_calls": args.speed_calls,
           "candidates": args.candidates, "stability": args.stability_steps, "threads": args.threads}
    cached = work / "models" / f"{name}.json"
    if cached.is_file() and (saved := load_json(cached))["key"] == key:
        result = saved["result"]
        if "codec_goal" not in result:  # a row from before the ceiling was measured
            result["codec_goal"] = codec_ceiling(WorldModel.load(ckpt), goals)
            write_json_atomic(cached, {"key": key, "result": result})
        return result
    t0 = time.perf_counter()
    wm = WorldModel.load(ckpt)
    play = Episodes(args.data, args.episodes)
    h = min(args.horizon, play.length - 1)
    held, _, _ = score(wm, play, h)
    held["psnr_play"], held["psnr_play_first"] = held[f"psnr_1_{h}"], held[f"psnr_first_1_{h}"]
    t_play = time.perf_counter() - t0
    tele = teleop(name, ckpt, work, args.candidates, TELEOP_SEED, args.steps)
    scores = ranking(name, ckpt, work, args.episodes, args.steps)
    names = sorted(mujoco["ranking"], key=lambda n: -mujoco["ranking"][n])
    agree = agreement([mujoco["ranking"][n] for n in names], [scores[n] for n in names], ("MuJoCo", name))
    t_studies = time.perf_counter() - t0 - t_play
    runs = stability({name: wm}, args.stability_steps, every=STABILITY_EVERY, progress=False)
    fast = speed(wm, play.img[0, 0], n=args.speed_calls)
    result = {
        "checkpoint": str(ckpt), **held, "teleop_kept": f"{tele['kept']}/{tele['candidates']}",
        "teleop_rate": tele["acceptance_rate"], "teleop_iou": tele["mean_candidate_max_iou"],
        "ranking": scores, "pearson": agree["pearson"], "spearman": agree["spearman"], "mmrv": agree["mmrv"],
        "spread": float(np.ptp(list(scores.values()))), "stable_t": float(runs[name]["detected"].mean()),
        "stable_t_mujoco": float(runs["mujoco"]["detected"].mean()), **fast, "threads": args.threads,
        "codec_goal": codec_ceiling(wm, goals),
        "minutes": {"play": t_play / 60, "studies": t_studies / 60,
                    "total": (time.perf_counter() - t0) / 60}}
    cached.parent.mkdir(parents=True, exist_ok=True)
    write_json_atomic(cached, {"key": key, "result": result})
    return result


def scaling_figure(path: Path, models: dict[str, dict], mujoco: dict) -> None:
    """The yardstick's object measures against the training steps of one run."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    steps = [int(Path(r["checkpoint"]).name) for r in models.values()]
    rows = [("T kept, held-out play (192 steps)", "t_found", 1.0), ("T kept, 2000-step run", "stable_t", 1.0),
            ("teleop mean max IoU", "teleop_iou", mujoco["teleop"]["mean_candidate_max_iou"]),
            ("PSNR 1-192 minus repeat-first (dB)", None, None)]
    fig, axes = plt.subplots(1, len(rows), figsize=(4 * len(rows), 3.2))
    for ax, (title, key, ref) in zip(axes, rows):
        if key is None:
            ys = [r["psnr_play"] - r["psnr_play_first"] for r in models.values()]
            ax.axhline(4.0, color="k", ls=":", label="target")
        else:
            ys = [r[key] for r in models.values()]
            ax.axhline(ref, color="k", ls="--", label="MuJoCo")
        ax.plot(steps, ys, "o-")
        ax.set_title(title, fontsize=9), ax.set_xlabel("training steps"), ax.grid(alpha=0.3), ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def cell(r: dict, key: str, fmt: str) -> str:
    v = r.get(key)
    if v is None:
        return "undefined"
    text = fmt.format(v)
    if key == "psnr_play":
        text += f" ({r['psnr_play_first']:.2f})"
    return text


def contact_rest_markdown(report: dict) -> list[str]:
    """Item 8's table: one row per model with the measure."""
    rows = {n: r["contact_rest"] for n, r in report["models"].items() if "fit_model" in r.get("contact_rest", {})}
    if not rows:
        return []
    c0 = next(iter(rows.values()))
    ref = report["mujoco"].get("contact_rest", {})
    lines = ["", "## Contact, then rest (issue 64)", "",
             f"From {c0['episodes']} fresh MuJoCo starts (seeds from {fam.REST_SEED}) the pixel expert pushes for "
             f"{c0['push_steps']} steps, the pushers withdraw {fam.WITHDRAW_M * 100:g} cm and rest "
             f"{c0['rest_steps']} steps; the model replays MuJoCo's commands. Over the {c0['moved']} episodes whose "
             "block moved: the T's outline fit in the last frame, the share back within 0.02 of the codec's "
             "rendering of MuJoCo's last frame, and the pose error against MuJoCo's (median)."
             + ("" if ref.get("fit_mujoco") is None else f" MuJoCo's own fit: {ref['fit_mujoco']:.3f}."), "",
             "| model | T fit | codec's fit | back to the codec's level | pose error px / deg | crisp and in place |",
             "|---|---|---|---|---|---|", "| target | - | - | >= 90% | - | - |"]
    for n, c in rows.items():
        err = "no T found" if c["pose_err_px"] is None else f"{c['pose_err_px']:.1f} / {c['pose_err_deg']:.1f}"
        lines.append(f"| {n} | {c['fit_model']:.3f} | {c['fit_codec']:.3f} | {c['back_to_codec']:.0%} | {err} | "
                     f"{c['crisp_in_place']:.0%} |")
    return lines


def generalisation_markdown(report: dict) -> list[str]:
    """Item 7's tables: one row per model for the pooled figures and the idle measure, then
    each model's families."""
    rows = {n: r for n, r in report["models"].items() if "generalisation" in r or "idle" in r}
    if not rows:
        return []
    m = report["mujoco"]
    lines = ["", "## Generalisation: operator families and the idle measure (issue 41)", "",
             f"Families from {report.get('family_seeds')} MuJoCo first states (seeds from {fam.SEED}, never used "
             f"for training), {report['steps']} steps; the score of an episode is its max pixel IoU. A family is "
             "*seen* when the model's training data held its kind of motion; the targets count the unseen ones. "
             "The learned family's policies are trained on MuJoCo demonstrations of the expert; no world model "
             "here trains on their rollouts (one trained on `learned-zoo` saw those of other policies: other "
             "demonstrations, other training seeds)." + ("" if "idle_episodes" not in report else
             f" Idle: the pushers held still for {fam.IDLE_STEPS} steps from {report['idle_episodes']} fresh "
             f"starts; a frame keeps the block when the T fits >= {fam.CRISP} and lies within "
             f"{fam.IN_PLACE_PX:g} px and {fam.IN_PLACE_DEG:g} degrees of MuJoCo's."), "",
             "| model | unseen: max abs offset | unseen: r | unseen: MMRV | all: r | all: MMRV | idle: block kept "
             "| idle: T fit @10/@20/@50 | trust: rho(novelty, abs error) | minutes |",
             "|---|---|---|---|---|---|---|---|---|---|",
             "| target | <= 0.10 | >= 0.9 | - | - | - | >= 95% | - | > 0 | - |"]
    if "idle" in m:
        i = m["idle"]
        lines.append(f"| MuJoCo | 0 | 1 | 0 | 1 | 0 | 100% | {i['fit_10']:.3f} / {i['fit_20']:.3f} / "
                     f"{i[f'fit_{fam.IDLE_STEPS}']:.3f} | - | - |")
    for n, r in rows.items():
        g, i = r.get("generalisation"), r.get("idle")
        u, a = (g or {}).get("pooled", {}).get("unseen"), (g or {}).get("pooled", {}).get("all")
        cells = [f"{u['max_abs_offset']:.2f}", f"{u['pearson']:.2f}", f"{u['mmrv']:.3f}"] if u else ["-"] * 3
        cells += [f"{a['pearson']:.2f}", f"{a['mmrv']:.3f}"] if a else ["-"] * 2
        cells += [f"{i['kept']:.0%}", f"{i['fit_10']:.3f} / {i['fit_20']:.3f} / {i[f'fit_{fam.IDLE_STEPS}']:.3f}"] \
            if i else ["-"] * 2
        cells.append(novelty_rho((g or {}).get("trust", {})))
        lines.append(f"| {n} | " + " | ".join(cells) + f" | {(g or {}).get('minutes', 0):.0f} |")
    pairs = report.get("trust_pairs", {})
    if pairs:
        lines += ["", "The ensemble trust signal (`iwsim eval policy --trust-model`): each episode's score "
                  "difference between the model and a partner model, against the model's error |model - MuJoCo| "
                  "over all family episodes (Spearman rho; > 0: it ranks episodes by their error).", "",
                  "| model = partner | rho(disagreement, abs error) | episodes |", "|---|---|---|"]
        for pair, t in pairs.items():
            rho = "undefined" if t["spearman_error"] is None else f"{t['spearman_error']:.2f}"
            lines.append(f"| {pair} | {rho} | {t['episodes']} |")
    lines += trust_markdown(rows)
    lines += paired_markdown(rows)
    for n, r in rows.items():
        g = r.get("generalisation")
        if not g:
            continue
        lines += ["", f"`{n}` (seen: {', '.join(g['seen']) or 'none'}):", "",
                  "| family | what | MuJoCo | model | offset [95%] | seen | novelty |", "|---|---|---|---|---|---|---|"]
        for f, row in g["families"].items():
            lo, hi = row["offset_interval"]
            nov = f"{row['novelty']:.2f}" if "novelty" in row else "-"
            lines.append(f"| {f} | {fam.FAMILIES[f][1]} | {row['mujoco']:.3f} | {row['model']:.3f} | "
                         f"{row['offset']:+.3f} [{lo:+.2f}, {hi:+.2f}] | {'seen' if row['seen'] else 'unseen'} "
                         f"| {nov} |")
    return lines


def paired_markdown(rows: dict) -> list[str]:
    """The paired estimates of each model with them: per n the coverage, the widths and the
    ranking of the estimates beside the model's own scores, then per family."""
    lines: list[str] = []
    for n, r in rows.items():
        pr = (r.get("generalisation") or {}).get("paired")
        if not pr:
            continue
        lines += ["", f"Paired estimates of `{n}`: each family's real mean max IoU from the model's episodes and "
                  f"MuJoCo's first n of the same first states, judged against MuJoCo's mean over "
                  f"{pr['holdout_episodes']} other first states (seeds from {pr['holdout_seed']}); {pr['method']}. "
                  "Targets: coverage >= 90%, half-width <= 0.75x of n MuJoCo episodes alone, r >= 0.9 and "
                  "MMRV <= 0.05 at n = 5.", "",
                  "| n | weighting | coverage (n MuJoCo alone) | median half-width | against n MuJoCo alone | "
                  "r (the model's own; n MuJoCo alone) | MMRV (the model's own; n MuJoCo alone) |",
                  "|---|---|---|---|---|---|---|"]
        parts = {"the model as it is": pr["by_n"], **{f"distrusted where `{s}` > {t['warn']:g}": t["by_n"]
                                                    for s, t in pr.get("trust_weighted", {}).items()}}
        for k in pr["by_n"]:
            for what, by_n in parts.items():
                j = by_n[k]
                a, m, r, ratio = (j["agreement"], j["agreement_model"], j["agreement_real_alone"],
                                  j["median_half_width_ratio"])
                lines.append(f"| {k} | {what} | {j['coverage']:.0%} ({j['coverage_real_alone']:.0%}) | "
                             f"{j['median_half_width']:.3f} | {'-' if ratio is None else f'{ratio:.2f}x'} | "
                             f"{fmt(a['pearson'])} ({fmt(m['pearson'])}; {fmt(r['pearson'])}) | "
                             f"{fmt(a['mmrv'], 3)} ({fmt(m['mmrv'], 3)}; {fmt(r['mmrv'], 3)}) |")
        lines += ["", *judged_table(pr["by_n"], "family")]
        lines += ["", "(* : the interval misses the held-out mean.)"]
    return lines


def fmt(x: float | None, digits: int = 2) -> str:
    return "undefined" if x is None else f"{x:.{digits}f}"


def novelty_rho(trust: dict) -> str:
    """The novelty column: its rho over all family episodes (a report from before the
    other signals kept it as ``spearman_error``)."""
    rho = trust.get("spearman_error") if "spearman_error" in trust else \
        trust.get("spearman", {}).get("novelty", {}).get("all")
    return "no signal" if rho is None else f"{rho:.2f}"


def trust_markdown(rows: dict) -> list[str]:
    """The per-episode trust signals (:mod:`iwsim.eval.trust`) of each model with them: how
    well each ranks the family episodes by their error, and the error predictor fitted on
    the seen families and judged on the unseen ones."""
    lines: list[str] = []
    for n, r in rows.items():
        t = (r.get("generalisation") or {}).get("trust", {})
        if "spearman" not in t:
            continue
        eps = t["episodes"]
        lines += ["", f"Trust signals of `{n}`: Spearman rho of each episode's signal against its error "
                  f"|model - MuJoCo| over the seen families' {eps['seen']} episodes, the unseen ones' "
                  f"{eps['unseen']} and all (target on the unseen: >= 0.5); the predictor (a ridge regression of "
                  "the error on the standardised signals and the model's score) is fitted on the seen families' "
                  "episodes only. Flagged: the mean error of the unseen episodes each flags first (its top 20%), "
                  f"against {np.mean(t['error_unseen']):.3f} over all of them.", "",
                  "| signal | rho seen | rho unseen | rho all | unseen error of the flagged 20% |",
                  "|---|---|---|---|---|"]

        def f(x: float | None) -> str:
            return "-" if x is None else f"{x:.2f}"

        for name, rho in t["spearman"].items():
            flagged = next(c["flagged_error"] for c in t["calibration"][name] if c["share"] == 0.2)
            lines.append(f"| {name} | {f(rho['seen'])} | {f(rho['unseen'])} | {f(rho['all'])} | {flagged:.3f} |")
        if "predictor" in t:
            pr = t["predictor"]
            flagged = next(c["flagged_error"] for c in pr["calibration"] if c["share"] == 0.2)
            weights = ", ".join(f"{k} {v:+.3f}" for k, v in pr["weights"].items())
            lines.append(f"| predictor ({weights}) | (fitted) | {f(pr['spearman_unseen'])} | - | {flagged:.3f} |")
    return lines


def trust_figures(out: Path, report: dict) -> None:
    """``trust_<model>.png``: the calibration of each signal on the unseen family episodes."""
    for n, r in report["models"].items():
        g = r.get("generalisation") or {}
        t = g.get("trust", {})
        if "spearman" not in t or not t["error_unseen"]:
            continue
        unseen = [f for f in g["families"] if not g["families"][f]["seen"]]
        err = np.asarray(t["error_unseen"])
        sig = g.get("signals", {})
        curves = {name: (np.concatenate([sig[name][f] for f in unseen]), err) for name in t["spearman"] if name in sig}
        if "predictor" in t:
            curves["predictor"] = (np.asarray(t["predictor"]["per_episode_unseen"]), err)
        calibration_figure(out / f"trust_{n}.png", curves, f"{n}: trust signals on the unseen families "
                           f"({len(err)} episodes)")


def markdown(report: dict, strip_rows: list[str]) -> str:
    lines = ["# The world model's yardstick (`bench/yardstick.py`)", "", "Commands, in the order they were run:", "",
             *(f"    {c}" for c in report["commands"])]
    if "ranking" in report["mujoco"]:
        lines += core_markdown(report, strip_rows)
    return "\n".join(lines + generalisation_markdown(report) + contact_rest_markdown(report)) + "\n"


def core_markdown(report: dict, strip_rows: list[str]) -> list[str]:
    """Items 1-6's tables: one row per model, then the scripted policies' scores."""
    m = report["mujoco"]
    lines = ["", f"Held-out play: {report['episodes']} episodes of `{report['data']}`, {report['horizon']} steps "
             "open loop. "
             f"Teleoperation: the pixel expert from {report['candidates']} MuJoCo first frames (seeds from "
             f"{TELEOP_SEED}), kept at pixel IoU 0.9. Ranking: 8 scripted policies x {report['episodes']} "
             f"episodes x {report['steps']} steps from seed {RANK_SEED}. Stability: {report['stability_steps']} "
             f"play steps, every {STABILITY_EVERY}th frame decoded. Speed at the thread count in brackets. "
             f"`expert_strip.png`: the pixel expert's first 100 steps, one row per model ({', '.join(strip_rows)}), "
             "MuJoCo last; `run_strip.png`: the stability run's frames at steps "
             f"{', '.join(map(str, strip_steps(report['stability_steps'])))}, the same rows.", "",
             "| model | " + " | ".join(c for c, *_ in COLUMNS) + " | minutes |",
             "|---" * (len(COLUMNS) + 2) + "|",
             "| target | " + " | ".join(t for *_, t in COLUMNS) + " | ~20 |"]
    mj = {"t_found": 1.0, "teleop_kept": m["teleop"]["kept_text"], "teleop_iou": m["teleop"]["mean_candidate_max_iou"],
          "pearson": 1.0, "spearman": 1.0, "mmrv": 0.0, "spread": float(np.ptp(list(m["ranking"].values()))),
          "stable_t": m.get("stable_t")}
    lines.append("| MuJoCo | " + " | ".join("-" if mj.get(k) is None else cell(mj, k, f) for _, k, f, _ in COLUMNS)
                 + " | - |")
    core = {n: r for n, r in report["models"].items() if "t_found" in r}
    for name, r in core.items():
        speed_cells = {"steps_per_s", "frames_per_s_batch64"}
        row = [cell(r, k, f) + (f" ({r['threads']})" if k in speed_cells else "") for _, k, f, _ in COLUMNS]
        lines.append(f"| {name} | " + " | ".join(row) + f" | {r['minutes']['total']:.0f} |")
    lines += ["", "Scripted policies' mean max IoU (MuJoCo, then each model):", "",
              "| policy | MuJoCo | " + " | ".join(core) + " |", "|---" * (len(core) + 2) + "|"]
    for n in sorted(m["ranking"], key=lambda n: -m["ranking"][n]):
        lines.append(f"| {n} | {m['ranking'][n]:.3f} | "
                     + " | ".join(f"{r['ranking'][n]:.3f}" for r in core.values()) + " |")
    return lines


def parse_seen(items: list[str], models: dict[str, str]) -> dict[str, list[str]]:
    """``--trained-on NAME=POLICY,POLICY`` (the policies ``iwsim collect`` recorded its
    training data with) -> the families each model has seen. A model not named has seen
    the shipped model's (play and the noisy expert)."""
    seen = {n: fam.seen_families(["play", "expert-noisy"]) for n in models}
    for item in items:
        name, sep, policies = item.partition("=")
        if not sep or name not in models:
            raise ValueError(f"--trained-on takes NAME=POLICY,... for a model of --models, got {item!r}.")
        seen[name] = fam.seen_families([p for p in policies.split(",") if p])
    return seen


def read_report(path: Path) -> dict:
    """A yardstick report (``results.json``) to merge, or one line of error."""
    report = load_json(path, "--merge report")
    if not (isinstance(report, dict) and isinstance(report.get("models"), dict) and "mujoco" in report
            and "commands" in report):
        raise InputError(f"--merge {path} is not a report of bench/yardstick.py (its results.json).")
    return report


def check_trust_pairs(pairs: list[str], names: list[str]) -> None:
    """Each ``MODEL=PARTNER`` names two models of this run or of its reports: checked
    before any work (whether both have the families part shows only after it)."""
    for pair in pairs:
        a, sep, b = pair.partition("=")
        unknown = [n for n in (a, b) if n not in names]
        if not sep or not a or not b or a == b or unknown:
            raise InputError(f"--trust-pairs takes MODEL=PARTNER, two models of --models or of the report, got "
                             f"{pair!r}" + (f" ({', '.join(map(repr, unknown))} unknown)" if sep and unknown else "")
                             + ".")


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--models", nargs="+", required=True, help="NAME=CHECKPOINT_OR_RUN world models")
    p.add_argument("--parts", default=",".join(PARTS), help=f"which parts to run, of {', '.join(PARTS)} "
                   "(default: all)")
    p.add_argument("--data", default="data/play_eval.zarr", help="held-out play store (default: %(default)s)")
    p.add_argument("--episodes", type=int, default=20,
                   help="held-out episodes, and ranking episodes per policy (default: %(default)s)")
    p.add_argument("--steps", type=int, default=300, help="steps of a teleop take / ranking episode / family "
                   "episode (default: %(default)s)")
    p.add_argument("--candidates", type=int, default=32, help="teleoperation takes (default: %(default)s)")
    p.add_argument("--stability-steps", type=int, default=2000, help="(default: %(default)s)")
    p.add_argument("--horizon", type=int, default=192, help="open-loop steps on held-out play (default: %(default)s)")
    p.add_argument("--speed-calls", type=int, default=100, help="timed steps per speed test (default: %(default)s)")
    p.add_argument("--threads", type=int, default=1, help="torch threads (default: %(default)s)")
    p.add_argument("--jobs", type=int, default=1, help="families evaluated at once, in processes of one thread "
                   "(default: %(default)s)")
    p.add_argument("--families", default=",".join(fam.FAMILIES), help="operator families (default: all)")
    p.add_argument("--family-seeds", type=int, default=24, help="first states per family (default: %(default)s)")
    p.add_argument("--rest-episodes", type=int, default=20, help="fresh starts of the contact-then-rest measure "
                   "(default: %(default)s)")
    p.add_argument("--idle-episodes", type=int, default=20, help="fresh starts of the idle measure "
                   "(default: %(default)s)")
    p.add_argument("--zoo", nargs="*", default=[], help="policy runs or checkpoints of the learned family "
                   "(default: none, and no learned family)")
    p.add_argument("--trained-on", nargs="*", default=[], help="NAME=POLICY,...: the collect policies of a "
                   "model's training data, for its seen families (default: play,expert-noisy)")
    p.add_argument("--curve", help="NAME,NAME,...: models of one run (checkpoints named by their step) to plot "
                   "against training steps in scaling.png")
    p.add_argument("--trust-samples", type=int, default=1, help="samples of each model per family episode (its "
                   "noise drawn again), for the sample-spread trust signal (default: %(default)s: none)")
    p.add_argument("--trust-pairs", nargs="*", default=[], help="MODEL=PARTNER: the ensemble trust signal, "
                   "each family episode's |MODEL - PARTNER| against MODEL's error (both with the families part)")
    p.add_argument("--merge", nargs="*", default=[], help="reports (results.json) of yardstick runs made side by "
                   "side into other --out directories: their models' rows join this report's")
    p.add_argument("--paired-episodes", help="N,N,...: judge the paired estimates of each family from its first N "
                   "first states in both (e.g. 2,5,10; default: none)")
    p.add_argument("--paired-holdout", type=int, default=50, help="MuJoCo episodes per family, from other first "
                   "states, that judge the paired estimates (default: %(default)s)")
    p.add_argument("--work", default="runs/yardstick", help="cache (default: %(default)s)")
    p.add_argument("--out", default="bench/results/yardstick", help="report directory (default: %(default)s)")
    args = p.parse_args(argv)
    parts = [x for x in args.parts.split(",") if x]
    args.families = [f for f in args.families.split(",") if f]
    if bad := [x for x in parts if x not in PARTS] + [f for f in args.families if f not in fam.FAMILIES]:
        p.error(f"unknown parts or families {bad}; parts: {', '.join(PARTS)}; families: {', '.join(fam.FAMILIES)}")
    if not args.zoo and fam.LEARNED in args.families:
        args.families.remove(fam.LEARNED)
    check_positive(args, "episodes", "steps", "candidates", "stability_steps", "horizon", "speed_calls", "threads",
                   "trust_samples", "jobs", "family_seeds", "idle_episodes", "rest_episodes", "paired_holdout")
    if args.paired_episodes is not None:
        args.paired_episodes = list(numbers("--paired-episodes", args.paired_episodes, int, "counts N,N,..."))
        if not all(2 <= n <= args.family_seeds for n in args.paired_episodes):
            raise InputError(f"--paired-episodes must be counts in 2..{args.family_seeds} (--family-seeds), got "
                             f"{args.paired_episodes}.")
        if "families" not in parts:
            raise InputError("--paired-episodes judges the families part: add families to --parts.")
    models = named_checkpoints(args.models)
    for name, ckpt in models.items():
        check_model_task(WorldModel.load(ckpt), PUSHT, f"--models {name}={ckpt}")
    try:
        seen = parse_seen(args.trained_on, models)
    except ValueError as e:
        p.error(str(e))
    out = Path(args.out)
    report_path = out / "results.json"
    report = load_json(report_path) if report_path.is_file() else {"models": {}}
    merged = [read_report(Path(path)) for path in args.merge]
    check_trust_pairs(args.trust_pairs, [*models, *report["models"], *(n for m in merged for n in m["models"])])
    set_threads(args.threads)
    torch.manual_seed(0)
    work = Path(args.work)
    out.mkdir(parents=True, exist_ok=True)
    command = command_line(__file__, argv)
    report["commands"] = [c for c in report.get("commands", []) if c != command] + [command]
    for other in merged:  # rows measured side by side into other reports
        report["commands"] = [c for c in report["commands"] if c not in other["commands"]] + other["commands"]
        for name, row in other["models"].items():
            report["models"][name] = {**report["models"].get(name, {}), **row}
        report.setdefault("mujoco", {}).update({k: v for k, v in other["mujoco"].items() if k not in
                                                report.get("mujoco", {})})
        report.update({k: other[k] for k in ("family_seeds", "idle_episodes", "steps") if k in other})
    mujoco = report.setdefault("mujoco", {})
    goals = None

    def save() -> None:
        """The report so far, its first key the commands that made it, in the order they were run."""
        write_json_atomic(report_path, with_command(" && ".join(report["commands"]), report, sort_keys=True),
                          sort_keys=False)

    if "core" in parts:
        mujoco.update(ranking=ranking("mujoco", None, work, args.episodes, args.steps),
                      teleop=teleop("mujoco", None, work, args.candidates, TELEOP_SEED, args.steps))
        goals = goal_frames(work / "teleop" / "mujoco.zarr")  # the store teleop("mujoco") recorded
        mujoco["teleop"]["kept_text"] = f"{mujoco['teleop']['kept']}/{mujoco['teleop']['candidates']}"
        report.update(data=args.data, horizon=args.horizon, episodes=args.episodes, candidates=args.candidates,
                      stability_steps=args.stability_steps)
    if "families" in parts:
        mujoco["families"] = fam.family_scores(None, work, args.families, args.family_seeds, args.steps, args.zoo,
                                               args.jobs)[0]
        report.update(family_seeds=args.family_seeds)
        if args.paired_episodes:
            mujoco["families_holdout"] = fam.family_scores(None, work, args.families, args.paired_holdout, args.steps,
                                                           args.zoo, args.jobs, first_seed=fam.HOLDOUT_SEED)[0]
    if "idle" in parts:
        mujoco["idle"] = {k: v for k, v in fam.idle(None, work, args.idle_episodes).items() if k != "pose"}
        report.update(idle_episodes=args.idle_episodes)
    if "rest" in parts:
        mujoco["contact_rest"] = fam.contact_rest(None, work, args.rest_episodes)
    report["steps"] = args.steps
    for name, ckpt in models.items():
        r = report["models"].get(name, {}) if report["models"].get(name, {}).get("checkpoint") == ckpt else {}
        r["checkpoint"] = ckpt
        if "core" in parts:
            r.update(evaluate(name, ckpt, args, work, mujoco, goals))
            report["mujoco"]["stable_t"] = r["stable_t_mujoco"]
            print(f"{name}: " + ", ".join(f"{c} {cell(r, k, f)}" for c, k, f, _ in COLUMNS), flush=True)
        if "families" in parts:
            r["generalisation"] = generalisation(name, ckpt, args, work, mujoco, seen[name])
            print(f"{name}: generalisation {r['generalisation']['pooled']}", flush=True)
        if "idle" in parts:
            r["idle"] = fam.idle(ckpt, work, args.idle_episodes)
            print(f"{name}: idle block kept {r['idle']['kept']:.0%}", flush=True)
        if "rest" in parts:
            r["contact_rest"] = fam.contact_rest(ckpt, work, args.rest_episodes)
            c = r["contact_rest"]
            print(f"{name}: contact then rest: " + ("no block moved" if "fit_model" not in c else
                  f"T fit {c['fit_model']:.3f} (codec {c['fit_codec']:.3f}), back in {c['back_to_codec']:.0%} "
                  f"of {c['moved']}"), flush=True)
        report["models"][name] = r
        save()
    for pair in args.trust_pairs:
        a, sep, b = pair.partition("=")
        rows = [report["models"].get(n, {}).get("generalisation") for n in (a, b)]
        if not sep or not all(rows):
            p.error(f"--trust-pairs takes MODEL=PARTNER of models with the families part, got {pair!r}")
        report.setdefault("trust_pairs", {})[pair] = fam.ensemble_trust(mujoco["families"], rows[0]["scores"],
                                                                         rows[1]["scores"])
        save()
    if args.curve:
        curve = [n.strip() for n in args.curve.split(",")]
        missing = [n for n in curve if "t_found" not in report["models"].get(n, {})]
        if missing:
            p.error(f"--curve names models without the core part: {', '.join(missing)}")
        scaling_figure(out / "scaling.png", {n: report["models"][n] for n in curve}, report["mujoco"])
    trust_figures(out, report)
    # The strip needs the weights: models evaluated on an earlier machine whose runs are gone drop out of it.
    present = {n: r["checkpoint"] for n, r in report["models"].items() if Path(r["checkpoint"]).is_dir()}
    if len(present) < len(report["models"]):
        print("expert_strip.png leaves out (checkpoint not on this machine): "
              + ", ".join(n for n in report["models"] if n not in present), flush=True)
    if "core" in parts:
        shown = min(100, args.steps)  # the expert's first 100 steps, a frame every 10, or a shorter take's
        strip(out / "expert_strip.png", [*present.values(), None], RANK_SEED, shown, max(1, shown // 10))
        kept = strip_steps(args.stability_steps)
        runs = stability({n: WorldModel.load(c) for n, c in present.items()}, kept[-1], every=kept[-1],
                         progress=False, keep=kept)
        write_run_strip(out / "run_strip.png", runs, [*present, "mujoco"])
    write_text_atomic(out / "results.md", markdown(report, list(present)))
    print((out / "results.md").read_text())
    return 0


if __name__ == "__main__":
    raise SystemExit(reporting_errors("yardstick.py", main))
