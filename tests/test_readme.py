"""The documentation's commands, snippets and the names its prose gives (README.md, then the
pages of docs/ in the order of ``DOCUMENTS``, one reader's session: a page may read what an
earlier one wrote), checked without running anything expensive
(``tests/tools/readme_run.py`` runs the commands, slowly). Each failure names its file and
line. The fenced shell blocks:

- ``iwsim ...`` parses with the real parser (``iwsim.cli.build_parser``; parsing runs no
  handler), every flag spelled out (argparse would take an abbreviation, which a new flag
  can make ambiguous), and the values a handler checks first are known: a preset, a
  ``--variant``, a collect ``--task``, ``--policy`` or ``--image-size``.
- ``make X``: X is a Makefile target. ``bash FILE``: FILE exists.
- ``python bench/X.py ...`` (or ``scripts/X.py``): the script exists and the parser its
  ``main()`` builds accepts the arguments (captured at ``parse_args``, so nothing after it
  runs; the scripts have no parser-building function of their own). ``python -m M``: M exists (``iwsim.cli``
  parses as above).
- Shell: continuation lines are joined, comments dropped, environment assignments
  (``MUJOCO_GL=egl``) and wrappers (``taskset -c 0``) set aside, ``&&``, ``;``, ``|`` and
  ``&`` split commands.
- Placeholders (an ALL-CAPS word such as NAME or N, ``<run>``, or ``...``) stand for what
  the reader chooses: ``...`` is dropped, the others are parsed as the flag's value (``1``
  for a numeric flag) and are never paths. A ``[...]`` group in the code is optional: it is
  parsed in its place. ``[--flag ...]`` groups in comments (lists of further flags) are
  parsed at the end of the command above them. A trailing ``# or a, b`` lists other values
  of the command's flag with choices: each must be one of them.
- Paths: every path a command reads (its store, run, checkpoint, dataset flags and
  positionals, also by default, e.g. the yardstick's ``data/play_eval.zarr``) is committed
  (it exists in the checkout outside what .gitignore ignores) or lies under a path an
  earlier command writes (``--out``, ``--work``, ``--record-to``, ``--latent-cache``,
  by default too, e.g. a study's ``runs/experiments``). A value counts as a path when it
  holds a ``/`` or ends in ``.zarr``; ``NAME=PATH`` pairs, ``STORE:N`` mixtures, comma lists
  and globs (up to the first ``*``) are split first. Paths under ``~`` or absolute are the
  reader's own files (``~/datasets/my_robot``) and are not checked. ``--dry-run`` reads
  nothing. ``make`` targets' own reads are not followed.
- The fenced Python snippets compile; their imports resolve (modules and the names taken from them,
  names imported by an earlier snippet stay bound, as in one session); attribute chains on
  imported names exist (``iwsim.WorldModel.load``); ``gym.make`` ids are registered; their
  string literals under ``data/``, ``runs/``, ``checkpoints/`` and ``outputs/`` follow the
  path rule above. They are fragments (they use frames and actions they do not define), so
  they are not run.
- The prose's inline code: ``iwsim ...`` names real subcommands and spells out their flags
  (spans are fragments: nothing else is parsed), ``make X`` is a target, ``bench/X.py
  --flag`` (or ``scripts/X.py --flag``) is a flag of that script, a dotted ``iwsim.`` name
  resolves, and files of the repository it names (``src/``, ``iwsim/``, ``bench/``,
  ``scripts/``, ``tests/``, ``checkpoints/``), as its relative links, are committed.
"""

from __future__ import annotations

import argparse
import ast
import contextlib
import fnmatch
import functools
import importlib
import importlib.util
import io
import json
import logging
import os
import re
from pathlib import Path
from types import ModuleType
from unittest import mock

import pytest

from tests.tools.readme_run import DOCUMENTS, FENCE, PLACEHOLDER, Command, Snippet, documentation_items, readme_items
from tests.tools.scripts import load_script

ROOT = Path(__file__).resolve().parents[1]

