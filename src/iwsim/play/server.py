"""The ``iwsim play`` server: FastAPI serves the page and one WebSocket per session.

Two threads. The engine's thread (:class:`Runner`, the main thread under ``iwsim play``)
owns the :class:`~iwsim.play.engine.Engine`: it runs the server's requests in order and
steps all sessions at the control rate. The server's thread runs uvicorn's event loop:
each connection has a receive loop (messages -> engine) and a sender, which keeps only the
newest frame, so a slow client misses frames instead of stalling everyone else's. So the
event loop keeps receiving and sending while a step computes, and a message that arrives
during step k is applied before step k + 1.

Why the engine gets the main thread: PyTorch's CPU kernels run this model markedly slower
when called from a second thread (bench/bench_play.py measures a step's latency).

Access (the token, allowed origins and hosts) is decided in :mod:`iwsim.play.access`.
Either thread failing stops the other and the process: a web server that cannot serve
must not leave a simulator running that nobody can reach.
"""

from __future__ import annotations

import asyncio
import contextlib
import html
import logging
import queue
import signal
import socket
import threading
import time
from collections import deque
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass
from importlib import resources
from typing import Any

from fastapi import FastAPI, Request, WebSocket, WebSocketDisconnect
from fastapi.responses import HTMLResponse, PlainTextResponse, Response

from iwsim.play import protocol as proto
from iwsim.play.access import Access, PlayError, bind, check_bind
from iwsim.play.engine import Engine, Session

log = logging.getLogger(__name__)

WS_MAX_BYTES = 1 << 20  # larger messages close the connection (1009); smaller bad ones get an error
STATIC = ("index.html", "play.js")
TOKEN_META = '<meta name="iwsim-token" content="{}">'  # where the page finds its token


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
        assert self.loop is not None  # the app sets it before it serves
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
        assert self.loop is not None  # a job comes from call
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


MAX_UNSENT_EVENTS = 256  # a client that leaves this many messages unread is dropped
OVERFLOW_REASON = "dropped: the client sent faster than it read the replies"
# The page sends at most two actions per control step (20/s at 10 Hz) and a few commands;
# a connection that sends more than this many messages per step (100 a second at 10 Hz),
# sustained over a burst of twice as many, is dropped, so one client cannot take the
# server's time from the others.
MAX_MESSAGES_PER_STEP = 10
RATE_REASON = "dropped: more than {} messages a second"
# What a message costs the budget, in messages. A restart encodes a new first frame (and
# resets the MuJoCo twin), side by side builds or closes a MuJoCo renderer: tens of
# milliseconds of the engine's thread each, against well under one for an action. Charged
# by that cost, they are limited to 2 (restarts) and 1 (side by side) a second beyond a
# short burst, so a client toggling them cannot take the other sessions' frames; one over
# the budget is refused with an error and the session goes on.
MESSAGE_COST = {proto.Reset: 5 * MAX_MESSAGES_PER_STEP, proto.SideBySide: 10 * MAX_MESSAGES_PER_STEP}
COST_REASON = "too many restarts a second: this one is ignored; wait a moment and try again."


class MessageBudget:
    """A token bucket: ``take()`` is False once a connection's messages outrun
    ``rate`` a second beyond a burst of ``2 * rate``."""

    def __init__(self, rate: float, clock: Callable[[], float] = time.monotonic) -> None:
        self.rate, self.burst, self.clock = rate, 2 * rate, clock
        self.tokens, self.last = self.burst, clock()

    def take(self, cost: float = 1) -> bool:
        """Whether a message of ``cost`` (in messages) fits; if so it is charged."""
        now = self.clock()
        self.tokens = min(self.burst, self.tokens + (now - self.last) * self.rate)
        self.last = now
        if self.tokens < cost:
            return False
        self.tokens -= cost
        return True


