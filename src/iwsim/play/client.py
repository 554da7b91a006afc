"""Driving ``iwsim play`` from outside, as the benchmarks do (``bench/bench_play.py``,
``bench/bench_play_soak.py``): the real server in a subprocess on a free port, a WebSocket
client that behaves like the page, and the latency summary their records hold."""

from __future__ import annotations

import json
import os
import random
import secrets
import socket
import subprocess
import sys
import threading
import time
import urllib.request
from pathlib import Path
from typing import Any

import numpy as np

from iwsim.play.protocol import unpack_frame


def free_port() -> int:
    """A TCP port of 127.0.0.1 that nothing listens on now."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


class Server:
    """``iwsim play`` in a subprocess, for one configuration; sessions need ``self.token``
    (handed to it in the environment, as a user would, not on the command line). Its output
    goes to ``log``; it is ready once its page loads."""

    def __init__(self, checkpoint: str, hz: float, sessions: int, log: Path) -> None:
        self.port = free_port()
        self.token = secrets.token_urlsafe(16)
        iwsim = str(Path(sys.executable).with_name("iwsim"))
        log.parent.mkdir(parents=True, exist_ok=True)
        self.log = open(log, "w")
        self.proc = subprocess.Popen(
            [iwsim, "play", "--checkpoint", checkpoint, "--port", str(self.port), "--hz", str(hz),
             "--max-sessions", str(sessions)], env={**os.environ, "MUJOCO_GL": "egl", "IWSIM_PLAY_TOKEN": self.token},
            stdout=self.log, stderr=subprocess.STDOUT, text=True)
        deadline = time.monotonic() + 120
        while True:
            if self.proc.poll() is not None:
                raise RuntimeError(f"iwsim play exited: see {log}")
            try:  # the port listens before the model is loaded: wait for the page itself
                urllib.request.urlopen(f"http://127.0.0.1:{self.port}/", timeout=1).close()
                return
            except OSError:
                if time.monotonic() > deadline:
                    raise RuntimeError("iwsim play did not start within 120 s") from None
                time.sleep(0.2)

    @property
    def ws_url(self) -> str:
        return f"ws://127.0.0.1:{self.port}/ws?token={self.token}"

    def close(self) -> None:
        self.proc.terminate()
        self.proc.wait(30)
        self.log.close()


def client(url: str, hz: float, warmup: float, seconds: float, seed: int, out: dict[str, Any]) -> None:
    """One page-like client of the session socket ``url``: a key press every 0.4-0.6 s, held
    for 0.2 s with the target sent twice per control step (at most 60 a second), as the page
    does. After ``warmup`` seconds, for ``seconds``, it fills ``out`` with each frame's
    arrival time (``frame_times``), each press's latency in ms from sending its first action
    to the first frame that acknowledges it (``latencies``) and the server's step time of
    each frame (``step_ms``)."""
    from websockets.sync.client import connect

    rng = random.Random(seed)
    sent: dict[int, float] = {}  # seq of a press's first action -> send time
    lock = threading.Lock()
    latencies: list[float] = []
    frame_times: list[float] = []
    step_ms: list[float] = []
    with connect(url, max_size=None) as ws:
        hello = json.loads(ws.recv())
        if hello["type"] != "hello":
            raise RuntimeError(f"expected hello, got {hello}")
        frame = ws.recv()
        if not isinstance(frame, bytes):
            raise RuntimeError(f"expected the first frame, got {frame}")
        header, _ = unpack_frame(frame)
        target = list(header["action"])
        seq = 0
        stop = threading.Event()

        rate = min(60.0, 2 * hz)  # the page sends a held key's motion twice per control step

        def presses() -> None:
            nonlocal seq
            direction = 1.0
            while not stop.is_set():
                time.sleep(rng.uniform(0.4, 0.6))
                held_until = time.perf_counter() + 0.2
                first = True
                while time.perf_counter() < held_until and not stop.is_set():
                    target[0] = float(np.clip(target[0] + direction * 0.2 / rate, -0.2, 0.2))
                    if abs(target[0]) >= 0.2:
                        direction = -direction
                    seq += 1
                    if first:
                        with lock:
                            sent[seq] = time.perf_counter()
                        first = False
                    ws.send(json.dumps({"type": "action", "seq": seq, "action": target}))
                    time.sleep(1 / rate)

        sender = threading.Thread(target=presses, daemon=True)
        t0 = time.perf_counter()
        sender.start()
        while time.perf_counter() < t0 + warmup + seconds:
            data = ws.recv(timeout=5)
            if isinstance(data, str):
                continue
            now = time.perf_counter()
            header, _ = unpack_frame(data)
            with lock:
                seen = [s for s in sent if s <= header["ack"]]
                for s in seen:
                    if now - t0 > warmup:
                        latencies.append(1000 * (now - sent[s]))
                    del sent[s]
            if now - t0 > warmup:
                frame_times.append(now)
                step_ms.append(header["step_ms"])
        stop.set()
        sender.join(2)
    out.update(latencies=latencies, frame_times=frame_times, step_ms=step_ms)


def summary(x: np.ndarray) -> dict[str, float]:
    """Count, median, 95th percentile, mean and max of latencies ``x`` (ms); ``{"n": 0}`` for none."""
    if not len(x):
        return {"n": 0}
    return {"n": int(len(x)), "p50": float(np.percentile(x, 50)), "p95": float(np.percentile(x, 95)),
            "mean": float(np.mean(x)), "max": float(np.max(x))}
