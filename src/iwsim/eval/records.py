"""Recorded results carry the command that reproduces them at their top: a JSON record's
first key ``"command"``, a Markdown report's line under its title (bench/README.md)."""

from __future__ import annotations

import json
import shlex
import sys
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

from iwsim.core.checkpoint import PROJECT_ROOT


def command_line(program: str, args: Sequence[str] | None = None) -> str:
    """The command line that reproduces a result, shell-quoted, as run from the project's
    root: ``iwsim ARGS`` for ``program="iwsim"``, ``python bench/NAME.py ARGS`` for a
    script (``program`` is its ``__file__``; its path is made relative to the project's
    root, else to the working directory, so no machine's directory layout is recorded).
    ``args`` defaults to this process's arguments (``sys.argv[1:]``)."""
    words = list(sys.argv[1:] if args is None else args)
    if not program.endswith(".py"):
        return shlex.join([program, *words])
    path = Path(program).resolve()
    for root in (PROJECT_ROOT, Path.cwd()):
        if path.is_relative_to(root):
            program = path.relative_to(root).as_posix()
            break
    return shlex.join(["python", program, *words])


def with_command(command: str, record: Mapping[str, Any], sort_keys: bool = False) -> dict[str, Any]:
    """``record`` with ``command`` as its first key; with ``sort_keys``, its other keys at
    every level in the order ``json.dumps(..., sort_keys=True)`` writes them (dump the
    result with ``sort_keys=False`` to keep the command first)."""
    rest = {k: v for k, v in record.items() if k != "command"}
    if sort_keys:
        rest = json.loads(json.dumps(rest, sort_keys=True))
    return {"command": command, **rest}
