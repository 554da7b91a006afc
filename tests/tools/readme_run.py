"""Run the documentation's commands in order in a fresh clone: does every one run as written?

    OMP_NUM_THREADS=1 python tests/tools/readme_run.py --list
    OMP_NUM_THREADS=1 python tests/tools/readme_run.py --venv .venv [--first N] [--skip "make test"]

The commands are those of the fenced shell blocks of README.md, then of the pages of docs/
in the order of ``DOCUMENTS`` (continuation lines joined,
comments dropped, ``[...]`` groups without placeholders kept: ``[tuned=runs/x]`` runs, the
``[--flag N]`` lists in comments do not). They run one after another in a clone of this
repository (``git clone`` of the checkout this script sits in: what is committed, not what
is only in the working tree; ``--copy`` copies the working tree instead), each through
``bash -c`` from the clone's root, long ones shrunk by the flags of ``SHRINK``: fewer
episodes, steps and workers, a tiny study preset. The shrunk stores keep what later
commands read from them (``rollout --episode 19`` becomes ``--episode 1``, and so on).

``iwsim play`` serves until stopped: it runs on a free port with a random token, its page
must load, and a WebSocket client records two short takes when it has ``--record-to``
(later commands train on them), then it is stopped. Files the reader brings (a LeRobot
dataset of their robot, a token file) are replaced by ones the README's earlier commands
made (``SUBSTITUTE``). The Python snippets are fragments (they use frames and actions
they do not define); ``tests/test_readme.py`` compiles them and checks their imports and
paths, and checks every command's flags, without running anything.

One line per command: PASS / FAIL, seconds, its file and line and the command as run; a
failure prints the end of its log (kept under the clone's ``readme_logs/``) and stops the
run (``--keep-going`` goes on). Exit status 1 when any command failed. ``--venv DIR``
skips the installation ``make`` would do: ``.venv/bin/python`` and ``.venv/bin/iwsim`` of
the clone run DIR's interpreter on the clone's sources (and ``make`` finds its install
stamp, so nothing is installed into DIR). Without it the first ``make`` creates the
clone's own ``.venv`` (downloads PyTorch).
"""

from __future__ import annotations

import argparse
import json
import math
import os
import re
import secrets
import shlex
import shutil
import signal
import socket
import subprocess
import tempfile
import time
import urllib.request
from dataclasses import dataclass, field, replace
from pathlib import Path

from iwsim.core.errors import InputError, reporting_errors

REPO = Path(__file__).resolve().parents[2]

SHELL_LANGS = ("bash", "sh", "shell", "console", "zsh")
FENCE = re.compile(r"^(\s*)```\s*([\w+-]*)\s*$")
SEPARATORS = ("&&", "||", ";", "|", "&")
ENV_ASSIGNMENT = re.compile(r"^[A-Za-z_][A-Za-z0-9_]*=")
# A placeholder stands for a value the reader chooses: NAME, RUN_OR_CHECKPOINT, N, <run>, `...`.
PLACEHOLDER = re.compile(r"^(?:[A-Z][A-Z0-9_]*|<[^>]*>|\.\.\.)$")
SAFE_WORD = re.compile(r"^[\w@%+=:,./~*?-]+$")  # a word bash takes as it is, or expands (~, globs) as typed
GROUP = re.compile(r"(?<!\S)\[([^\[\]]*)\](?!\S)")  # an optional group: [--flag value] or [NAME=PATH]


# -- the README's commands ------------------------------------------------------------------