class Outbox:
    """What one connection still has to send: events in order (at most
    MAX_UNSENT_EVENTS; beyond that ``overflow`` is set and the connection is closed), then
    the newest frame (older unsent frames are skipped), so its memory is bounded."""

    def __init__(self, ws: WebSocket) -> None:
        self.ws = ws
        self.events: deque[str] = deque()
        self.frame: bytes | None = None
        self.dropped = 0
        self.overflow = False
        self._wake = asyncio.Event()

    def event(self, text: str) -> None:
        if len(self.events) >= MAX_UNSENT_EVENTS:
            self.overflow = True
            return
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


def create_app(runner: Runner, access: Access) -> FastAPI:
    """The app: ``/`` (the page), ``/play.js`` and the ``/ws`` session socket, open to whom
    ``access`` allows. Someone must call ``runner.run()`` (see :func:`serve` and
    :func:`running`)."""
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

    @app.middleware("http")
    async def known_hosts_only(request: Request, call_next: Callable) -> Response:
        # A foreign name resolving to this machine (DNS rebinding) gets nothing, not even the page.
        if not access.known_host(request.headers.get("host")):
            return PlainTextResponse("unknown host", status_code=421)
        return await call_next(request)

    @app.get("/")
    async def index(request: Request) -> HTMLResponse:
        token = access.page_token(request.headers.get("host"), request.client.host if request.client else None)
        page = pages["index.html"]
        if token is not None:
            page = page.replace("<head>", "<head>\n" + TOKEN_META.format(html.escape(token)), 1)
        # no-store: the page may carry the token, which belongs to this run only
        return HTMLResponse(page, headers={"Cache-Control": "no-store", "Referrer-Policy": "no-referrer"})

    @app.get("/play.js")
    async def script() -> Response:
        return Response(pages["play.js"], media_type="text/javascript")

    @app.websocket("/ws")
    async def session_socket(ws: WebSocket) -> None:
        host = ws.headers.get("host")
        if not access.known_host(host):  # DNS rebinding: as for HTTP, a foreign name gets nothing
            log.warning("refused a session for host %r", host)
            await ws.close(code=1008)
            return
        if not access.origin_allowed(ws.headers.get("origin"), host):
            log.warning("refused a session from origin %r (host %r)", ws.headers.get("origin"), host)
            await ws.close(code=1008)  # before accepting: the handshake fails with HTTP 403
            return
        await ws.accept()
        if not access.token_ok(ws.query_params.getlist("token")):
            await _refuse(ws, "error", "wrong, missing or repeated token: open the page this server serves, "
                                       "or add ?token=SECRET once.", 1008)
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
        budget = MessageBudget(MAX_MESSAGES_PER_STEP * engine.cfg.hz)
        try:
            while not sender.done():  # messages -> engine until the client goes
                try:
                    msg = await ws.receive()
                except (WebSocketDisconnect, RuntimeError):
                    break
                if msg["type"] == "websocket.disconnect":
                    break
                if not budget.take():
                    await _drop(ws, sender, s.id, RATE_REASON.format(f"{budget.rate:g}"))
                    break
                text = msg.get("text")
                data = text if text is not None else msg.get("bytes", b"")
                try:
                    parsed = proto.parse(data, engine.model.action_dim)
                except proto.ProtocolError as e:
                    out.event(proto.event("error", message=str(e)))
                else:
                    extra = MESSAGE_COST.get(type(parsed), 1) - 1  # the message itself is charged above
                    if extra and not budget.take(extra):
                        out.event(proto.event("error", message=COST_REASON))
                        continue
                    events, frame = await runner.call(apply, s, parsed)
                    for text in events:
                        out.event(text)
                    if frame is not None:
                        out.put_frame(frame)
                if out.overflow:
                    await _drop(ws, sender, s.id, OVERFLOW_REASON)
                    break
        finally:
            sender.cancel()
            with contextlib.suppress(asyncio.CancelledError, Exception):
                await sender
            outboxes.pop(s.id, None)
            await runner.call(engine.close, s)
            log.info("session %d closed (%d frames skipped while it was slow to read)", s.id, out.dropped)

    return app


