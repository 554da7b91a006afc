"""Serving speed of ``iwsim play``: frames per second per client and key-to-frame latency.

Starts the real server (``iwsim play``) once per configuration and drives it with N
WebSocket clients that behave like the page: a key press every 0.4-0.6 s (not aligned with
the control steps), held for 0.2 s with the target sent twice per control step, as the
page does. Latency is from sending a press's first action to receiving the first frame
that acknowledges it (``ack``); the page shows the same figure measured from the key
event. With ``--browser`` one more run drives the real page in Debian's chromium and reads
the page's own counters.

    MUJOCO_GL=egl .venv/bin/python bench/bench_play.py --checkpoint checkpoints/pusht-64

Writes ``results.json``, ``results.md`` and ``latency.png`` to ``--out``.
"""

from __future__ import annotations

import argparse
import json
import os
import random
import threading
import time
from pathlib import Path

import numpy as np

from iwsim.core.errors import reporting_errors
from iwsim.eval.records import command_line
from iwsim.play.client import Server, client, summary

REPO = Path(__file__).resolve().parents[1]
SERVER_LOG = REPO / "outputs" / "bench_play_server.log"  # the last server's log
CHROMIUM_FLAGS = ["--no-sandbox", "--disable-gpu", "--disable-background-networking",
                  "--disable-component-update", "--no-first-run"]


def run_clients(checkpoint: str, hz: float, n: int, warmup: float, seconds: float) -> dict:
    server = Server(checkpoint, hz, n, SERVER_LOG)
    try:
        outs = [{} for _ in range(n)]
        threads = [threading.Thread(target=client, args=(server.ws_url, hz, warmup, seconds, i, outs[i]))
                   for i in range(n)]
        for t in threads:
            t.start()
        for t in threads:
            t.join()
    finally:
        server.close()
    if any("frame_times" not in o for o in outs):
        raise RuntimeError("a client failed; see the traceback above")
    fps = [len(o["frame_times"]) / seconds for o in outs]
    lat = np.concatenate([o["latencies"] for o in outs])
    return {"kind": "websocket", "clients": n, "hz": hz, "seconds": seconds, "fps_per_client": fps,
            "fps_min": min(fps), "latency_ms": summary(lat), "latencies": lat.round(2).tolist(),
            "step_ms_mean": float(np.mean(np.concatenate([o["step_ms"] for o in outs])))}


def run_browser(checkpoint: str, hz: float, warmup: float, seconds: float, out: Path) -> dict:
    """The real page in chromium: key taps every 0.4-0.6 s; the page's own fps and latency."""
    from playwright.sync_api import sync_playwright

    server = Server(checkpoint, hz, 1, SERVER_LOG)
    rng = random.Random(0)
    try:
        with sync_playwright() as p:
            browser = p.chromium.launch(executable_path="/usr/bin/chromium", args=CHROMIUM_FLAGS)
            page = browser.new_page(viewport={"width": 1500, "height": 800})
            page.goto(f"http://127.0.0.1:{server.port}/")
            page.wait_for_function("window.iwsim.stats.frames > 2", timeout=60_000)
            keys = "dadajlj"
            t0 = time.perf_counter()
            i = 0
            while time.perf_counter() < t0 + warmup:
                time.sleep(0.1)
            page.evaluate("window.iwsim.state.latencies.length = 0")
            frames0 = page.evaluate("window.iwsim.stats.frames")
            t1 = time.perf_counter()
            while time.perf_counter() < t1 + seconds:
                page.keyboard.down(keys[i % len(keys)])
                time.sleep(0.15)
                page.keyboard.up(keys[i % len(keys)])
                i += 1
                time.sleep(rng.uniform(0.25, 0.45))
            frames = page.evaluate("window.iwsim.stats.frames") - frames0
            elapsed = time.perf_counter() - t1
            lat = np.array(page.evaluate("window.iwsim.state.latencies"))
            page.screenshot(path=str(out / f"page_{hz:g}hz.png"))
            browser.close()
    finally:
        server.close()
    return {"kind": "chromium", "clients": 1, "hz": hz, "seconds": elapsed, "fps_per_client": [frames / elapsed],
            "fps_min": frames / elapsed, "latency_ms": summary(lat), "latencies": lat.round(2).tolist(),
            "step_ms_mean": None}


