"""The layers run one way: every module of ``src/iwsim`` imports (at module or function
level) only from its own layer or those below (``iwsim.core.layers.LAYERS``), and no imports
form a cycle. A task's modules are imported only by ``envs/`` and the Task registry (and
the ground-truth tooling, named in ``iwsim.core.layers.GROUND_TRUTH_TOOLING``)."""

from __future__ import annotations

import ast
import subprocess
import sys
from pathlib import Path

import pytest

from iwsim.core.layers import (
    GROUND_TRUTH_TOOLING,
    LAYERS,
    T_PUSH_DEFAULTS_SPELLED,
    TASK_IMPORTERS,
    TASK_MODULES,
    layer_of,
    within,
)

SRC = Path(__file__).resolve().parents[1] / "src"
ROOT = "iwsim"  # the package's __init__, outside the layers


def module_name(path: Path) -> str:
    parts = list(path.relative_to(SRC).with_suffix("").parts)
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


MODULES = {module_name(p): p for p in sorted((SRC / ROOT).rglob("*.py"))}


def imports(name: str) -> set[str]:
    """The iwsim modules ``name`` imports anywhere in its file (``from a import b`` counts
    as ``a.b`` when that is a module, else as ``a``)."""
    path = MODULES[name]
    package = name if path.name == "__init__.py" else name.rpartition(".")[0]
    found = set()
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            found.update(a.name for a in node.names)
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                up = package.split(".")[: len(package.split(".")) - node.level + 1]
                base = ".".join(up + ([base] if base else []))
            found.update(f"{base}.{a.name}" if f"{base}.{a.name}" in MODULES else base for a in node.names)
    return {m for m in found if m in MODULES and m != ROOT and m != name}


GRAPH = {name: imports(name) for name in MODULES if name != ROOT}


def test_every_module_has_a_layer():
    assert [name for name in GRAPH if layer_of(name) is None] == []


def test_no_module_imports_from_a_higher_layer():
    upward = [f"{name} (layer {layer_of(name) + 1}) imports {dep} (layer {layer_of(dep) + 1})"
              for name, deps in sorted(GRAPH.items()) for dep in sorted(deps)
              if layer_of(name) is not None and layer_of(dep) is not None and layer_of(dep) > layer_of(name)]
    assert upward == []


def test_imports_have_no_cycle():
    state: dict[str, int] = {}  # 1: on the current path, 2: done
    cycles = []

    def visit(name: str, path: list[str]) -> None:
        state[name] = 1
        for dep in sorted(GRAPH[name]):
            if state.get(dep) == 1:
                cycles.append(" -> ".join([*path[path.index(dep):], dep]))
            elif dep not in state:
                visit(dep, [*path, dep])
        state[name] = 2

    for name in sorted(GRAPH):
        if name not in state:
            visit(name, [name])
    assert cycles == []


def test_only_envs_and_the_task_registry_import_a_task_module():
    """The world model's callers (WorldModel-v0, play, evaluation, the studies, the CLI)
    reach a task only through the Task seam."""
    found = [f"{name} imports {dep}" for name, deps in sorted(GRAPH.items()) for dep in sorted(deps)
             if within(dep, TASK_MODULES) and not within(name, TASK_IMPORTERS) and name not in GROUND_TRUTH_TOOLING]
    assert found == []


def test_the_ground_truth_tooling_list_only_names_modules_that_need_it():
    """A module that stops importing a task module leaves the list (so it can only shrink)."""
    assert [m for m in GROUND_TRUTH_TOOLING if not any(within(d, TASK_MODULES) for d in GRAPH[m])] == []


def test_scripted_policies_and_the_studies_reach_a_task_through_the_seam():
    """Issue 45: evaluation, the studies and the scripted policies behind the policy interface
    make a task's scripted policies, simulator and scores through the Task
    (``Task.pixel_policy``, ``Task.ground_truth_env``, ``Task.score``), so that they run on
    any task with a ground truth: the scripted policies import only what every tabletop task
    shares (their degradations), and evaluation and the studies no task module at all."""
    shared = ("iwsim.envs.tabletop.scripting",)
    assert [d for d in GRAPH["iwsim.policies.scripted"] if within(d, TASK_MODULES) and d not in shared] == []
    seam_users = [m for m in GRAPH if within(m, ("iwsim.experiments", "iwsim.eval.policy"))]
    assert "iwsim.experiments.demos" in seam_users
    assert [f"{m} imports {d}" for m in seam_users for d in sorted(GRAPH[m]) if within(d, TASK_MODULES)] == []


