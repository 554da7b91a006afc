"""What several commands share: flag parsing, memory checks, JSON input."""

from __future__ import annotations

import argparse

from iwsim.core.errors import InputError


def numbers(flag: str, text: str, kind: type, expected: str | None = None, count: int | None = None) -> tuple:
    """The comma-separated numbers of a flag's value (``count`` of them when given), or
    one line: "FLAG takes EXPECTED, got TEXT." (EXPECTED: comma-separated KINDs)."""
    try:
        values = tuple(kind(v) for v in text.split(",") if v.strip())
    except ValueError:
        values = None
    if values is None or (count is not None and len(values) != count):
        raise InputError(f"{flag} takes {expected or f'comma-separated {kind.__name__}s'}, got {text!r}.")
    return values


def check_frames_memory(what: str, frames: int, copies: int = 1) -> None:
    """Refuse flags that keep more frames in memory than fit: a lower bound, counted as RGB
    frames of the smallest image size (the model's may be larger)."""
    from iwsim.core.resources import require_memory
    from iwsim.envs import SMALLEST_FRAME_BYTES

    require_memory(frames * copies * SMALLEST_FRAME_BYTES, f"{what} (at least {frames * copies} frames in memory)")


def wait_for_lock_flag(p: argparse.ArgumentParser) -> None:
    p.add_argument("--wait-for-lock", action="store_true",
                   help="when another process is writing the store, wait for it instead of stopping")


def read_json(path: str, flag: str) -> object:
    import json

    from iwsim.core.resources import read_capped

    try:
        return json.loads(read_capped(path, 16 << 20))
    except OSError as e:
        raise InputError(f"{flag} {path}: cannot read it ({e.strerror}).") from None
    except (json.JSONDecodeError, UnicodeDecodeError) as e:
        raise InputError(f"{flag} {path} is not valid JSON: {e}.") from None
