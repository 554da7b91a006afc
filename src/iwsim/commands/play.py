"""``iwsim play``: drive a world model from the browser and record demonstrations."""

from __future__ import annotations

import argparse
import logging

from iwsim.commands.common import read_json, wait_for_lock_flag
from iwsim.core.errors import check_positive
from iwsim.envs.registry import DEFAULT_TASK as TASK

log = logging.getLogger("iwsim")


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("play", help="drive a world model from the browser and record demonstrations")
    p.add_argument("--checkpoint", default=TASK.checkpoint, help="world model (default: %(default)s)")
    p.add_argument("--host", default="127.0.0.1",
                   help="address to bind; others need a token of your choice (default: %(default)s)")
    p.add_argument("--port", type=int, default=8000, help="port, 0 for any free one (default: %(default)s)")
    p.add_argument("--token-file", help="file whose first line is the secret sessions need (default: "
                                        "$IWSIM_PLAY_TOKEN, else a random one the page served here knows)")
    p.add_argument("--token", help="the secret on the command line (visible to other users in ps; "
                                   "prefer --token-file or $IWSIM_PLAY_TOKEN)")
    p.add_argument("--allow-origin", action="append", default=[], metavar="ORIGIN",
                   help="another web origin (http://host:port) whose pages may open sessions; repeatable")
    p.add_argument("--record-to", help="episode store that saved demonstrations are appended to")
    p.add_argument("--store", help="episode store to draw 'frame from store' starts from (for a task other than "
                                   "T-push also its starts; default: the store its checkpoint records)")
    p.add_argument("--bindings", help="JSON file of teleop bindings instead of the task's: {\"keys\": {\"w\": "
                                      "[dim, sign], ...}, \"axes\": [[axis, dim, sign], ...], \"speed\": "
                                      "[units/s per dim]}")
    p.add_argument("--hz", type=float, default=10.0, help="control rate, steps per second (default: %(default)s)")
    p.add_argument("--max-sessions", type=int, default=4, help="concurrent sessions (default: %(default)s)")
    p.add_argument("--device", default="auto", help="auto, cpu, cuda or cuda:N (default: %(default)s)")
    wait_for_lock_flag(p)
    p.set_defaults(func=_play)


def _play(args: argparse.Namespace) -> int:
    from iwsim.play.access import LOOPBACK, Access, bind, check_bind, resolve_token
    from iwsim.play.engine import check_sessions_memory

    # Before the model loads: a bad token, too many sessions for this machine's memory or a
    # taken port fails at once.
    token, source = resolve_token(args.token, args.token_file)
    bindings = None if args.bindings is None else read_json(args.bindings, "--bindings")
    check_positive(args, "max_sessions")
    check_sessions_memory(args.max_sessions)
    check_bind(args.host, token)
    sock = bind(args.host, args.port)
    try:
        access = Access.create(token, args.host, sock.getsockname()[1], args.allow_origin)
        from pathlib import Path

        from iwsim.core.trainer import resolve_device
        from iwsim.play.engine import Engine, PlayConfig
        from iwsim.play.server import serve
        from iwsim.world_model import WorldModel

        port = access.port
        cfg = PlayConfig(hz=args.hz, max_sessions=args.max_sessions, checkpoint=args.checkpoint,
                         record_to=Path(args.record_to) if args.record_to else None,
                         store=Path(args.store) if args.store else None, wait_for_lock=args.wait_for_lock,
                         bindings=bindings)
        engine = Engine(WorldModel.load(args.checkpoint, resolve_device(args.device)), cfg)
        shown = "localhost" if args.host in ("0.0.0.0", "::") else args.host
        # The token is never logged: the page served here carries it, remote users know their own.
        how = "" if args.host in LOOPBACK else f"; from elsewhere open /?token=... with the token of {source}"
        log.info("serving %s at http://%s:%d/ (%s Hz, up to %d sessions%s%s); Ctrl-C stops", args.checkpoint,
                 shown, port, args.hz, args.max_sessions,
                 f", recording to {args.record_to}" if args.record_to else "", how)
        serve(engine, sock, access)
    finally:
        sock.close()
    return 0
