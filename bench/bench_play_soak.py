"""Soak test of ``iwsim play``: a long session with well-behaved clients and two flood clients.

Starts the real server (``iwsim play`` in a subprocess, as ``bench_play.py`` does) with room
for every client, drives it for ``--seconds`` with ``--clients`` page-like clients (key
presses every 0.4-0.6 s, :func:`iwsim.play.client.client`), one flood client that sends as fast as
it can (valid actions, malformed and oversized messages, and now and then a connection
without the token) and reads what comes back, and one token holder that floods bad
messages and never reads (a tiny receive buffer); both reconnect whenever they are dropped.
Records the well-behaved clients' frames/s and key-to-frame latency (p50/p95, per minute
as well, to show drift), what the flood clients got through, how often the server dropped
the one that never reads, and the server's resident memory every second.

    MUJOCO_GL=egl .venv/bin/python bench/bench_play_soak.py --seconds 300

Writes ``results.json`` and ``results.md`` to ``--out``.
"""

from __future__ import annotations

import argparse
import json
import multiprocessing
import os
import threading
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from iwsim.core.errors import reporting_errors
from iwsim.eval.records import command_line
from iwsim.play.client import Server, client, summary

REPO = Path(__file__).resolve().parents[1]
SERVER_LOG = REPO / "outputs" / "bench_play_soak_server.log"
FLOOD_MESSAGES = [  # sent after each valid action
    "{not json",
    json.dumps({"type": "teleport"}),
    json.dumps({"type": "action", "seq": 1, "action": [0, float("nan"), 0, 0]}),
    '{"type": "action", "pad": "' + "x" * 5000 + '"}',  # over the 4 KiB message limit
    json.dumps({"type": "record"}),
    json.dumps({"type": "discard"}),
]


def rss_mib(pid: int) -> float | None:
    """Resident memory of process ``pid`` in MiB (Linux), or None once it is gone."""
    try:
        for line in Path(f"/proc/{pid}/status").read_text().splitlines():
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) / 1024
    except OSError:
        return None
    return None


@dataclass
class Target:
    """What a flood process needs of the server (``Server`` itself holds the process)."""

    port: int
    ws_url: str


def run_niced(fn, port: int, ws_url: str, seconds: float, results) -> None:
    os.nice(19)
    out: dict = {}
    fn(Target(port, ws_url), seconds, out)
    results.put((fn.__name__, out))


def flood(server: Target, seconds: float, out: dict) -> None:
    """Send as fast as the socket takes it; drain what comes back; knock without the token;
    reconnect whenever the server drops the connection (it must: the messages outrun its
    per-connection rate)."""
    from websockets.exceptions import ConnectionClosed
    from websockets.sync.client import connect

    sent = received = refused = drops = 0
    stop = time.perf_counter() + seconds
    seq = 0
    while time.perf_counter() < stop:
        try:
            with connect(server.ws_url, max_size=None) as ws:
                def drain() -> None:
                    nonlocal received
                    try:
                        while True:
                            ws.recv()
                            received += 1
                    except (ConnectionClosed, OSError):
                        pass

                threading.Thread(target=drain, daemon=True).start()
                while time.perf_counter() < stop:
                    seq += 1
                    for msg in [json.dumps({"type": "action", "seq": seq, "action": [0.01, 0.0, -0.01, 0.0]}),
                                *FLOOD_MESSAGES]:
                        ws.send(msg)
                        sent += 1
                    if seq % 100 == 0:  # a foreign knock: no token
                        try:
                            with connect(f"ws://127.0.0.1:{server.port}/ws") as bad:
                                bad.recv(timeout=5)
                                bad.recv(timeout=5)
                        except ConnectionClosed:
                            refused += 1
        except (ConnectionClosed, OSError):  # dropped: come back
            drops += 1
            time.sleep(0.2)
    out.update(sent=sent, received=received, refused_without_token=refused, dropped=drops)


def flood_never_reading(server: Target, seconds: float, out: dict) -> None:
    """Send bad messages as fast as the socket takes them and never read; reconnect when
    the server drops the connection (it must: its replies pile up unread)."""
    import socket

    from websockets.exceptions import ConnectionClosed, InvalidStatus
    from websockets.sync.client import connect

    sent = drops = 0
    stop = time.perf_counter() + seconds
    bad = json.dumps({"type": "action", "seq": 1, "action": [0, 0, 0]})
    while time.perf_counter() < stop:
        sock = socket.socket()
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)
        try:
            sock.connect(("127.0.0.1", server.port))
            with connect(server.ws_url, sock=sock, max_queue=1) as ws:
                while time.perf_counter() < stop:
                    ws.send(bad)
                    sent += 1
        except (ConnectionClosed, InvalidStatus, OSError):
            drops += 1
            time.sleep(0.2)
    out.update(sent=sent, dropped=drops)


