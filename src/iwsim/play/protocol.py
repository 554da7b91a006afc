"""The messages between the play page and the server (one WebSocket per session).

Client -> server: JSON text, at most ``MAX_MESSAGE_BYTES``::

    {"type": "action", "seq": 17, "action": [a0, ..., aA-1]}    the task's command (T-push:
                                                                pusher targets [lx, ly, rx, ry]
                                                                in m), from the next control step
    {"type": "reset", "source": "mujoco" | "dataset" | "store", "seed": 3}  seed optional
    {"type": "record"} | {"type": "save"} | {"type": "discard"}
    {"type": "side_by_side", "on": true}                         restarts the episode

Server -> client: JSON text for events (``hello``, ``status``, ``saved``, ``error``,
``busy``) and one binary message per control step::

    uint32 little-endian n | n bytes of JSON header | views, each (H, W, 3) uint8 RGB

The header holds the step, ``ack`` (the ``seq`` of the last action applied), the action,
pixel IoU, recording state and ``views`` (names of the frames that follow, the world
model first, then MuJoCo in side-by-side mode).
"""

from __future__ import annotations

import json
import math
import struct
from dataclasses import dataclass
from typing import Any

import numpy as np

from iwsim.core.errors import InputError

MAX_MESSAGE_BYTES = 4096
RESET_SOURCES = ("mujoco", "dataset", "store")  # the task's own starts (T-push: mujoco; others: dataset), or a store's
MAX_SEED = 2**31 - 1


class ProtocolError(InputError):
    """A client message that is malformed, too large or unknown; the session goes on."""


@dataclass(frozen=True)
class Action:
    seq: int
    action: tuple[float, ...]


@dataclass(frozen=True)
class Reset:
    source: str
    seed: int | None


@dataclass(frozen=True)
class Command:
    """record, save or discard."""

    name: str


@dataclass(frozen=True)
class SideBySide:
    on: bool


Message = Action | Reset | Command | SideBySide
COMMANDS = ("record", "save", "discard")
TYPES = ("action", "reset", "side_by_side", *COMMANDS)


def _int(msg: dict, key: str, low: int, high: int, default: Any = ...) -> Any:
    if key not in msg:
        if default is ...:
            raise ProtocolError(f"'{msg['type']}' needs an integer '{key}'.")
        return default
    v = msg[key]
    if isinstance(v, bool) or not isinstance(v, int) or not low <= v <= high:
        raise ProtocolError(f"'{key}' must be an integer in [{low}, {high}], got {v!r}.")
    return v


def parse(data: str | bytes, action_dim: int) -> Message:
    """One client message -> a :data:`Message`, or :class:`ProtocolError` saying what is wrong."""
    # the limit counts bytes: a character may take up to 4 in UTF-8
    size = len(data.encode("utf-8", "surrogatepass")) if isinstance(data, str) else len(data)
    if size > MAX_MESSAGE_BYTES:
        raise ProtocolError(f"message of {size} bytes is over the limit of {MAX_MESSAGE_BYTES}.")
    if isinstance(data, bytes):
        raise ProtocolError("binary messages are not accepted; send JSON text.")
    try:
        msg = json.loads(data)
    except (json.JSONDecodeError, RecursionError):
        raise ProtocolError("message is not valid JSON.") from None
    if not isinstance(msg, dict) or not isinstance(msg.get("type"), str):
        raise ProtocolError('message must be a JSON object with a string "type".')
    kind = msg["type"]
    if kind not in TYPES:
        raise ProtocolError(f"unknown message type {kind[:40]!r}; expected one of {', '.join(TYPES)}.")
    if kind == "action":
        seq = _int(msg, "seq", 0, 2**53)
        a = msg.get("action")
        if (not isinstance(a, list) or len(a) != action_dim
                or not all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in a)):
            raise ProtocolError(f"'action' must be a list of {action_dim} numbers, got {str(a)[:60]}.")
        try:
            values = tuple(float(v) for v in a)  # an integer beyond float range overflows here
        except OverflowError:
            values = (math.inf,)
        if not all(math.isfinite(v) for v in values):
            raise ProtocolError(f"'action' must be finite numbers, got {str(a)[:60]}.")
        return Action(seq, values)
    if kind == "reset":
        source = msg.get("source", "mujoco")
        if source not in RESET_SOURCES:
            raise ProtocolError(f"reset 'source' must be one of {', '.join(RESET_SOURCES)}, got {str(source)[:40]!r}.")
        return Reset(source, _int(msg, "seed", 0, MAX_SEED, None))
    if kind == "side_by_side":
        on = msg.get("on")
        if not isinstance(on, bool):
            raise ProtocolError(f"'on' must be true or false, got {str(on)[:40]}.")
        return SideBySide(on)
    return Command(kind)


def event(kind: str, **fields: Any) -> str:
    """A server -> client JSON text message."""
    return json.dumps({"type": kind, **fields})


def pack_frame(header: dict[str, Any], views: list[np.ndarray]) -> bytes:
    """A binary frame message: the JSON header, then each view's RGB bytes."""
    head = json.dumps(header).encode()
    return b"".join([struct.pack("<I", len(head)), head, *(np.ascontiguousarray(v, np.uint8).tobytes() for v in views)])


def unpack_frame(data: bytes) -> tuple[dict[str, Any], list[np.ndarray]]:
    """Inverse of :func:`pack_frame` (for Python clients: tests and the bench)."""
    (n,) = struct.unpack_from("<I", data)
    header = json.loads(data[4:4 + n])
    size = header["size"]
    pixels = np.frombuffer(data, np.uint8, offset=4 + n).reshape(len(header["views"]), size, size, 3)
    return header, list(pixels)