@dataclass(frozen=True)
class Command:
    """One shell command of a fenced block. ``argv`` is the program and its arguments
    (without environment assignments, wrappers such as ``taskset -c 0`` and ``[...]``
    groups), ``optional`` each ``[...]`` group of the code as (its place in ``argv``, its
    tokens), ``commented`` the tokens of each ``[--flag ...]`` group in its comments (they
    go at the end), ``alternatives`` the values listed by a trailing ``# or a, b`` comment."""

    line: int
    text: str
    argv: tuple[str, ...]
    env: tuple[tuple[str, str], ...] = ()
    wrapper: tuple[str, ...] = ()
    optional: tuple[tuple[int, tuple[str, ...]], ...] = ()
    commented: tuple[tuple[str, ...], ...] = ()
    alternatives: tuple[str, ...] = ()
    background: bool = False
    source: str = "README.md"  # the file it is in, relative to the repository

    @property
    def words(self) -> tuple[str, ...]:
        """``argv`` with the program named as the table names it: ``iwsim``, ``python``, ``make``."""
        name = Path(self.argv[0]).name
        if re.fullmatch(r"python(3(\.\d+)*)?", name):
            name = "python"
        return (name, *self.argv[1:])

    def with_optional(self, placeholders: bool = False) -> tuple[str, ...]:
        """``argv`` with the code's ``[...]`` groups in their places: those that hold no
        placeholder (they run), or all of them."""
        argv = list(self.argv)
        for at, group in reversed(self.optional):
            if placeholders or not any(PLACEHOLDER.match(t) for t in group):
                argv[at:at] = group
        return tuple(argv)


@dataclass(frozen=True)
class Snippet:
    """A fenced Python block; ``line`` is the README line of its first code line."""

    line: int
    code: str
    source: str = "README.md"


@dataclass(frozen=True)
class Block:
    lang: str
    lines: tuple[tuple[int, str], ...]  # (README line, text without the fence's indentation)


def fenced_blocks(text: str) -> list[Block]:
    """The fenced code blocks of a markdown text, fences indented under list items too."""
    blocks: list[Block] = []
    current: list[tuple[int, str]] | None = None
    lang = indent = ""
    for n, line in enumerate(text.splitlines(), 1):
        m = FENCE.match(line)
        if current is None:
            if m:
                current, indent, lang = [], m.group(1), m.group(2).lower()
        elif m and not m.group(2):
            blocks.append(Block(lang, tuple(current)))
            current = None
        else:
            current.append((n, line[len(indent):] if line.startswith(indent) else line.lstrip()))
    if current is not None:
        raise InputError(f"README line {current[0][0] - 1 if current else '?'}: a fenced block is never closed.")
    return blocks


def split_comment(line: str) -> tuple[str, str]:
    """A shell line's code and its comment (a ``#`` that starts a word outside quotes)."""
    quote = ""
    for i, c in enumerate(line):
        if quote:
            if c == quote:
                quote = ""
        elif c in "'\"":
            quote = c
        elif c == "#" and (i == 0 or line[i - 1].isspace()):
            return line[:i], line[i + 1:]
    return line, ""


def _tokens(code: str) -> list[str]:
    lex = shlex.shlex(code, posix=True, punctuation_chars=";&|")
    lex.whitespace_split = True
    lex.commenters = ""
    return list(lex)


def _command(line: int, text: str, tokens: list[str], background: bool,
             groups: list[tuple[str, ...]]) -> Command:
    env = []
    while tokens and ENV_ASSIGNMENT.match(tokens[0]):
        name, _, value = tokens.pop(0).partition("=")
        env.append((name, value))
    wrapper = []
    if tokens and tokens[0] == "taskset":  # taskset [-c LIST | MASK] COMMAND
        wrapper.append(tokens.pop(0))
        while tokens and tokens[0].startswith("-"):
            flag = tokens.pop(0)
            wrapper.append(flag)
            if flag in ("-c", "--cpu-list"):
                wrapper.append(tokens.pop(0))
                break
        else:
            wrapper.append(tokens.pop(0))
    while tokens and tokens[0] in ("nohup", "time"):
        wrapper.append(tokens.pop(0))
    argv, optional = [], []
    for t in tokens:
        m = re.fullmatch(r"\x00(\d+)", t)
        if m:
            optional.append((len(argv), groups[int(m.group(1))]))
        else:
            argv.append(t)
    return Command(line, text, tuple(argv), tuple(env), tuple(wrapper), tuple(optional), background=background)