README = ROOT / "README.md"
READS = {"data", "src", "path", "sources", "checkpoint", "ae", "init", "run", "world_model", "trust_model", "decoder",
         "novelty_data", "store", "bindings", "token_file", "demos", "models", "baselines", "zoo", "merge", "weights",
         "takeover"}
WRITES = {"out", "work", "record_to", "latent_cache", "table"}
SNIPPET_PATHS = ("data/", "runs/", "checkpoints/", "outputs/")


# -- parsers ------------------------------------------------------------------------------------


@functools.cache
def iwsim_parser() -> argparse.ArgumentParser:
    from iwsim.cli import build_parser

    return build_parser()


class _Captured(Exception):
    def __init__(self, parser: argparse.ArgumentParser) -> None:
        self.parser = parser


@functools.cache
def script_parser(path: Path) -> argparse.ArgumentParser:
    """The parser a bench script's ``main()`` builds, taken at its ``parse_args``."""
    module = load_script(path, "_readme")

    def capture(self: argparse.ArgumentParser, *args: object, **kwargs: object) -> None:
        raise _Captured(self)

    with mock.patch.object(argparse.ArgumentParser, "parse_args", capture), \
            mock.patch.object(logging, "basicConfig"):
        try:
            module.main()
        except _Captured as c:
            return c.parser
    raise AssertionError(f"{path.name}'s main() parsed no arguments")


def leaf(parser: argparse.ArgumentParser, argv: list[str]) -> argparse.ArgumentParser:
    """The (sub)parser the subcommand words of ``argv`` select."""
    for token in argv:
        subs = [a for a in parser._actions if isinstance(a, argparse._SubParsersAction)]
        if subs and token in subs[0].choices:
            parser = subs[0].choices[token]
    return parser


def fill_placeholders(parser: argparse.ArgumentParser, argv: list[str]) -> list[str]:
    """Placeholders as values: ``...`` dropped, a number for a numeric flag."""
    out: list[str] = []
    sub = leaf(parser, argv)
    for token in argv:
        if token == "...":
            continue
        if PLACEHOLDER.match(token) and out and out[-1] in sub._option_string_actions:
            kind = sub._option_string_actions[out[-1]].type
            token = "1" if kind in (int, float) else token
        out.append(token)
    return out


def parse(parser: argparse.ArgumentParser, argv: list[str]) -> argparse.Namespace | str:
    """The namespace, or argparse's error line (it exits; no handler runs)."""
    err = io.StringIO()
    try:
        with contextlib.redirect_stderr(err), contextlib.redirect_stdout(io.StringIO()):
            return parser.parse_args(fill_placeholders(parser, argv))
    except SystemExit:
        lines = err.getvalue().strip().splitlines()
        return lines[-1] if lines else "argparse exited"


@functools.cache
def make_targets() -> frozenset[str]:
    targets = set()
    for line in (ROOT / "Makefile").read_text().splitlines():
        m = re.match(r"^([^\s:=#][^:=]*):(?!=)", line)
        if m:
            targets.update(m.group(1).split())
    return frozenset(targets)


# -- the values handlers check first --------------------------------------------------------------


def semantic_problems(words: tuple[str, ...], ns: argparse.Namespace) -> list[str]:
    problems = []
    if words[:2] == ("iwsim", "collect"):
        from iwsim.envs import IMAGE_SIZES, POLICIES, TASKS

        learned = "/" in ns.policy  # a policy run or checkpoint: a read (reads_and_writes)
        task = ns.task or "pusht"  # a scripted policy's default (a learned one's task is its own)
        for flag, value, allowed in (("--task", task, TASKS), ("--policy", ns.policy, POLICIES.get(task, ())),
                                     ("--image-size", ns.image_size, IMAGE_SIZES)):
            if flag == "--policy" and learned:
                continue
            if value not in allowed:
                problems.append(f"{flag} {value}: not one of {', '.join(map(str, allowed))}")
    if words[:2] == ("iwsim", "train") and getattr(ns, "train_command", None) in ("ae", "dynamics", "policy"):
        from iwsim.policies import PRESETS as POLICY_PRESETS
        from iwsim.world_model.presets import AE_PRESETS, DYNAMICS_PRESETS

        presets = {"ae": AE_PRESETS, "dynamics": DYNAMICS_PRESETS, "policy": POLICY_PRESETS}[ns.train_command]
        preset = ns.preset or getattr(ns, "policy", None)
        if preset not in presets:
            problems.append(f"--preset {preset}: not one of {', '.join(presets)}")
    variants = getattr(ns, "variant", None) or getattr(ns, "variants", None)
    if variants:
        from iwsim.core.errors import InputError
        from iwsim.world_model.presets import DYNAMICS_PRESETS, variant

        for name in variants.split(","):
            try:
                variant(DYNAMICS_PRESETS["tiny"], name)
            except InputError as e:
                problems.append(str(e))
    return problems


