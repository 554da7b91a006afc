"""The errors ``iwsim`` reports to its user as one line (:func:`reporting_errors`, which
``cli.main`` and the bench scripts run under, catches these, and OSError, and nothing else):
everything else is a bug and shows its traceback."""

from __future__ import annotations

import os
import sys
from collections.abc import Callable
from typing import Any

EXIT_USER_ERROR = 1  # bad values the library rejected (argparse's own usage errors exit 2)


class IwsimError(Exception):
    """A failure that is not a bug: the message says what happened and what to do."""


class InputError(IwsimError, ValueError):
    """Bad input from a user (a file, flag, message or action), named in one sentence with
    what was expected. A ValueError too, as these always were."""


def check_positive(args: Any, *names: str) -> None:
    """Each named integer flag of the parsed ``args``, when given, must be >= 1."""
    for name in names:
        v = getattr(args, name)
        if v is not None and v < 1:
            raise InputError(f"--{name.replace('_', '-')} must be a positive integer, got {v}.")


def check_seed(args: Any, *names: str) -> None:
    """Each named seed flag of the parsed ``args``, when given, must be >= 0 (MuJoCo's and
    NumPy's generators take no negative seeds)."""
    for name in names:
        v = getattr(args, name)
        if v is not None and v < 0:
            raise InputError(f"--{name.replace('_', '-')} must be a non-negative integer, got {v}.")


def reporting_errors(prog: str, body: Callable[[], int | None]) -> int:
    """Run a command's ``body`` and return its exit status: a user's error (an
    :class:`IwsimError` or an OSError) is one line ``prog: error: ...`` on stderr, an
    interrupt one line too; anything else is a bug and raises with its traceback."""
    try:
        return body() or 0
    except BrokenPipeError:  # e.g. `iwsim data info x | head`: the reader left, nothing to say
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return EXIT_USER_ERROR
    except (IwsimError, OSError) as e:
        print(f"{prog}: error: {one_line(e)}", file=sys.stderr)
        return EXIT_USER_ERROR
    except KeyboardInterrupt:
        print(f"{prog}: interrupted", file=sys.stderr)
        return 130


def one_line(e: BaseException) -> str:
    """An error's message on one line (an OSError as ``file: reason.``)."""
    if isinstance(e, OSError) and e.strerror and e.filename is not None:
        return f"{e.filename}: {e.strerror}."
    return " ".join(str(e).split()) or type(e).__name__