def per_minute(frame_times: list[float], t0: float) -> list[float]:
    """Frames per second in each whole minute after ``t0``."""
    x = np.asarray(frame_times) - t0
    return [float(np.sum((x >= m * 60) & (x < (m + 1) * 60)) / 60) for m in range(int(x.max() // 60) if len(x) else 0)]


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--checkpoint", default="checkpoints/pusht-64")
    p.add_argument("--clients", type=int, default=4, help="well-behaved clients (default: %(default)s)")
    p.add_argument("--hz", type=float, default=10.0)
    p.add_argument("--seconds", type=float, default=300.0, help="measured seconds (default: %(default)s)")
    p.add_argument("--warmup", type=float, default=5.0)
    p.add_argument("--out", default="bench/results/play_soak")
    args = p.parse_args()
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    server = Server(args.checkpoint, args.hz, args.clients + 2, SERVER_LOG)
    memory: list[tuple[float, float]] = []
    try:
        t0 = time.perf_counter()
        outs = [{} for _ in range(args.clients)]
        flood_out: dict = {}
        silent_out: dict = {}
        threads = [threading.Thread(target=client, args=(server.ws_url, args.hz, args.warmup, args.seconds, i, o))
                   for i, o in enumerate(outs)]
        # The flooders run in processes of their own at the lowest priority: an attacker's own
        # CPU is not the server's (it would sit on another machine), and in threads here they
        # would starve the measuring clients of this process's GIL.
        ctx = multiprocessing.get_context("spawn")
        results = ctx.Queue()
        floods = [ctx.Process(target=run_niced, args=(f, server.port, server.ws_url, args.warmup + args.seconds,
                                                      results)) for f in (flood, flood_never_reading)]
        for t in [*threads, *floods]:
            t.start()
        while any(t.is_alive() for t in [*threads, *floods]):
            rss = rss_mib(server.proc.pid)
            if rss is not None:
                memory.append((round(time.perf_counter() - t0, 1), round(rss, 1)))
            time.sleep(1.0)
        for t in threads:
            t.join()
        for _ in floods:
            name, got = results.get(timeout=60)
            (flood_out if name == "flood" else silent_out).update(got)
        for t in floods:
            t.join()
        alive = server.proc.poll() is None
    finally:
        server.close()
    if any("frame_times" not in o for o in outs):
        raise RuntimeError(f"a well-behaved client failed; see the traceback above and {SERVER_LOG}")
    fps = [len(o["frame_times"]) / args.seconds for o in outs]
    lat = np.concatenate([o["latencies"] for o in outs])
    start = t0 + args.warmup
    mem = np.array([m for _, m in memory])
    result = {
        "command": command_line(__file__),
        "meta": {"cpus": os.cpu_count(), "checkpoint": args.checkpoint, "clients": args.clients, "hz": args.hz,
                 "seconds": args.seconds},
        "fps_per_client": fps, "fps_min": min(fps),
        "fps_per_minute": [per_minute(o["frame_times"], start) for o in outs],
        "latency_ms": summary(lat),
        "flood": flood_out,
        "never_reading": silent_out,
        "server_alive_at_end": alive,
        "memory_mib": {"start": float(mem[0]), "max": float(mem.max()), "end": float(mem[-1])} if len(mem) else {},
        "memory_trace": memory,
    }
    (out / "results.json").write_text(json.dumps(result, indent=1))
    lat_s = result["latency_ms"]
    md = "\n".join([
        "# iwsim play: soak", "", f"`{result['command']}`", "",
        f"Machine: {os.cpu_count()} CPU cores; model {args.checkpoint}; {args.clients} well-behaved clients and two "
        f"flood clients (own processes, lowest priority); the server steps at {args.hz:g} Hz; measured for "
        f"{args.seconds:g} s (after {args.warmup:g} s warm-up).", "",
        "| frames/s per client (min) | key-to-frame p50 | p95 | max | server RSS start / max / end | "
        "flood messages sent | flood frames/events received | flood drops | knocks without token refused |",
        "|---|---|---|---|---|---|---|---|---|",
        f"| {min(fps):.1f} | {lat_s.get('p50', float('nan')):.0f} ms | {lat_s.get('p95', float('nan')):.0f} ms | "
        f"{lat_s.get('max', float('nan')):.0f} ms | "
        + (" / ".join(f"{result['memory_mib'][k]:.0f}" for k in ("start", "max", "end")) + " MiB"
           if result["memory_mib"] else "n/a")
        + f" | {flood_out.get('sent', 0)} | {flood_out.get('received', 0)} | {flood_out.get('dropped', 0)} | "
          f"{flood_out.get('refused_without_token', 0)} |", "",
        f"The token holder that floods and never reads sent {silent_out.get('sent', 0)} messages and was dropped "
        f"{silent_out.get('dropped', 0)} times (each connection's unsent replies and message rate are bounded).",
        "",
        f"Server still running at the end: {alive}.", ""])
    (out / "results.md").write_text(md)
    print(md)


if __name__ == "__main__":
    raise SystemExit(reporting_errors("bench_play_soak.py", main))