# -- paths ------------------------------------------------------------------------------------------


@functools.cache
def ignore_patterns() -> tuple[str, ...]:
    lines = (ROOT / ".gitignore").read_text().splitlines()
    return tuple(x.strip() for x in lines if x.strip() and not x.startswith("#"))


def committed(path: str) -> bool:
    """In the checkout and outside what .gitignore ignores (a local data/ or runs/ does not count)."""
    if not (ROOT / path).exists():
        return False
    parts = Path(path).parts
    for pattern in ignore_patterns():
        pat = pattern.strip("/").replace("**/", "*")
        anchored = "/" in pattern.rstrip("/")
        for i in range(1, len(parts) + 1):
            if fnmatch.fnmatch("/".join(parts[:i]) if anchored else parts[i - 1], pat):
                return False
    return True


def paths_in(value: object, pairs: bool) -> list[str]:
    """The paths a flag's value names (see the module docstring)."""
    if value is None or isinstance(value, bool | int | float):
        return []
    if isinstance(value, list | tuple):
        return [p for v in value for p in paths_in(v, pairs)]
    out = []
    for part in str(value).split(","):
        if "=" in part:
            part = part.split("=", 1)[1]
        if pairs:
            part = part.split("+")[0]  # NAME=RUN+reencode
        part = re.sub(r":\d+$", "", part)  # STORE:N
        part = part.split("*")[0].rstrip("/")  # a glob: the directory it lies in
        if ("/" not in part and not part.endswith(".zarr")) or "://" in part or part.startswith(("~", "/", "$")):
            continue
        if any(PLACEHOLDER.match(c) for c in part.split("/")):
            continue
        out.append(part)
    return out


def reads_and_writes(words: tuple[str, ...], ns: argparse.Namespace) -> tuple[list[str], list[str]]:
    reads: list[str] = []
    writes: list[str] = []
    for dest, value in vars(ns).items():
        if dest in READS and not getattr(ns, "dry_run", False):
            reads += paths_in(value, pairs=dest == "models")
        elif dest in WRITES:
            writes += paths_in(value, pairs=False)
    if words[:2] == ("iwsim", "collect"):
        reads += paths_in(ns.policy, pairs=False)  # a learned policy's run (a scripted name has no "/")
        if ns.out is None:
            writes.append(f"data/{ns.task or 'pusht'}_{ns.policy}.zarr")
    if words[:2] == ("iwsim", "bench") and ns.data is None and committed(ns.checkpoint):
        # without --data it reads the store the checkpoint was trained on
        config = json.loads((ROOT / ns.checkpoint / "config.json").read_text())
        reads += paths_in(config.get("provenance", {}).get("data"), pairs=False)
    return reads, writes


class Paths:
    """What the README has written so far, and whether a read finds it."""

    def __init__(self) -> None:
        self.written: list[str] = []

    def missing(self, path: str) -> bool:
        path = path.rstrip("/")
        return not (committed(path) or any(path == w or path.startswith(w + "/") for w in self.written))


# -- checking ---------------------------------------------------------------------------------------