def shell_commands(block: Block) -> list[Command]:
    """The commands of a shell block, in order."""
    commands: list[Command] = []
    pending: list[tuple[int, str, str]] = []  # the physical lines of a logical line: (line, code, comment)
    for n, raw in block.lines:
        code, comment = split_comment(raw)
        continued = code.rstrip().endswith("\\")
        if continued:
            code = code.rstrip()[:-1]
        pending.append((n, code, comment))
        if continued:
            continue
        first, codes, comments = pending[0][0], [c for _, c, _ in pending], [c for _, _, c in pending]
        pending = []
        code = " ".join(c.strip() for c in codes).strip()
        groups = [m.group(1) for c in comments for m in GROUP.finditer(c) if m.group(1).startswith("--")]
        if not code:  # a comment line: its [--flag ...] groups belong to the command above
            if commands and groups:
                last = commands[-1]
                commands[-1] = replace(last, commented=last.commented + tuple(tuple(_tokens(g)) for g in groups))
            continue
        optional: list[tuple[str, ...]] = []  # each [...] group leaves a marker token in its place
        pieces, at = [], 0
        for m in GROUP.finditer(code):
            pieces += [code[at:m.start()], f" \x00{len(optional)} "]
            optional.append(tuple(_tokens(m.group(1))))
            at = m.end()
        tokens = _tokens("".join(pieces) + code[at:])
        segments: list[tuple[list[str], bool]] = [([], False)]
        for t in tokens:
            if t in SEPARATORS:
                segments[-1] = (segments[-1][0], t == "&")
                segments.append(([], False))
            else:
                segments[-1][0].append(t)
        parts = [_command(first, code, toks, bg, optional) for toks, bg in segments if toks]
        if not parts:
            continue
        alternatives: tuple[str, ...] = ()
        trailing = comments[-1].strip() if comments else ""
        if re.match(r"or [\w.-]+(, [\w.-]+)*$", trailing):
            alternatives = tuple(v.strip() for v in trailing[3:].split(","))
        parts[-1] = replace(parts[-1], alternatives=alternatives, commented=tuple(tuple(_tokens(g)) for g in groups))
        commands += parts
    return commands


def readme_items(path: Path, source: str | None = None) -> list[Command | Snippet]:
    """A markdown file's shell commands and Python snippets, in the order they appear;
    ``source``: the file's name in their reports (default: its name)."""
    source = source or path.name
    items: list[Command | Snippet] = []
    for block in fenced_blocks(path.read_text()):
        if block.lang in SHELL_LANGS:
            items += [replace(c, source=source) for c in shell_commands(block)]
        elif block.lang == "python" and block.lines:
            items.append(Snippet(block.lines[0][0], "\n".join(text for _, text in block.lines) + "\n", source))
    return items


# The documentation, in the order a reader runs it: the README, then the pages it links. A
# page's commands may read what an earlier page's wrote (the data page's stores, say).
DOCUMENTS = ("README.md", "docs/tasks.md", "docs/data.md", "docs/training.md", "docs/play.md", "docs/policies.md",
             "docs/own-robot.md", "docs/benchmarks.md", "docs/studies.md", "docs/yardstick.md", "docs/layout.md")


def documentation_items(root: Path = REPO) -> list[Command | Snippet]:
    """The commands and snippets of every file of :data:`DOCUMENTS`, in that order."""
    return [item for doc in DOCUMENTS for item in readme_items(root / doc, doc)]


# -- shrinking ---------------------------------------------------------------------------------

