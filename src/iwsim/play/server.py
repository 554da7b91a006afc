"""The ``iwsim play`` server: FastAPI serves the page and one WebSocket per session.

One asyncio task steps the :class:`~iwsim.play.engine.Engine` at the control rate; each
connection has a receive loop (messages -> engine) and a sender. A sender keeps only the
newest frame, so a slow client misses frames instead of stalling everyone else's.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import secrets
from collections import deque
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


def create_app(engine: Engine, token: str | None = None) -> FastAPI:
    """The app: ``/`` (the page), ``/play.js`` and the ``/ws`` session socket."""
    outboxes: dict[int, Outbox] = {}

    async def stepper() -> None:
        loop = asyncio.get_running_loop()
        period = 1.0 / engine.cfg.hz
        next_t = loop.time()
        while True:
            delay = next_t - loop.time()
            if delay > 0:
                await asyncio.sleep(delay)
            for s in engine.tick():
                if s.id in outboxes:
                    outboxes[s.id].put_frame(engine.frame_message(s))
            for s, text in engine.finished_saves():
                if s.id in outboxes:
                    outboxes[s.id].event(text)
            # a fixed rate: the next step is due one period later; after an overrun, skip
            # the missed steps rather than bursting to catch up
            next_t = max(next_t + period, loop.time())

    @contextlib.asynccontextmanager
    async def lifespan(app: FastAPI):
        task = asyncio.create_task(stepper())
        try:
            yield
        finally:
            task.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await task
            engine.shutdown()

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
        s = engine.open()
        if s is None:
            await _refuse(ws, "busy", f"the simulator is busy: all {engine.cfg.max_sessions} sessions are in "
                                      "use; try again later.", 1013)
            return
        log.info("session %d opened (%d open)", s.id, len(engine.sessions))
        out = Outbox(ws)
        outboxes[s.id] = out
        out.event(engine.hello(s))
        out.put_frame(engine.frame_message(s))
        sender = asyncio.create_task(out.run())
        try:
            await _receive(ws, engine, s, out, sender)
        finally:
            sender.cancel()
            with contextlib.suppress(asyncio.CancelledError, Exception):
                await sender
            outboxes.pop(s.id, None)
            engine.close(s)
            log.info("session %d closed (%d open, %d frames dropped)", s.id, len(engine.sessions), out.dropped)

    return app


async def _refuse(ws: WebSocket, kind: str, message: str, code: int) -> None:
    with contextlib.suppress(Exception):
        await ws.send_text(proto.event(kind, message=message))
        await ws.close(code=code, reason=kind)


async def _receive(ws: WebSocket, engine: Engine, s: Session, out: Outbox, sender: asyncio.Task) -> None:
    """Messages -> engine until the client goes (or its sender fails)."""
    while not sender.done():
        try:
            msg: dict[str, Any] = await ws.receive()
        except (WebSocketDisconnect, RuntimeError):
            return
        if msg["type"] == "websocket.disconnect":
            return
        data = msg.get("text") if msg.get("text") is not None else msg.get("bytes", b"")
        try:
            parsed = proto.parse(data, engine.model.action_dim)
        except proto.ProtocolError as e:
            out.event(proto.event("error", message=str(e)))
            continue
        for text in engine.handle(s, parsed):
            out.event(text)
        if isinstance(parsed, (proto.Reset, proto.SideBySide)):
            out.put_frame(engine.frame_message(s))  # the new start, without waiting a step


def serve(engine: Engine, host: str = "127.0.0.1", port: int = 8000, token: str | None = None) -> None:
    """Run the server until interrupted."""
    import uvicorn

    check_bind(host, token)
    app = create_app(engine, token)
    uvicorn.run(app, host=host, port=port, ws_max_size=WS_MAX_BYTES, log_level="warning")