def check_command(cmd: Command, paths: Paths) -> list[str]:
    words = cmd.words
    where = f"{cmd.source}:{cmd.line}: {' '.join(words)}"
    if words[0] == "make":
        return [f"{where}: no Makefile target {t!r}" for t in words[1:] if not t.startswith("-")
                and "=" not in t and t not in make_targets()]
    if words[0] in ("bash", "sh"):
        return [] if len(words) < 2 or (ROOT / words[1]).is_file() else [f"{where}: no file {words[1]}"]
    if words[0] == "python" and words[1:2] == ("-m",):
        module = words[2]
        if module != "iwsim.cli":
            return [] if _module_exists(module) else [f"{where}: no module {module}"]
        parser, args = iwsim_parser(), list(cmd.with_optional(placeholders=True))[3:]
    elif words[0] == "python":
        script = ROOT / words[1]
        if not script.is_file():
            return [f"{where}: no script {words[1]}"]
        parser, args = script_parser(script), list(cmd.with_optional(placeholders=True))[2:]
    elif words[0] == "iwsim":
        parser, args = iwsim_parser(), list(cmd.with_optional(placeholders=True))[1:]
    else:
        return []  # not a program of this repository
    ns = parse(parser, args)
    if isinstance(ns, str):  # what it would write still counts, or every reader below fails too
        paths.written += [b for a, b in zip(args, args[1:]) if a.lstrip("-").replace("-", "_") in WRITES]
        return [f"{where}: {ns}"]
    known = leaf(parser, args)._option_string_actions  # argparse takes abbreviations; the README spells flags out
    problems = [f"{where}: {t.split('=')[0]} is not a flag of its own (an abbreviation?)" for t in args
                if t.startswith("--") and t.split("=")[0] not in known]
    for group in cmd.commented:
        extended = parse(parser, args + list(group))
        if isinstance(extended, str):
            problems.append(f"{where} [{' '.join(group)}] (in its comment): {extended}")
    if cmd.alternatives:
        sub = leaf(parser, args)
        flags = [a for a in sub._actions if a.choices and not isinstance(a, argparse._SubParsersAction)
                 and getattr(ns, a.dest, None) in a.choices]
        if not flags:
            problems.append(f"{where}: its comment lists other values ({', '.join(cmd.alternatives)}) of no flag "
                            "with choices")
        for value in cmd.alternatives:
            if flags and not any(value in a.choices for a in flags):
                problems.append(f"{where}: the value {value!r} its comment offers is not one of "
                                f"{', '.join(flags[0].choices)}")
    problems += [f"{where}: {p}" for p in semantic_problems(words, ns)]
    reads, writes = reads_and_writes(words, ns)
    problems += [f"{where}: reads {p}, which is not committed and no earlier command writes" for p in reads
                 if paths.missing(p)]
    paths.written += writes
    return problems


def _module_exists(name: str) -> bool:
    try:
        return importlib.util.find_spec(name) is not None
    except ModuleNotFoundError:  # its package is missing
        return False


def _chain(node: ast.AST) -> list[str] | None:
    names = []
    while isinstance(node, ast.Attribute):
        names.append(node.attr)
        node = node.value
    if isinstance(node, ast.Name):
        return [node.id, *reversed(names)]
    return None