# Command prefix (as `Command.words` begin) -> flags replaced or added; None drops a flag, and
# a string instead of a dict replaces the whole command. Every row whose prefix matches
# applies, in order. The stores stay big enough for what later commands read from them: 4
# episodes of 40 steps (a held-out episode, and windows for the longest unroll, 24).
SHRINK: tuple[tuple[str, dict[str, str | None] | str], ...] = (
    ("make test", "make test-fast"),
    ("iwsim collect", {"--episodes": "4", "--steps": "40", "--workers": "1"}),
    ("iwsim train ae", {"--steps": "2"}),
    ("iwsim train dynamics", {"--steps": "2"}),
    ("iwsim train policy", {"--steps": "2"}),
    ("iwsim train policy --policy act --data data/wm_demos.zarr:30,data/pusht_expert.zarr:70",
     {"--data": "data/wm_demos.zarr:1,data/pusht_expert.zarr:3"}),
    ("iwsim train decoder-finetune", {"--steps": "2"}),
    ("iwsim rollout", {"--steps": "16"}),
    ("iwsim rollout --checkpoint runs/wm --data data/pusht_play.zarr --episode 19", {"--episode": "1"}),
    ("iwsim eval policy", {"--episodes": "2", "--steps": "20", "--videos": "1"}),
    # data/contact.zarr's 8 episodes hold one held-out episode (the split holds out every 20th)
    ("iwsim bench", {"--episodes": "1", "--steps": "8", "--stability-steps": "20", "--speed-batch": "2",
                     "--speed-calls": "2"}),
    # its own work directory: the tiny studies' demonstration recipes differ, and they may not
    # share one store (the full presets do)
    ("iwsim experiment datagen", {"--preset": "tiny", "--jobs": "1", "--work": "runs/experiments_datagen"}),
    ("iwsim experiment datagen --preset act", {"--policy": "act"}),
    # 100 demonstrations keep the run names (dp-100demos) the yardstick's --zoo reads
    ("iwsim experiment policy-eval", {"--preset": "tiny", "--demo-episodes": "100", "--jobs": "1"}),
    ("python bench/ablate_dynamics.py train", {"--steps": "2"}),
    ("python bench/ablate_dynamics.py eval", {"--episodes": "2", "--horizon": "32"}),
    ("python bench/wm_studies_check.py", {"--episodes": "2", "--steps": "20", "--candidates": "2"}),
    ("python bench/yardstick.py", {"--episodes": "2", "--steps": "20", "--candidates": "2", "--horizon": "32",
                                   "--stability-steps": "20", "--speed-calls": "2", "--family-seeds": "2",
                                   "--idle-episodes": "2"}),
    ("python bench/bench_task.py", {"--quick": ""}),
    ("python bench/bench_ae.py", {"--frames": "20"}),
    ("python bench/bench_play.py", {"--configs": "1@10", "--seconds": "2", "--warmup": "1"}),
)

# Files the reader brings, replaced by ones the README's earlier commands made ({work}: the
# run's scratch directory, outside the clone).
SUBSTITUTE = {
    "~/datasets/my_robot": "outputs/pusht_lerobot",  # a LeRobot v3 dataset: the export of data/pusht_play.zarr
    "~/.iwsim-token": "{work}/iwsim-token",
}


def _matches(words: tuple[str, ...], prefix: str) -> bool:
    p = tuple(prefix.split())
    return words[:len(p)] == p


def _set_flag(argv: list[str], flag: str, value: str | None) -> list[str]:
    if flag in argv:
        i = argv.index(flag)
        has_value = i + 1 < len(argv) and not argv[i + 1].startswith("--")
        if value is None:
            return argv[:i] + argv[i + 1 + has_value:]
        if value == "" or not has_value:
            return argv[:i + 1] + ([value] if value else []) + argv[i + 1:]
        return argv[:i + 1] + [value] + argv[i + 2:]
    if value is None:
        return argv
    return argv + [flag] + ([value] if value else [])


def shrink(cmd: Command, work: str = "{work}") -> Command:
    """``cmd`` as the run executes it: ``SHRINK``'s flags applied, the reader's files
    substituted, the code's concrete ``[...]`` groups included."""
    argv = list(cmd.with_optional())
    for prefix, change in SHRINK:
        if not _matches(cmd.words, prefix):
            continue
        if isinstance(change, str):
            argv = change.split()
        else:
            for flag, value in change.items():
                argv = _set_flag(argv, flag, value)

    def sub(s: str) -> str:
        for mine, theirs in SUBSTITUTE.items():
            s = s.replace(mine, theirs.format(work=work))
        return s

    return replace(cmd, argv=tuple(sub(a) for a in argv), env=tuple((k, sub(v)) for k, v in cmd.env),
                   optional=(), commented=())


def shell_line(cmd: Command) -> str:
    """The command as one bash line: words bash takes as they are stay so (a ``~`` or a
    glob expands as typed), environment values that are not go in double quotes (so a
    ``$(...)`` in them runs as typed), other words in single quotes."""
    env = [f"{k}={v}" if SAFE_WORD.match(v) else f'{k}="{_escape_double(v)}"' for k, v in cmd.env]
    return " ".join([*env, *(a if SAFE_WORD.match(a) else shlex.quote(a) for a in (*cmd.wrapper, *cmd.argv))])


