"""Every tracked text file under bench/results/ carries the command that produced it at its
top (bench/README.md): a JSON record's first key ``"command"``, a Markdown report's command
within its first lines; and the helpers the writers build them with."""

from __future__ import annotations

import argparse
import itertools
import json
import re
import shlex
import shutil
import subprocess
from pathlib import Path

import pytest

from iwsim.cli import build_parser
from iwsim.eval.records import command_line, with_command

ROOT = Path(__file__).resolve().parents[1]
HEAD_LINES = 8  # a Markdown report's command is within its first lines

# Files without their command at their top, each with the reason. Keep this short: a file
# regenerated with its command (or removed) leaves the list (test_exempt_files_are_still_exempt).
EXEMPT = {
    # notebooks written by hand: no command writes them; each row or section names its own
    "bench/results/ablations.md": "notebook; ablate_dynamics.py eval --table appends dated sections",
    "bench/results/experiments/dp_runs.md": "notebook of the 2026-11-23/24 Diffusion Policy session",
    "bench/results/policies/runs.md": "notebook of the issue-25 campaign, a bench/policy_runs.py run per row",
    # copies of a run's output under another name, of models or code since replaced
    "bench/results/ablations/results_300.json": "ablate_dynamics.py eval --out outputs/eval_ablate (ablations.md, "
                                                "2026-11-23 16:05), renamed; variants of the 2026-11-23 code",
}


def tracked_results() -> list[str]:
    """The tracked text files under bench/results/ (pictures aside)."""
    if shutil.which("git") is None:
        pytest.skip("git is not installed")
    run = subprocess.run(["git", "ls-files", "bench/results"], cwd=ROOT, capture_output=True, text=True)
    if run.returncode != 0 or not run.stdout.strip():
        pytest.skip("not a git checkout")
    return [p for p in run.stdout.split() if p.endswith((".json", ".md"))]


def _iwsim_command(words: list[str]) -> bool:
    """Whether ``words`` (after ``iwsim``) start with a subcommand, down to a leaf of the CLI."""
    parser = build_parser()
    for word in words:
        subs = [a for a in parser._actions if isinstance(a, argparse._SubParsersAction)]
        if not subs:
            return True
        if word not in subs[0].choices:
            return False
        parser = subs[0].choices[word]
    return not any(isinstance(a, argparse._SubParsersAction) for a in parser._actions)


def names_a_command(text: str) -> bool:
    """Whether ``text`` is a command line (or several joined by ``&&``) each of which runs
    an existing ``bench/*.py`` (or ``scripts/*.py``) script with python, or an ``iwsim``
    subcommand; leading ``NAME=value`` environment words aside."""
    try:
        words = shlex.split(text)
    except ValueError:
        return False
    parts = [list(g) for sep, g in itertools.groupby(words, lambda w: w == "&&") if not sep]
    if not parts:
        return False
    for part in parts:
        prog = list(itertools.dropwhile(lambda w: re.fullmatch(r"[A-Za-z_]\w*=\S*", w), part))
        script = len(prog) >= 2 and re.fullmatch(r"(?:bench|scripts)/[\w/]+\.py", prog[1])
        if script and Path(prog[0]).name.startswith("python"):
            if not (ROOT / prog[1]).is_file():
                return False
        elif not (prog and Path(prog[0]).name == "iwsim" and _iwsim_command(prog[1:])):
            return False
    return True


def markdown_commands(text: str) -> list[str]:
    """The candidate commands in a report's first lines: inline code, and the lines of code
    blocks (fenced or indented); headings aside."""
    found, fenced = [], False
    for line in text.splitlines()[:HEAD_LINES]:
        if line.startswith("```"):
            fenced = not fenced
        elif fenced or line.startswith("    "):
            found.append(line.strip())
        elif not line.startswith("#"):
            found += re.findall(r"(?<!`)`([^`]+)`(?!`)", line)
    return found


def command_at_top(path: str) -> bool:
    text = (ROOT / path).read_text()
    if path.endswith(".json"):
        record = json.loads(text)
        first = next(iter(record), None) if isinstance(record, dict) else None
        return first == "command" and isinstance(record["command"], str) and names_a_command(record["command"])
    return any(names_a_command(c) for c in markdown_commands(text))


def test_every_tracked_result_names_its_command_at_its_top():
    missing = [p for p in tracked_results() if p not in EXEMPT and not command_at_top(p)]
    assert not missing, f"no command at the top of {missing} (bench/README.md; or an entry in EXEMPT, with why)"


def test_exempt_files_are_still_exempt():
    tracked = set(tracked_results())
    gone = [p for p in EXEMPT if p not in tracked]
    fixed = [p for p in EXEMPT if p in tracked and command_at_top(p)]
    assert not gone and not fixed, f"drop from EXEMPT: {gone + fixed}"


def test_names_a_command_knows_scripts_and_subcommands():
    assert names_a_command("python bench/yardstick.py --models a=b")
    assert names_a_command("MUJOCO_GL=egl .venv/bin/python bench/bench_play.py --browser 10,20,25")
    assert names_a_command("iwsim experiment datagen --preset act && python bench/bench_task.py")
    assert names_a_command("OMP_NUM_THREADS=1 .venv/bin/iwsim bench --checkpoint c --out o")
    assert not names_a_command("python bench/no_such_script.py")
    assert names_a_command("python scripts/ship_checkpoint.py --checkpoint c")
    assert not names_a_command("python bench/ship_checkpoint.py --checkpoint c")  # moved to scripts/
    assert not names_a_command("iwsim no-such-command --out o")
    assert not names_a_command("iwsim experiment")  # not a leaf: which study?
    assert not names_a_command("bench/yardstick.py")  # a title's mention is not a command
    assert not names_a_command("python bench/yardstick.py && ls")
    assert markdown_commands("# Title (`iwsim bench`)\n\n`iwsim bench --out x`\n") == ["iwsim bench --out x"]
    assert markdown_commands("# T\n\n```\niwsim data info d\n```\n\n    python bench/rest_stats.py\n") == [
        "iwsim data info d", "python bench/rest_stats.py"]


def test_command_line_is_relative_to_the_project_and_shell_quoted(monkeypatch, tmp_path):
    monkeypatch.chdir(tmp_path)  # not the project: the script's path is still bench/NAME.py
    script = str(ROOT / "bench" / "yardstick.py")
    assert command_line(script, ["--models", "a=b c", "--out", "x"]) == (
        "python bench/yardstick.py --models 'a=b c' --out x")
    assert command_line("iwsim", ["bench", "--out", "bench/results/x"]) == "iwsim bench --out bench/results/x"
    monkeypatch.setattr("sys.argv", [script, "--parts", "idle"])
    assert command_line(script) == "python bench/yardstick.py --parts idle"
    outside = tmp_path / "probe.py"
    assert command_line(str(outside), []) == "python probe.py"  # relative to the working directory


def test_with_command_puts_it_first_and_can_sort_the_rest():
    record = {"z": 1, "command": "old", "a": {"y": 2, "b": 3}}
    assert list(with_command("new", record)) == ["command", "z", "a"]
    sorted_ = with_command("new", record, sort_keys=True)
    assert list(sorted_) == ["command", "a", "z"] and list(sorted_["a"]) == ["b", "y"]
    assert json.dumps(sorted_).startswith('{"command": "new"')
    assert record["command"] == "old"  # the record itself is left as it was