def check_snippet(snippet: Snippet, bound: dict[str, ModuleType | object], paths: Paths) -> list[str]:
    def where(node: ast.AST) -> str:
        return f"{snippet.source}:{snippet.line + getattr(node, 'lineno', 1) - 1}"

    try:
        tree = ast.parse(snippet.code)
        compile(tree, snippet.source, "exec")
    except SyntaxError as e:
        return [f"{snippet.source}:{snippet.line + (e.lineno or 1) - 1}: the Python snippet does not compile: {e.msg}"]
    problems = []
    for node in ast.walk(tree):  # imports first: they bind the names the chains below start from
        if isinstance(node, ast.Import):
            for alias in node.names:
                try:
                    module = importlib.import_module(alias.name)
                except ImportError as e:
                    problems.append(f"{where(node)}: import {alias.name}: {e}")
                    continue
                bound[alias.asname or alias.name.split(".")[0]] = (
                    module if alias.asname else importlib.import_module(alias.name.split(".")[0]))
        elif isinstance(node, ast.ImportFrom):
            try:
                module = importlib.import_module(node.module)
            except ImportError as e:
                problems.append(f"{where(node)}: from {node.module} import ...: {e}")
                continue
            for alias in node.names:
                if hasattr(module, alias.name):
                    bound[alias.asname or alias.name] = getattr(module, alias.name)
                elif hasattr(module, "__path__") and importlib.util.find_spec(f"{node.module}.{alias.name}"):
                    bound[alias.asname or alias.name] = importlib.import_module(f"{node.module}.{alias.name}")
                else:
                    problems.append(f"{where(node)}: {node.module} has no {alias.name}")
    assigned = {t.id for n in ast.walk(tree) if isinstance(n, ast.Assign) for t in ast.walk(n) if
                isinstance(t, ast.Name) and isinstance(t.ctx, ast.Store)}
    inner = {id(n.value) for n in ast.walk(tree) if isinstance(n, ast.Attribute)}
    for node in ast.walk(tree):
        if isinstance(node, ast.Attribute) and id(node) not in inner:
            chain = _chain(node)
            if not chain or chain[0] not in bound or chain[0] in assigned:
                continue
            obj = bound[chain[0]]
            for i, name in enumerate(chain[1:], 1):
                if not hasattr(obj, name):
                    problems.append(f"{where(node)}: {'.'.join(chain[:i])} has no attribute {name}")
                    break
                obj = getattr(obj, name)
        if isinstance(node, ast.Call) and _chain(node.func) == ["gym", "make"] and "gym" in bound and node.args \
                and isinstance(node.args[0], ast.Constant):
            import gymnasium

            import iwsim  # noqa: F401  (registers the ids)

            if node.args[0].value not in gymnasium.registry:
                problems.append(f"{where(node)}: gym.make({node.args[0].value!r}): no such environment id")
        if isinstance(node, ast.Constant) and isinstance(node.value, str) and node.value.startswith(SNIPPET_PATHS):
            if paths.missing(node.value):
                problems.append(f"{where(node)}: reads {node.value}, which is not committed and no earlier "
                                "command writes")
    return problems


@functools.cache
def readme_problems() -> tuple[str, ...]:
    paths, bound, problems = Paths(), {}, []
    for item in documentation_items(ROOT):
        if isinstance(item, Command):
            problems += check_command(item, paths)
        else:
            problems += check_snippet(item, bound, paths)
    return tuple(problems)


def test_readme_commands_and_snippets():
    problems = readme_problems()
    assert not problems, "\n" + "\n".join(problems)


def prose_spans(text: str) -> list[tuple[int, str]]:
    """The inline code spans outside fenced blocks, with the README line each starts on."""
    lines, fenced = [], False
    for line in text.splitlines():
        m = FENCE.match(line)
        if m and (not fenced or not m.group(2)):  # an opening fence, or a closing one
            fenced = not fenced
            lines.append("")
        else:
            lines.append("" if fenced else line)
    prose = "\n".join(lines)
    return [(prose.count("\n", 0, m.start()) + 1, m.group(1)) for m in re.finditer(r"`([^`]+)`", prose)]


def resolves(dotted: str) -> bool:
    parts = dotted.split(".")
    for i in range(len(parts), 0, -1):
        if _module_exists(".".join(parts[:i])):
            obj = importlib.import_module(".".join(parts[:i]))
            break
    else:
        return False
    for name in parts[i:]:
        if not hasattr(obj, name):
            return False
        obj = getattr(obj, name)
    return True


def flag_problems(parser: argparse.ArgumentParser, name: str, tokens: list[str], where: str) -> list[str]:
    """Subcommand words that are not ones, and flags not spelled as the (sub)parser has them."""
    problems, current = [], parser
    for token in tokens:
        subs = [a for a in current._actions if isinstance(a, argparse._SubParsersAction)]
        if token.startswith("-") or not subs or token in ("...", "|") or PLACEHOLDER.match(token):
            break
        if token not in subs[0].choices:
            problems.append(f"{where}: {name} has no subcommand {token!r}")
            break
        current, name = subs[0].choices[token], f"{name} {token}"
    known = current._option_string_actions
    return problems + [f"{where}: {t.split('=')[0]} is not a flag of {name}" for t in tokens
                       if t.startswith("--") and t.split("=")[0] not in known]