def _escape_double(value: str) -> str:
    return re.sub(r'(["`\\])', r"\\\1", value)


def is_play(cmd: Command) -> bool:
    return cmd.words[:2] == ("iwsim", "play")


# -- running -----------------------------------------------------------------------------------


@dataclass
class Run:
    root: Path  # the clone
    work: Path  # scratch outside it (the token file)
    env: dict[str, str]
    timeout: float
    logs: Path = field(init=False)

    def __post_init__(self) -> None:
        self.logs = self.root / "readme_logs"
        self.logs.mkdir(exist_ok=True)


def prepare(dest: Path, copy: bool, venv: Path | None) -> None:
    """A clone (or copy) of this checkout at ``dest``; with ``venv``, wrappers in place of
    the ``.venv`` that ``make`` would create."""
    if copy:
        ignored = _gitignored_names()
        shutil.copytree(REPO, dest, symlinks=True,
                        ignore=lambda d, names: [n for n in names if n == ".git" or (Path(d) == REPO and n in ignored)])
    else:
        subprocess.run(["git", "clone", "--quiet", str(REPO), str(dest)], check=True)
    if venv is not None:
        python = venv.resolve() / "bin" / "python"
        if not python.exists():
            raise InputError(f"--venv {venv}: no {python}.")
        bin_dir = dest / ".venv" / "bin"
        bin_dir.mkdir(parents=True)
        env = f'PYTHONPATH="{dest / "src"}${{PYTHONPATH:+:$PYTHONPATH}}"'
        scripts = {"python": f'{env} exec "{python}" "$@"',
                   "iwsim": f'{env} exec "{python}" -c "import sys; from iwsim.cli import main; sys.exit(main())" "$@"'}
        for name, body in scripts.items():
            (bin_dir / name).write_text(f"#!/bin/sh\n{body}\n")
            (bin_dir / name).chmod(0o755)
        (dest / ".venv" / ".installed").touch()  # make's install stamp, newer than pyproject.toml


def _gitignored_names() -> set[str]:
    """Top-level names the checkout's .gitignore ignores (the copy leaves out data, runs, ...)."""
    names = set()
    for line in (REPO / ".gitignore").read_text().splitlines():
        line = line.strip().strip("/")
        if line and "/" not in line and not any(c in line for c in "*?[!#"):
            names.add(line)
    return names | {e.name for e in REPO.iterdir() if e.name.endswith(".egg-info")}


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def run_command(cmd: Command, run: Run, index: int) -> tuple[bool, str]:
    """Run one (shrunk) command; ``(passed, log path)``."""
    log = run.logs / f"{index:02d}_{re.sub(r'[^A-Za-z0-9]+', '_', ' '.join(cmd.words[:3]))}.log"
    with open(log, "w") as f:
        f.write(f"$ {shell_line(cmd)}\n")
        f.flush()
        if is_play(cmd):
            return drive_play(cmd, run, f), str(log)
        proc = spawn(cmd, run, f)
        try:
            code = proc.wait(run.timeout)
        except subprocess.TimeoutExpired:
            f.write(f"\nreadme_run: timed out after {run.timeout:g} s\n")
            return False, str(log)
        finally:
            stop(proc, signal.SIGKILL)
        f.write(f"\nreadme_run: exit status {code}\n")
        return code == 0, str(log)


def spawn(cmd: Command, run: Run, log, env: dict[str, str] | None = None) -> subprocess.Popen:
    """``cmd`` through bash in a process group of its own (so all of it can be stopped)."""
    return subprocess.Popen(["bash", "-c", shell_line(cmd)], cwd=run.root, env={**run.env, **(env or {})},
                            stdout=log, stderr=subprocess.STDOUT, start_new_session=True)


def stop(proc: subprocess.Popen, sig: int) -> None:
    """Signal ``proc``'s process group if it still runs (SIGKILL after 30 s); reap it."""
    if proc.poll() is None:
        os.killpg(proc.pid, sig)
        try:
            proc.wait(30)
        except subprocess.TimeoutExpired:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait()


def start_background(cmd: Command, run: Run, index: int) -> tuple[subprocess.Popen, str]:
    log = run.logs / f"{index:02d}_background.log"
    with open(log, "w") as f:  # the child keeps its own descriptor
        f.write(f"$ {shell_line(cmd)}\n")
        f.flush()
        return spawn(cmd, run, f), str(log)


