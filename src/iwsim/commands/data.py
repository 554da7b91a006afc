"""``iwsim data``: inspect, export, import, merge and validate episode stores."""

from __future__ import annotations

import argparse
import sys

from iwsim.core.errors import EXIT_USER_ERROR, InputError, check_positive
from iwsim.core.resources import human_bytes
from iwsim.envs.registry import DEFAULT_TASK as TASK


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("data", help="inspect episode stores")
    data_sub = p.add_subparsers(dest="data_command", required=True, metavar="COMMAND")
    q = data_sub.add_parser("info", help="episodes, frames, arrays and attributes of a store")
    q.add_argument("path", help="episode store (a .zarr directory)")
    q.set_defaults(func=_data_info)
    from iwsim.data.formats import EXPORT_FORMATS, IMPORT_FORMATS

    q = data_sub.add_parser("export", help="write a store as LeRobot v3 / v2.1 or ALOHA HDF5")
    q.add_argument("--format", required=True, choices=EXPORT_FORMATS)
    q.add_argument("--in", dest="src", required=True, help="episode store")
    q.add_argument("--out", required=True, help="output directory (must not exist)")
    q.add_argument("--fps", type=int, help="frames per second (default: the store's)")
    q.add_argument("--task", help="task description (default: the store's task)")
    q.add_argument("--no-progress", action="store_true", help="hide the progress bar")
    q.set_defaults(func=_data_export)
    q = data_sub.add_parser("import", help="read LeRobot, ALOHA/robomimic HDF5 or Diffusion Policy Zarr into a store")
    q.add_argument("--format", required=True, choices=IMPORT_FORMATS)
    q.add_argument("--in", dest="src", required=True, help="dataset directory or file")
    q.add_argument("--out", required=True, help="episode store to create (must not exist)")
    q.add_argument("--camera", help="import only this camera, as a store of one view (default: every camera of the "
                                    "source, the first as data/img, each further one as data/img_<name>)")
    q.add_argument("--image-size", type=int, default=TASK.image_size,
                   help="frame size after a centred square crop; 0 keeps the source's (default: %(default)s)")
    q.add_argument("--no-progress", action="store_true", help="hide the progress bar")
    q.set_defaults(func=_data_import)
    q = data_sub.add_parser("merge", help="episode stores of one task into a new store (e.g. play + expert data)")
    q.add_argument("sources", nargs="+", help="episode stores, in order")
    q.add_argument("--out", required=True, help="episode store to create (must not exist)")
    q.add_argument("--no-progress", action="store_true", help="hide the progress bar")
    q.set_defaults(func=_data_merge)
    q = data_sub.add_parser("validate", help="check a store or an export against its format; list what is wrong")
    q.add_argument("path", help="episode store, LeRobot dataset directory or HDF5 file/directory")
    q.set_defaults(func=_data_validate)


def _data_info(args: argparse.Namespace) -> int:
    from iwsim.data.store import EpisodeStore
    from iwsim.data.views import store_cameras

    info = EpisodeStore.open(args.path, "r").info()
    attrs = info["attrs"]
    rows = [
        ("path", info["path"]),
        ("task", f"{info['task']} (policy {attrs['policy']})" if "policy" in attrs else info["task"]),
        ("episodes", info["episodes"]),
        ("frames", info["frames"]),
        ("fps", info["fps"]),
        ("image size", info["image_size"]),
        ("cameras", ", ".join(store_cameras(attrs, info["arrays"]))),
        ("size on disk", human_bytes(info["bytes_on_disk"])),
    ]
    width = max(len(k) for k, _ in rows)
    lines = [f"{k:<{width}}  {v}" for k, v in rows]
    lines.append("arrays")
    kw = max((len(k) for k in info["arrays"]), default=0)
    for k, a in info["arrays"].items():
        lines.append(f"  {k:<{kw}}  {str(a['shape']):<20} {a['dtype']}")
    print("\n".join(lines))
    return 0


def _data_export(args: argparse.Namespace) -> int:
    from iwsim.data.formats import export

    check_positive(args, "fps")
    print(export(args.format, args.src, args.out, fps=args.fps, task=args.task, progress=not args.no_progress))
    return 0


def _data_import(args: argparse.Namespace) -> int:
    from iwsim.data.formats import import_

    if args.image_size < 0:
        raise InputError(f"--image-size must be a positive integer or 0, got {args.image_size}.")
    store = import_(args.format, args.src, args.out, camera=args.camera, image_size=args.image_size or None,
                    progress=not args.no_progress)
    print(f"{store.path}: {store.n_episodes} episodes, {store.n_frames} frames")
    return 0


def _data_merge(args: argparse.Namespace) -> int:
    from iwsim.data.formats import merge

    store = merge(args.sources, args.out, progress=not args.no_progress)
    print(f"{store.path}: {store.n_episodes} episodes, {store.n_frames} frames ({store.attrs['policy']})")
    return 0


def _data_validate(args: argparse.Namespace) -> int:
    from iwsim.data.formats import validate

    kind, problems = validate(args.path)
    if not problems:
        print(f"{args.path}: a valid {kind}")
        return 0
    print(f"{args.path}: {kind} with {len(problems)} problem(s):", file=sys.stderr)
    for p in problems:
        print(f"  {p}", file=sys.stderr)
    return EXIT_USER_ERROR