def test_the_store_layer_does_not_reach_the_tasks():
    """Issue 43: data/ imported the task registry through collection; collection is the
    tasks' own tool now (envs/), and data/ sits below every task."""
    assert layer_of("iwsim.data") < layer_of("iwsim.envs.registry") == layer_of("iwsim.envs.collect")
    assert [f"{m} imports {d}" for m in GRAPH if within(m, ("iwsim.data",))
            for d in GRAPH[m] if within(d, ("iwsim.envs",))] == []


def test_the_package_root_reaches_up_only_for_the_lazy_world_model():
    """``import iwsim`` registers the Gymnasium ids by name (importing no task);
    ``iwsim.WorldModel`` (public) is the one upward import, inside a function so that
    ``import iwsim`` does not import torch."""
    tree = ast.parse(MODULES[ROOT].read_text())
    top = {a.name if isinstance(n, ast.Import) else n.module for stmt in tree.body
           if not isinstance(stmt, ast.FunctionDef) for n in ast.walk(stmt)
           if isinstance(n, (ast.Import, ast.ImportFrom)) for a in n.names}
    lazy = {n.module for stmt in tree.body if isinstance(stmt, ast.FunctionDef) for n in ast.walk(stmt)
            if isinstance(n, ast.ImportFrom)}
    assert top == {"gymnasium.envs.registration"} and lazy == {"iwsim.world_model"}
    code = ("import sys, iwsim, gymnasium; assert 'torch' not in sys.modules; "
            "assert {'iwsim/BimanualPushT-v0', 'iwsim/PileSweep-v0', 'iwsim/WorldModel-v0'} <= "
            "set(gymnasium.registry); "
            "assert iwsim.WorldModel.load and 'torch' in sys.modules")
    subprocess.run([sys.executable, "-c", code], check=True)


SHIPPED_CHECKPOINT = "checkpoints/pusht-64"


def spells_t_push_defaults(name: str) -> bool:
    """Whether ``name`` holds the shipped checkpoint's path outside a docstring, or calls
    ``get_task("pusht")`` at module level."""
    tree = ast.parse(MODULES[name].read_text())
    docstrings = {id(n.body[0].value) for n in ast.walk(tree)
                  if isinstance(n, (ast.Module, ast.ClassDef, ast.FunctionDef, ast.AsyncFunctionDef)) and n.body
                  and isinstance(n.body[0], ast.Expr) and isinstance(n.body[0].value, ast.Constant)}
    if any(isinstance(n, ast.Constant) and isinstance(n.value, str) and SHIPPED_CHECKPOINT in n.value
           and id(n) not in docstrings for n in ast.walk(tree)):
        return True
    top = [n for stmt in tree.body if not isinstance(stmt, (ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef))
           for n in ast.walk(stmt)]
    return any(isinstance(n, ast.Call) and getattr(n.func, "id", getattr(n.func, "attr", None)) == "get_task"
               and n.args and isinstance(n.args[0], ast.Constant) and n.args[0].value == "pusht" for n in top)


def test_the_t_push_defaults_have_one_home():
    """Issue 43: the shipped checkpoint and the module-level T-push task are spelled only by
    T-push's own modules and the task registry (the list of the others only shrinks)."""
    spelled = {name for name in MODULES if spells_t_push_defaults(name)}
    home = ("iwsim.envs.registry", *TASK_MODULES)
    assert sorted(m for m in spelled if not within(m, home) and m not in T_PUSH_DEFAULTS_SPELLED) == []
    assert sorted(m for m in T_PUSH_DEFAULTS_SPELLED if m not in spelled) == []


FRAME_SIZES = ("image_size", "frame_size", "size", "resolution")  # names of a frame's size in pixels


