"""The ``iwsim play`` server: FastAPI serves the page and one WebSocket per session.

Two threads. The engine's thread (:class:`Runner`, the main thread under ``iwsim play``)
owns the :class:`~iwsim.play.engine.Engine`: it runs the server's requests in order and
steps all sessions at the control rate. The server's thread runs uvicorn's event loop:
each connection has a receive loop (messages -> engine) and a sender, which keeps only the
newest frame, so a slow client misses frames instead of stalling everyone else's. So the
event loop keeps receiving and sending while a step computes, and a message that arrives
during step k is applied before step k + 1.

Why the engine gets the main thread: PyTorch's CPU kernels ran this model about half as
fast when called from a second thread (measured: 63 vs 30 ms per step at batch 1).
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import queue
import secrets
import signal
import threading
import time
from collections import deque
from collections.abc import Callable, Iterator
from importlib import resources
from typing import Any

from fastapi import FastAPI, WebSocket, WebSocketDisconnect
from fastapi.responses import HTMLResponse, Response

from iwsim.play import protocol as proto
from iwsim.play.engine import Engine, Session

log = logging.getLogger(__name__)

LOOPBACK = ("127.0.0.1", "localhost", "::1")
WS_MAX_BYTES = 1 << 20  # larger messages close the connection (1009); smaller bad ones get an error
STATIC = ("index.html", "play.js")


def check_bind(host: str, token: str | None) -> None:
    """Refuse to serve beyond this machine without a token."""
    if host not in LOOPBACK and not token:
        raise ValueError(f"refusing to bind {host} without --token: anyone who can reach it could drive "
                         "the simulator and write to the store; pass --token SECRET (clients add ?token=SECRET).")


class Runner:
    """The engine's thread: requests from the event loop, in order, and a step of every
    session each control period (after the requests that arrived before it)."""

    def __init__(self, engine: Engine) -> None:
        self.engine = engine
        self.loop: asyncio.AbstractEventLoop | None = None  # set by the app when it starts
        self.on_step: Callable[[list[tuple[int, bytes]], list[tuple[Session, str]]], None] | None = None
        self._jobs: queue.SimpleQueue = queue.SimpleQueue()
        self._stop = threading.Event()

    def call(self, fn: Callable[..., Any], *args: Any) -> asyncio.Future:
        """From the event loop: ``fn(*args)`` on the engine's thread, as a future."""
        future = self.loop.create_future()
        self._jobs.put((fn, args, future))
        return future

    def stop(self) -> None:
        self._stop.set()
        self._jobs.put(None)

    def run(self) -> None:
        """Serve requests and step until :meth:`stop`; blocks the calling thread. Requests
        still queued then fail, so no coroutine waits forever."""
        try:
            self._serve()
        finally:
            while self._stop.is_set():  # (not when interrupted: the caller may run again)
                try:
                    job = self._jobs.get_nowait()
                except queue.Empty:
                    break
                if job is not None and self.loop is not None:
                    self.loop.call_soon_threadsafe(_settle, job[2], None, RuntimeError("the engine has stopped"))

    def _serve(self) -> None:
        period = 1.0 / self.engine.cfg.hz
        next_t = time.monotonic()
        while not self._stop.is_set():
            try:
                job = self._jobs.get(timeout=max(0.0, next_t - time.monotonic()))
            except queue.Empty:
                job = None
            if job is not None:
                self._do(*job)
                if time.monotonic() < next_t:
                    continue
            while True:  # requests that came in before this step go first
                try:
                    job = self._jobs.get_nowait()
                except queue.Empty:
                    break
                if job is not None:
                    self._do(*job)
            if self._stop.is_set():
                break
            stepped = self.engine.tick()
            frames = [(s.id, self.engine.frame_message(s)) for s in stepped]
            saves = self.engine.finished_saves()
            if self.loop is not None and self.on_step is not None and (frames or saves):
                self.loop.call_soon_threadsafe(self.on_step, frames, saves)
            # a fixed rate: the next step is due one period later. A step that ran late is
            # caught up at once; when more than a whole step behind, skip the missed steps
            # rather than burst.
            next_t += period
            if time.monotonic() - next_t > period:
                next_t = time.monotonic()

    def _do(self, fn: Callable[..., Any], args: tuple, future: asyncio.Future) -> None:
        try:
            result = fn(*args)
        except Exception as e:  # noqa: BLE001 - handed to the awaiting coroutine
            self.loop.call_soon_threadsafe(_settle, future, None, e)
        else:
            self.loop.call_soon_threadsafe(_settle, future, result, None)