def drive_play(cmd: Command, run: Run, log) -> bool:
    """``iwsim play`` on a free port: its page must load; with ``--record-to`` a client
    records two takes of 20 steps. Then it is stopped (SIGINT, as Ctrl-C)."""
    port = free_port()
    cmd = replace(cmd, argv=(*cmd.argv, "--port", str(port)))
    token = (run.work / "iwsim-token").read_text().strip()
    proc = spawn(cmd, run, log, {"IWSIM_PLAY_TOKEN": token})
    try:
        deadline = time.monotonic() + min(run.timeout, 300)
        while True:  # the port listens before the model is loaded: wait for the page itself
            if proc.poll() is not None:
                log.write(f"\nreadme_run: iwsim play exited ({proc.returncode}) before serving\n")
                return False
            try:
                urllib.request.urlopen(f"http://127.0.0.1:{port}/", timeout=2).close()
                break
            except OSError:
                if time.monotonic() > deadline:
                    log.write("\nreadme_run: the page did not load\n")
                    return False
                time.sleep(0.3)
        log.write("\nreadme_run: the page loads\n")
        if "--record-to" in cmd.argv:
            for take in range(2):
                record_take(f"ws://127.0.0.1:{port}/ws?token={token}", steps=20, seed=take)
                log.write(f"readme_run: take {take} saved\n")
        log.flush()
        return proc.poll() is None
    except (OSError, RuntimeError, TimeoutError) as e:
        log.write(f"\nreadme_run: {type(e).__name__}: {e}\n")
        return False
    finally:
        stop(proc, signal.SIGINT)


def record_take(url: str, steps: int, seed: int) -> None:
    """One take through the play protocol: record, ``steps`` commands (a slow sway of the
    first action dimension within its bounds, one per frame), save."""
    from websockets.sync.client import connect

    from iwsim.play.protocol import unpack_frame

    def recv(ws) -> tuple[dict, bool]:
        data = ws.recv(timeout=60)
        if isinstance(data, str):
            return json.loads(data), False
        return unpack_frame(data)[0], True

    with connect(url, max_size=None, open_timeout=60) as ws:
        hello, _ = recv(ws)
        if hello.get("type") != "hello":
            raise RuntimeError(f"expected hello, got {hello}")
        low, high = hello["action_low"], hello["action_high"]
        header, is_frame = recv(ws)
        while not is_frame:
            header, is_frame = recv(ws)
        start = list(header["action"])
        ws.send(json.dumps({"type": "record"}))
        seq = frames = 0
        while frames < steps:
            msg, is_frame = recv(ws)
            if not is_frame:
                if msg.get("type") == "error":
                    raise RuntimeError(f"iwsim play: {msg.get('message')}")
                continue
            frames += 1
            seq += 1
            action = list(start)
            swing = 0.05 * (high[0] - low[0]) * math.sin(2 * math.pi * (frames + 5 * seed) / steps)
            action[0] = min(max(start[0] + swing, low[0]), high[0])
            ws.send(json.dumps({"type": "action", "seq": seq, "action": action}))
        ws.send(json.dumps({"type": "save"}))
        while True:
            msg, is_frame = recv(ws)
            if not is_frame and msg.get("type") == "saved":
                return
            if not is_frame and msg.get("type") == "error":
                raise RuntimeError(f"iwsim play: {msg.get('message')}")


def describe(cmd: Command) -> str:
    return shell_line(cmd) + (" &" if cmd.background else "")


