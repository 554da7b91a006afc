"""The benchmark's report: ``results.md`` from ``results.json``'s contents."""

from __future__ import annotations

from iwsim.eval.scores import LOWER_IS_BETTER, METRICS

COPY = "copy of the first frame"  # the reference row of the report


def _cell(acc: dict, metric: str, unavailable: dict[str, str], key: str = "mean") -> str:
    if metric in unavailable:
        return unavailable[metric]
    if metric not in acc:
        return "-"
    v = acc[metric]
    digits = 2 if metric in ("psnr", "fid", "fvd") else 4
    if key == "last":
        return f"{v['last']:.{digits}f} +- {v['last_std']:.{digits}f}"
    return f"{v['mean']:.{digits}f}" + (f" +- {v['std']:.{digits}f}" if "std" in v else "")


def compare(result: dict) -> list[str]:
    """Where ours wins and loses against each other model, metric by metric."""
    ours = result["ours"]
    mine = result["models"][ours]["accuracy"]
    lines = []
    for name, entry in result["models"].items():
        if name == ours:
            continue
        wins: list[str] = []
        losses: list[str] = []
        for m in METRICS:
            if m not in mine or m not in entry["accuracy"]:
                continue
            a, b = mine[m]["mean"], entry["accuracy"][m]["mean"]
            better = a <= b if m in LOWER_IS_BETTER else a >= b
            (wins if better else losses).append(f"{m.upper()} {a:.4g} vs {b:.4g}")
        for m in ("psnr", "ssim", "iou_err"):
            a, b = mine[m]["last"], entry["accuracy"][m]["last"]
            better = a <= b if m in LOWER_IS_BETTER else a >= b
            (wins if better else losses).append(f"{m.upper()} at step {result['steps']} {a:.4g} vs {b:.4g}")
        sp = result["models"][ours].get("speed"), entry.get("speed")
        ratio = f"; per frame at batch 1 ours is {sp[1]['step_ms'] / sp[0]['step_ms']:.2f}x as fast" if all(sp) else ""
        lines.append(f"- **vs {name}**: matches or beats on {', '.join(wins) or 'nothing'}; "
                     f"loses on {', '.join(losses) or 'nothing'}{ratio}.")
    return lines


def markdown(r: dict) -> str:
    """The Markdown report of a ``run_benchmark`` result."""
    un = r["unavailable"]
    names = list(r["models"])
    arrows = {m: "↓" if m in LOWER_IS_BETTER else "↑" for m in METRICS}
    lines = [
        "# World-model benchmark (`iwsim bench`)",
        "",
        *([f"`{r['command']}`", ""] if "command" in r else []),
        f"{len(r['episodes'])} held-out episodes of `{r['data']}` x {r['steps']} steps, open loop: context = the first "
        f"frame, then the recorded actions; per-frame metrics on [0, 1] images; mean +- std over episodes of each "
        f"episode's mean. Machine: {r['machine']}.",
        "",
        "| model | " + " | ".join(f"{m.upper()} {arrows[m]}" for m in METRICS) + " |",
        "|---|" + "---|" * len(METRICS),
    ]
    rows = [(n, r["models"][n]["accuracy"]) for n in names]
    rows += [(f"*{n}*", e["accuracy"]) for n, e in r.get("reference", {}).items()]
    for n, acc in rows:
        lines.append(f"| {n} | " + " | ".join(_cell(acc, m, un) for m in METRICS) + " |")
    lines += ["", f"At step {r['steps']}:", "", "| model | PSNR ↑ | SSIM ↑ | IoU error ↓ |", "|---|---|---|---|"]
    for n, acc in rows:
        lines.append(f"| {n} | " + " | ".join(_cell(acc, m, un, "last") for m in ("psnr", "ssim", "iou_err")) + " |")
    lines += ["", "![curves](curves.png)", "", "![frames](frames.png)", "", "## Training and speed", "",
              "| model | objective | training | step at batch 1 (ms) | steps/s | dynamics step (ms) | "
              f"frames/s at batch {_batch(r)} |", "|---|---|---|---|---|---|---|"]
    for n in names:
        e = r["models"][n]
        tr = f"{e['train_steps']} steps, {e['train_minutes']:.1f} min" if "train_steps" in e else "-"
        sp = e.get("speed", {})
        b = _batch(r)
        lines.append(f"| {n} | {e['objective']} | {tr} | {sp.get('step_ms', float('nan')):.1f} | "
                     f"{sp.get('steps_per_s', float('nan')):.1f} | {sp.get('dynamics_step_ms', float('nan')):.1f} | "
                     f"{sp.get(f'frames_per_s_batch{b}', float('nan')):.0f} |")
    if "stability" in r:
        st = r["stability"]
        lines += ["", "## Stability", "",
                  f"{st['steps']} steps under the play policy's actions (MuJoCo renders the same actions), "
                  f"scored every {st['every']} step(s); {st['minutes']:.1f} min for all models. Resident memory "
                  f"{st['memory_mib_first']:.0f} MiB at the start, {st['memory_mib_last']:.0f} MiB at the end.", "",
                  "| | frame mean | frame std | block pixels | block detected | detected, last 10% |",
                  "|---|---|---|---|---|---|"]
        for n, s in [*((n, r["models"][n]["stability"]) for n in names), ("MuJoCo", r["mujoco"]["stability"])]:
            lines.append(f"| {n} | {s['frame_mean']:.4f} | {s['frame_std']:.4f} | {s['block_pixels']:.1f} | "
                         f"{100 * s['block_detected']:.1f}% | {100 * s['block_detected_last_10pct']:.1f}% |")
        lines += ["", "![stability](stability.png)"]
    lines += ["", f"## Ours ({r['ours']}) against each model", "", *compare(r), ""]
    return "\n".join(lines)


def _batch(r: dict) -> int:
    for e in r["models"].values():
        for k in e.get("speed", {}):
            if k.startswith("frames_per_s_batch"):
                return int(k.removeprefix("frames_per_s_batch"))
    return 64