def _settle(future: asyncio.Future, result: Any, error: BaseException | None) -> None:
    if future.cancelled():
        return
    if error is not None:
        future.set_exception(error)
    else:
        future.set_result(result)


class Outbox:
    """What one connection still has to send: events in order, then the newest frame."""

    def __init__(self, ws: WebSocket) -> None:
        self.ws = ws
        self.events: deque[str] = deque()
        self.frame: bytes | None = None
        self.dropped = 0
        self._wake = asyncio.Event()

    def event(self, text: str) -> None:
        self.events.append(text)
        self._wake.set()

    def put_frame(self, data: bytes) -> None:
        if self.frame is not None:
            self.dropped += 1
        self.frame = data
        self._wake.set()

    async def run(self) -> None:
        while True:
            await self._wake.wait()
            self._wake.clear()
            while self.events:
                await self.ws.send_text(self.events.popleft())
            if self.frame is not None:
                frame, self.frame = self.frame, None
                await self.ws.send_bytes(frame)


def create_app(runner: Runner, token: str | None = None) -> FastAPI:
    """The app: ``/`` (the page), ``/play.js`` and the ``/ws`` session socket. Someone must
    call ``runner.run()`` (see :func:`serve` and :func:`running`)."""
    engine = runner.engine
    outboxes: dict[int, Outbox] = {}

    def deliver(frames: list[tuple[int, bytes]], saves: list[tuple[Session, str]]) -> None:
        for sid, frame in frames:
            if sid in outboxes:
                outboxes[sid].put_frame(frame)
        for s, text in saves:
            if s.id in outboxes:
                outboxes[s.id].event(text)

    def apply(s: Session, msg: proto.Message) -> tuple[list[str], bytes | None]:
        events = engine.handle(s, msg)
        # a new start goes out at once, without waiting for the next step
        restart = isinstance(msg, (proto.Reset, proto.SideBySide)) and not s.closed
        return events, engine.frame_message(s) if restart else None

    @contextlib.asynccontextmanager
    async def lifespan(app: FastAPI):
        runner.loop, runner.on_step = asyncio.get_running_loop(), deliver
        yield

    app = FastAPI(title="iwsim play", lifespan=lifespan)
    pages = {name: resources.files("iwsim.play").joinpath("static", name).read_text() for name in STATIC}

    @app.get("/")
    async def index() -> HTMLResponse:
        return HTMLResponse(pages["index.html"])

    @app.get("/play.js")
    async def script() -> Response:
        return Response(pages["play.js"], media_type="text/javascript")

    @app.websocket("/ws")
    async def session_socket(ws: WebSocket) -> None:
        await ws.accept()
        given = ws.query_params.get("token") or ""
        if token and not secrets.compare_digest(given.encode(), token.encode()):
            await _refuse(ws, "error", "wrong or missing token: open the page as /?token=SECRET.", 1008)
            return
        s = await runner.call(engine.open)
        if s is None:
            await _refuse(ws, "busy", f"the simulator is busy: all {engine.cfg.max_sessions} sessions are in "
                                      "use; try again later.", 1013)
            return
        log.info("session %d opened", s.id)
        out = Outbox(ws)
        outboxes[s.id] = out
        out.event(engine.hello(s))
        out.put_frame(await runner.call(engine.frame_message, s))
        sender = asyncio.create_task(out.run())
        try:
            while not sender.done():  # messages -> engine until the client goes
                try:
                    msg = await ws.receive()
                except (WebSocketDisconnect, RuntimeError):
                    break
                if msg["type"] == "websocket.disconnect":
                    break
                data = msg.get("text") if msg.get("text") is not None else msg.get("bytes", b"")
                try:
                    parsed = proto.parse(data, engine.model.action_dim)
                except proto.ProtocolError as e:
                    out.event(proto.event("error", message=str(e)))
                    continue
                events, frame = await runner.call(apply, s, parsed)
                for text in events:
                    out.event(text)
                if frame is not None:
                    out.put_frame(frame)
        finally:
            sender.cancel()
            with contextlib.suppress(asyncio.CancelledError, Exception):
                await sender
            outboxes.pop(s.id, None)
            await runner.call(engine.close, s)
            log.info("session %d closed (%d frames skipped while it was slow to read)", s.id, out.dropped)

    return app