def prose_problems(text: str, source: str = "README.md") -> list[str]:
    """What the prose of ``text`` (the file ``source``, relative to the repository) names
    that does not exist; its relative links are relative to its folder."""
    problems = []
    for line, span in prose_spans(text):
        where = f"{source}:{line}: `{' '.join(span.split())}`"
        m = re.search(r"(?:^|\s|/)iwsim(?:\.cli)?\s+(.*)$", span, re.S)
        if m:
            problems += flag_problems(iwsim_parser(), "iwsim", m.group(1).split(), where)
        m = re.fullmatch(r"\s*make ([\w-]+)\s*", span)
        if m and m.group(1) not in make_targets():
            problems.append(f"{where}: no Makefile target {m.group(1)!r}")
        m = re.match(r"\s*((?:bench|scripts)/\w+\.py)\s+(.*)$", span, re.S)
        if m and (ROOT / m.group(1)).is_file() and "--" in m.group(2):
            problems += flag_problems(script_parser(ROOT / m.group(1)), m.group(1), m.group(2).split(), where)
        for dotted in re.findall(r"(?<![\w./])iwsim(?:\.\w+)+", span):
            if not resolves(dotted):
                problems.append(f"{where}: {dotted} does not exist")
        for path in re.findall(r"(?<![\w./<~-])((?:src|bench|scripts|tests|checkpoints|iwsim)/[\w./-]*\w/?)", span):
            if re.match(r"iwsim/[A-Z]", path):  # an environment id
                continue
            if not committed("src/" + path if path.startswith("iwsim/") else path):
                problems.append(f"{where}: no {path} in the repository")
    for m in re.finditer(r"\]\(([^)\s#]+)[^)]*\)", text):
        if "://" in m.group(1):
            continue
        target = os.path.normpath(Path(source).parent / m.group(1))
        if target.startswith("..") or not committed(target):
            problems.append(f"{source}:{text.count(chr(10), 0, m.start()) + 1}: the link to {m.group(1)} is broken")
    return problems


@pytest.mark.parametrize("doc", DOCUMENTS)
def test_documentation_prose_names_what_exists(doc):
    problems = prose_problems((ROOT / doc).read_text(), doc)
    assert not problems, "\n" + "\n".join(problems)


def test_the_readme_is_a_few_screens_and_links_every_page():
    """The README says what iwsim is and links the pages that say the rest; a page of docs/
    that the README does not link (or DOCUMENTS does not list) is read by nobody."""
    text = README.read_text()
    assert len(text.splitlines()) <= 300
    pages = sorted(p.relative_to(ROOT).as_posix() for p in (ROOT / "docs").glob("*.md"))
    assert sorted(DOCUMENTS[1:]) == pages
    assert [p for p in pages if f"]({p}" not in text] == []


def test_readme_has_what_the_checks_look_for():
    """A parser that found nothing would pass everything."""
    items = documentation_items(ROOT)
    words = [i.words for i in items if isinstance(i, Command)]
    assert sum(w[0] == "iwsim" for w in words) > 20 and ("make", "demo") in words
    assert any(w[:2] == ("python", "bench/yardstick.py") for w in words)
    assert sum(isinstance(i, Snippet) for i in items) >= 5


# -- the checks themselves, on a README of our own ---------------------------------------------------