def markdown(rows: list[dict], meta: dict, command: str) -> str:
    lines = [
        "# iwsim play: serving speed", "",
        f"`{command}`", "",
        f"Machine: {meta['cpus']} CPU cores, no GPU; model {meta['checkpoint']} (64x64). Server and clients on "
        "the same machine. Latency: from sending a key press's first action to the first frame that "
        "acknowledges it (chromium rows: from the key event, as the page shows it).", "",
        "| client | clients | control rate | frames/s per client (min) | key-to-frame p50 | p95 | max "
        "| presses | tick compute |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        lat = r["latency_ms"]
        step = "" if r["step_ms_mean"] is None else f"{r['step_ms_mean']:.1f} ms"
        lines.append(f"| {r['kind']} | {r['clients']} | {r['hz']:g} Hz | {r['fps_min']:.1f} | "
                     f"{lat.get('p50', float('nan')):.0f} ms | {lat.get('p95', float('nan')):.0f} ms | "
                     f"{lat.get('max', float('nan')):.0f} ms | {lat['n']} | {step} |")
    lines += ["", "Targets: one client >= 15 frames/s with p95 key-to-frame <= 100 ms; four clients "
              ">= 10 frames/s each.", ""]
    return "\n".join(lines)


def plot(rows: list[dict], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7, 4))
    for r in rows:
        x = np.sort(r["latencies"])
        if len(x):
            label = f"{r['kind']}, {r['clients']} client(s), {r['hz']:g} Hz"
            ax.plot(x, np.arange(1, len(x) + 1) / len(x), label=label)
    ax.axvline(100, color="grey", ls="--", lw=1)
    ax.set_xlabel("key-to-frame latency (ms)")
    ax.set_ylabel("fraction of presses")
    ax.set_title("iwsim play: key-to-frame latency")
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--checkpoint", default="checkpoints/pusht-64")
    p.add_argument("--configs", default="1@10,1@20,4@10,4@15",
                   help="clients@hz, comma-separated (default: %(default)s)")
    p.add_argument("--seconds", type=float, default=20.0, help="measured seconds per configuration")
    p.add_argument("--warmup", type=float, default=3.0)
    p.add_argument("--browser", default="10,20", help="control rates of the chromium runs ('' for none)")
    p.add_argument("--out", default="bench/results/play")
    args = p.parse_args()
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    rows = []
    for spec in filter(None, args.configs.split(",")):
        n, hz = spec.split("@")
        print(f"{n} client(s) at {hz} Hz ...", flush=True)
        rows.append(run_clients(args.checkpoint, float(hz), int(n), args.warmup, args.seconds))
        print(f"  {rows[-1]['fps_per_client']} frames/s, latency {rows[-1]['latency_ms']}", flush=True)
    for hz in filter(None, args.browser.split(",")):
        print(f"chromium at {hz} Hz ...", flush=True)
        rows.append(run_browser(args.checkpoint, float(hz), args.warmup, args.seconds, out))
        print(f"  {rows[-1]['fps_min']:.1f} frames/s, latency {rows[-1]['latency_ms']}", flush=True)
    command = command_line(__file__)
    meta = {"cpus": os.cpu_count(), "checkpoint": args.checkpoint}
    (out / "results.json").write_text(json.dumps({"command": command, "meta": meta, "runs": rows}, indent=1))
    (out / "results.md").write_text(markdown(rows, meta, command))
    plot(rows, out / "latency.png")
    print((out / "results.md").read_text())


if __name__ == "__main__":
    raise SystemExit(reporting_errors("bench_play.py", main))