async def _refuse(ws: WebSocket, kind: str, message: str, code: int) -> None:
    with contextlib.suppress(Exception):
        await ws.send_text(proto.event(kind, message=message))
        await ws.close(code=code, reason=kind)


def _uvicorn(runner: Runner, host: str, port: int, token: str | None):
    import uvicorn

    config = uvicorn.Config(create_app(runner, token), host=host, port=port, ws_max_size=WS_MAX_BYTES,
                            log_level="warning", timeout_graceful_shutdown=5)
    return uvicorn.Server(config)


@contextlib.contextmanager
def running(engine: Engine, host: str = "127.0.0.1", port: int = 0, token: str | None = None) -> Iterator[str]:
    """The server in background threads (for tests and scripts); yields ``host:port``."""
    check_bind(host, token)
    runner = Runner(engine)
    server = _uvicorn(runner, host, port, token)
    web = threading.Thread(target=server.run, daemon=True)
    steps = threading.Thread(target=_run_engine, args=(runner,), daemon=True)
    web.start()
    steps.start()
    deadline = time.monotonic() + 30
    while not server.started:
        if not web.is_alive() or time.monotonic() > deadline:
            runner.stop()
            raise RuntimeError(f"the play server did not start on {host}:{port}.")
        time.sleep(0.02)
    try:
        yield f"{host}:{server.servers[0].sockets[0].getsockname()[1]}"
    finally:
        server.should_exit = True  # the web side closes its sessions through the engine first
        web.join(30)
        runner.stop()
        steps.join(30)


def _run_engine(runner: Runner) -> None:
    """The engine's thread: run, then shut down there (its MuJoCo renderers belong to it)."""
    try:
        runner.run()
    finally:
        runner.engine.shutdown()


def serve(engine: Engine, host: str = "127.0.0.1", port: int = 8000, token: str | None = None) -> None:
    """Run the server until Ctrl-C or SIGTERM: the engine on this (the main) thread, uvicorn
    on another. Stopping closes the web side first (its sessions close through the engine),
    then the engine."""
    check_bind(host, token)
    runner = Runner(engine)
    server = _uvicorn(runner, host, port, token)
    web = threading.Thread(target=lambda: (server.run(), runner.stop()), name="iwsim-server", daemon=True)
    web.start()  # when uvicorn ends (stopped, or failing to start: port in use, ...), so does the engine

    def stop(*_: Any) -> None:
        server.should_exit = True

    signal.signal(signal.SIGTERM, stop)
    try:
        while True:
            try:
                runner.run()
                break
            except KeyboardInterrupt:  # Ctrl-C: stop the web side, and serve it until it is done
                stop()
    finally:
        engine.shutdown()
        web.join(10)
    if not server.started:
        raise OSError(f"could not serve on {host}:{port} (is the port in use? see uvicorn's message above).")