def t_push_literals(source: str) -> list[int]:
    """The lines of ``source`` that default a frame size to T-push's 64 pixels or a task to
    "pusht": a parameter's or a class field's default, a fallback (``getattr(p, "image_size",
    64)``, ``c.get("image_size", 64)``, ``c.get("image_size") or 64``) or an argparse ``default=``."""

    def constant(node: ast.AST | None, value: object) -> bool:
        return isinstance(node, ast.Constant) and type(node.value) is type(value) and node.value == value

    def t_push(name: object, default: ast.AST | None) -> bool:  # ``name`` (a str, or None) defaults to ``default``
        frame_size = str(name).lstrip("-").replace("-", "_") in FRAME_SIZES
        return constant(default, "pusht") or (frame_size and constant(default, 64))

    def value(node: ast.AST) -> object:
        return getattr(node, "value", None)

    lines = set()
    for node in ast.walk(ast.parse(source)):
        pairs: list[tuple[object, ast.AST | None]] = []  # (name, its default)
        if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef, ast.Lambda)):
            a = node.args
            positional = [*a.posonlyargs, *a.args]
            pairs += zip([p.arg for p in positional[len(positional) - len(a.defaults):]], a.defaults)
            pairs += zip([p.arg for p in a.kwonlyargs], a.kw_defaults)
        elif isinstance(node, ast.ClassDef):  # a dataclass's fields
            pairs += [(getattr(t, "id", None), s.value) for s in node.body if isinstance(s, (ast.Assign, ast.AnnAssign))
                      for t in (s.targets if isinstance(s, ast.Assign) else [s.target])]
        elif isinstance(node, ast.Call):
            if getattr(node.func, "id", getattr(node.func, "attr", None)) in ("getattr", "get") and len(node.args) > 1:
                pairs.append((value(node.args[-2]), node.args[-1]))
            pairs += [(value(x), kw.value) for kw in node.keywords if kw.arg == "default" for x in node.args]
        elif isinstance(node, ast.BoolOp) and isinstance(node.values[0], ast.Call):  # c.get(key) or default
            pairs += [(value(x), node.values[-1]) for x in node.values[0].args]
        lines.update(default.lineno for name, default in pairs if default is not None and t_push(name, default))
    return sorted(lines)


def test_t_push_literals_finds_each_form():
    forms = ["def f(image_size: int = 64): ...", "def f(*, task='pusht'): ...", "class C:\n    image_size: int = 64",
             "getattr(p, 'image_size', 64)", "c.get('image_size', 64)", "c.get('image_size') or 64",
             "p.add_argument('--image-size', type=int, default=64)", "p.add_argument('--task', default='pusht')"]
    assert [s for s in forms if not t_push_literals(s)] == []
    assert t_push_literals("def f(image_size: int | None = None, batch: int = 64, name='pusht-64'): ...\n"
                           "p.add_argument('--batch', default=64)\nc.get('steps', 64)") == []


def test_no_frame_size_or_task_defaults_to_t_push_outside_its_homes():
    """Issue 43: generic modules take a frame size from the task (``image_size=None``: the
    task's own) or ``iwsim.envs.registry.DEFAULT_TASK``, never T-push's 64 pixels or "pusht"; only
    T-push's modules, the task registry and the presets (``config.py``, ``presets.py``) spell them."""
    home = ("iwsim.envs.registry", *TASK_MODULES)
    found = {name: lines for name in MODULES if not within(name, home) and name.rpartition(".")[2] not in
             ("config", "presets") and (lines := t_push_literals(MODULES[name].read_text()))}
    assert found == {}


@pytest.mark.parametrize("module, layer", [("iwsim.core.checkpoint", 0), ("iwsim.models.blocks", 0),
                                           ("iwsim.data.store", 1), ("iwsim.envs.pusht.scripted", 2),
                                           ("iwsim.envs.registry", 2), ("iwsim.envs.collect", 2),
                                           ("iwsim.world_model", 3), ("iwsim.world_model.env", 3),
                                           ("iwsim.policies.train", 3), ("iwsim.eval.demo", 4),
                                           ("iwsim.cli", len(LAYERS) - 1), ("iwsim.commands.train", len(LAYERS) - 1)])
def test_layer_of(module, layer):
    assert layer_of(module) == layer


def test_functions_and_the_command_line_stay_short():
    """A function of more than 120 lines, or a ``cli.py`` of more than 150, is read by
    nobody: the command line's groups live in ``iwsim.commands``, one module each."""
    import ast

    long = []
    for name, path in MODULES.items():
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)) and node.end_lineno - node.lineno >= 120:
                long.append(f"{name}.{node.name}: {node.end_lineno - node.lineno + 1} lines")
    assert long == []
    assert len(MODULES["iwsim.cli"].read_text().splitlines()) <= 150