async def _drop(ws: WebSocket, sender: asyncio.Task, sid: int, reason: str) -> None:
    """Close a session's connection with 1008 and ``reason``, not waiting long: its socket may be full."""
    log.warning("session %d: %s", sid, reason)
    sender.cancel()
    with contextlib.suppress(Exception):
        await asyncio.wait_for(ws.close(code=1008, reason=reason), timeout=2.0)


async def _refuse(ws: WebSocket, kind: str, message: str, code: int) -> None:
    with contextlib.suppress(Exception):
        await ws.send_text(proto.event(kind, message=message))
        await ws.close(code=code, reason=kind)


def _uvicorn(runner: Runner, access: Access):
    import uvicorn

    # access_log off: request lines would carry ?token= into the log
    config = uvicorn.Config(create_app(runner, access), ws_max_size=WS_MAX_BYTES, log_level="warning",
                            access_log=False, timeout_graceful_shutdown=5)
    return uvicorn.Server(config)


@dataclass(frozen=True)
class Served:
    """Where a :func:`running` server is and the token its sessions need."""

    address: str  # host:port
    token: str

    @property
    def page(self) -> str:
        return f"http://{self.address}/"

    @property
    def ws(self) -> str:
        """The session socket's URL, token included."""
        return f"ws://{self.address}/ws?token={self.token}"


@contextlib.contextmanager
def running(engine: Engine, host: str = "127.0.0.1", port: int = 0, token: str | None = None,
            origins: Iterable[str] = ()) -> Iterator[Served]:
    """The server in background threads (for tests and scripts); ``token`` None means a
    random one, as ``iwsim play`` does."""
    check_bind(host, token)
    sock = bind(host, port)
    port = sock.getsockname()[1]
    access = Access.create(token, host, port, origins)
    runner = Runner(engine)
    server = _uvicorn(runner, access)
    web = threading.Thread(target=server.run, kwargs={"sockets": [sock]}, daemon=True)
    steps = threading.Thread(target=_run_engine, args=(runner,), daemon=True)
    web.start()
    steps.start()
    deadline = time.monotonic() + 30
    while not server.started:
        if not web.is_alive() or time.monotonic() > deadline:
            runner.stop()
            sock.close()
            raise RuntimeError(f"the play server did not start on {host}:{port}.")
        time.sleep(0.02)
    try:
        yield Served(f"{host}:{port}", access.token)
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


def serve(engine: Engine, sock: socket.socket, access: Access) -> None:
    """Run the server on the bound ``sock`` until Ctrl-C or SIGTERM: the engine on this (the
    main) thread, uvicorn on another. Stopping closes the web side first (its sessions close
    through the engine), then the engine. If either side fails, the other stops too and a
    PlayError says so."""
    runner = Runner(engine)
    server = _uvicorn(runner, access)
    failure: list[BaseException] = []

    def web_side() -> None:
        try:
            server.run(sockets=[sock])
        except BaseException as e:  # noqa: BLE001 - incl. the SystemExit uvicorn raises on a failed start
            failure.append(e)
        finally:
            runner.stop()  # whatever ended the web side ends the engine

    web = threading.Thread(target=web_side, name="iwsim-server", daemon=True)
    web.start()

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
        stop()  # an engine that failed takes the web side down with it
        engine.shutdown()
        web.join(10)
        sock.close()
    if failure or not server.started:
        why = f": {_one_line(failure[0])}" if failure and not isinstance(failure[0], SystemExit) else \
            " (see the message above)"
        raise PlayError(f"the web server {'stopped' if server.started else 'did not start'}{why}; "
                        "the simulator stopped with it.")


def _one_line(e: BaseException) -> str:
    return " ".join(f"{type(e).__name__}: {e}".split())