TOY = """\
Text.

```bash
MUJOCO_GL=egl .venv/bin/iwsim collect --policy play --episodes 2 \\
    --out data/a.zarr   # a comment
.venv/bin/iwsim data info data/a.zarr && make lint
taskset -c 0 .venv/bin/iwsim train ae --data data/b.zarr --out runs/ae &   # reads a store nobody wrote
.venv/bin/iwsim data export --format lerobot-v3 --in data/a.zarr --out outputs/x   # or lerobot-v2.1, nope
.venv/bin/iwsim experiment datagen --jobs 1   # [--world-model checkpoints/pusht-64]
#   [--train-steps N] [--no-such-flag 1]
.venv/bin/python bench/wm_studies_check.py --models a=runs/ae [b=runs/b] [NAME=CHECKPOINT ...]
make no-such-target
.venv/bin/iwsim collect --episodes two --out data/c.zarr
.venv/bin/iwsim collect --episode 2 --out data/d.zarr
```

- a list item:

  ```python
  import iwsim
  wm = iwsim.WorldModel.load("runs/ae")
  iwsim.NoSuchThing
  ```

```python
def broken(:
```

Prose: `iwsim data exprt`, `iwsim train dynamics --inti X`, `make nope`, `iwsim.nope`, `make demo`,
`src/iwsim/nope.py`, `bench/bench_ae.py --rn runs/ae`, [a link](nope.md) and `iwsim export-model
--run runs/a --out runs/b`.
"""


def toy_problems(tmp_path: Path) -> list[str]:
    readme = tmp_path / "README.md"
    readme.write_text(TOY)
    paths, bound, problems = Paths(), {}, []
    for item in readme_items(readme):
        problems += check_command(item, paths) if isinstance(item, Command) else check_snippet(item, bound, paths)
    return problems


def test_shell_parsing_of_a_toy_readme(tmp_path):
    (tmp_path / "README.md").write_text(TOY)
    cmds = [i for i in readme_items(tmp_path / "README.md") if isinstance(i, Command)]
    first = cmds[0]
    assert first.line == 4 and first.env == (("MUJOCO_GL", "egl"),) and first.words[:2] == ("iwsim", "collect")
    assert first.argv[-2:] == ("--out", "data/a.zarr")
    assert [c.words[0] for c in cmds[1:3]] == ["iwsim", "make"] and cmds[1].line == cmds[2].line == 6
    assert cmds[3].wrapper == ("taskset", "-c", "0") and cmds[3].background
    assert cmds[4].alternatives == ("lerobot-v2.1", "nope")
    assert cmds[5].commented == (("--world-model", "checkpoints/pusht-64"), ("--train-steps", "N"),
                                 ("--no-such-flag", "1"))
    assert cmds[6].with_optional() == (".venv/bin/python", "bench/wm_studies_check.py", "--models", "a=runs/ae",
                                       "b=runs/b")


def test_a_toy_readme_fails_where_it_should(tmp_path):
    problems = toy_problems(tmp_path)
    text = "\n".join(problems)
    expected = {
        7: "reads data/b.zarr",
        8: "'nope'",
        9: "unrecognized arguments: --no-such-flag",
        11: "reads runs/b",
        12: "no Makefile target 'no-such-target'",
        13: "invalid int value: 'two'",
        14: "--episode is not a flag of its own",
        22: "iwsim has no attribute NoSuchThing",
        26: "does not compile",
    }
    for line, what in expected.items():
        assert any(p.startswith(f"README.md:{line}:") and what in p for p in problems), (line, what, text)
    assert len(problems) == len(expected), text  # runs/ae is written by line 7, --train-steps N parses


def test_prose_of_a_toy_readme():
    problems = prose_problems(TOY)
    text = "\n".join(problems)
    for what in ("no subcommand 'exprt'", "--inti is not a flag of iwsim train dynamics", "target 'nope'",
                 "iwsim.nope does not exist", "no src/iwsim/nope.py", "--rn is not a flag of bench/bench_ae.py",
                 "link to nope.md"):
        assert any(p.startswith(("README.md:29:", "README.md:30:")) and what in p for p in problems), (what, text)
    assert len(problems) == 7, text


@pytest.mark.parametrize("path, expected", [("checkpoints/pusht-64", True), ("runs/anything", False),
                                            ("data/pusht_play.zarr", False), ("bench/no_such_file.py", False)])
def test_committed(path, expected):
    assert committed(path) is expected
