"""The ``iwsim`` command line: the parser, built from the groups in :mod:`iwsim.commands`,
and ``main``, which runs the chosen subcommand's handler."""

from __future__ import annotations

import argparse
import logging
import os
import sys
from collections.abc import Sequence

from iwsim.core.errors import reporting_errors
from iwsim.core.resources import set_threads


def build_parser() -> argparse.ArgumentParser:
    from iwsim.commands import bench, collect, data, demo, evaluate, experiment, play, runs, train

    parser = argparse.ArgumentParser(prog="iwsim", description="Interactive world simulator for robot learning.")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    for group in (collect, data, train, evaluate, runs, bench, demo, play, experiment):
        group.register(sub)
    for q in _leaf_parsers(parser):
        q.add_argument("--threads", type=int,
                       help="torch threads (default: $OMP_NUM_THREADS, else the CPU cores this process may use)")
    return parser


def _leaf_parsers(parser: argparse.ArgumentParser) -> list[argparse.ArgumentParser]:
    """The parsers of every (sub)command that runs something."""
    subs = [a for a in parser._actions if isinstance(a, argparse._SubParsersAction)]
    if not subs:
        return [parser]
    return [leaf for a in subs for p in dict.fromkeys(a.choices.values()) for leaf in _leaf_parsers(p)]


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of the ``iwsim`` console script; returns the exit status."""
    args = build_parser().parse_args(argv)
    args.argv = list(sys.argv[1:] if argv is None else argv)  # what a report records of its command
    rank = int(os.environ.get("RANK", "0"))  # under torchrun only rank 0 logs
    logging.basicConfig(level=logging.INFO if rank == 0 else logging.WARNING,
                        format="%(levelname)s %(name)s: %(message)s")
    # PyOpenGL (under MuJoCo's renderer) says at import, at INFO, that its optional
    # accelerator is missing: noise, and a user error must stay one line.
    logging.getLogger("OpenGL").setLevel(logging.WARNING)
    def body() -> int:
        set_threads(args.threads)
        return args.func(args)

    return reporting_errors("iwsim", body)


if __name__ == "__main__":
    sys.exit(main())