def listing(items: list[Command | Snippet], skip: list[str]) -> list[str]:
    lines = []
    for cmd in (i for i in items if isinstance(i, Command)):
        small = shrink(cmd)
        note = ""
        if any(_matches(cmd.words, s) for s in skip):
            note = "  (skipped: --skip)"
        elif is_play(cmd):
            note = "  (served on a free port; page loaded" + (", two takes recorded" if "--record-to" in cmd.argv
                                                          else "") + ", then stopped)"
        lines.append(f"{cmd.source}:{cmd.line:<5d} {cmd.text}{note}")
        if describe(small) != describe(replace(cmd, argv=cmd.with_optional())):
            lines.append(f"{'':12s}-> {describe(small)}")
    snippets = [i for i in items if isinstance(i, Snippet)]
    lines.append(f"({len(snippets)} Python snippets, at {', '.join(f'{s.source}:{s.line}' for s in snippets)}: "
                 "fragments, not run; tests/test_readme.py compiles them)")
    return lines


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--list", action="store_true", help="print the commands and their shrunk forms; run nothing")
    p.add_argument("--venv", type=Path, help="an installed iwsim environment to run the clone's sources with, "
                                             "instead of the .venv make would install")
    p.add_argument("--copy", action="store_true", help="copy this working tree instead of cloning what is committed")
    p.add_argument("--first", type=int, help="run only the first N commands")
    p.add_argument("--skip", action="append", default=[], metavar="PREFIX",
                   help="skip commands that begin so (as the SHRINK table names them, e.g. 'make test'); repeatable")
    p.add_argument("--timeout", type=float, default=3600, help="seconds per command (default: %(default)s)")
    p.add_argument("--keep-going", action="store_true", help="run the rest after a failure")
    p.add_argument("--keep", action="store_true", help="keep the clone after a run that passed")
    args = p.parse_args(argv)

    if args.list:
        print("\n".join(listing(documentation_items(), args.skip)))
        return 0
    from tqdm import tqdm

    work = Path(tempfile.mkdtemp(prefix="iwsim-readme-"))
    root = work / "iwsim"
    (work / "iwsim-token").write_text(secrets.token_urlsafe(16) + "\n")
    prepare(root, args.copy, args.venv)
    commands = [i for i in documentation_items(root) if isinstance(i, Command)][:args.first]
    # PYTHONPATH is the wrappers' business: an inherited one would run another checkout's sources
    run = Run(root, work, {k: v for k, v in os.environ.items() if k != "PYTHONPATH"}, args.timeout)
    print(f"{'clone' if not args.copy else 'copy'} of {REPO} in {root}", flush=True)
    failed = 0
    pending: list[tuple[Command, subprocess.Popen, str, float]] = []  # background jobs (`... &`)
    bar = tqdm(total=len(commands), desc="docs", unit="cmd", disable=None)  # no bar when not a terminal

    def report(cmd: Command, passed: bool, log: str, seconds: float) -> None:
        nonlocal failed
        bar.write(f"{'PASS' if passed else 'FAIL'}  {seconds:6.1f}s  {cmd.source}:{cmd.line:<5d} {describe(cmd)}")
        if not passed:
            failed += 1
            tail = Path(log).read_text().splitlines()[-15:]
            bar.write("\n".join(f"      | {t}" for t in tail) + f"\n      (log: {log})")

    def wait_pending() -> None:
        for cmd, proc, log, started in pending:
            try:
                code = proc.wait(max(1.0, run.timeout - (time.perf_counter() - started)))
            except subprocess.TimeoutExpired:
                code = None
            finally:
                stop(proc, signal.SIGKILL)
            report(cmd, code == 0, log, time.perf_counter() - started)
        pending.clear()

    try:
        for i, cmd in enumerate(commands):
            small = shrink(cmd, str(work))
            if any(_matches(cmd.words, s) for s in args.skip):
                bar.write(f"SKIP  {'':>7s}  {cmd.source}:{cmd.line:<5d} {describe(small)}")
            elif small.background:
                pending.append((small, *start_background(small, run, i), time.perf_counter()))
            else:
                t0 = time.perf_counter()
                ok, log = run_command(small, run, i)
                wait_pending()  # a job sent to the background ends with the command after it, as in its block
                report(small, ok, log, time.perf_counter() - t0)
            bar.update()
            if failed and not args.keep_going:
                break
        wait_pending()
    finally:
        for _, proc, _, _ in pending:
            stop(proc, signal.SIGKILL)
        bar.close()
    if failed:
        print(f"{failed} command(s) failed; the clone is kept in {root}")
        return 1
    if args.keep:
        print(f"all passed; the clone is kept in {root}")
    else:
        shutil.rmtree(work)
        print("all passed")
    return 0


if __name__ == "__main__":
    raise SystemExit(reporting_errors("readme_run.py", main))
