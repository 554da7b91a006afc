"""A script of ``bench/`` or ``scripts/`` as a module, for the tests that call its ``main``
or read the parser it builds: loaded from its file under a name of its own (not
``__main__``, so it does not run), with nothing added to ``sys.path`` (scripts import only
the package)."""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path
from types import ModuleType


def load_script(path: Path, prefix: str = "_script") -> ModuleType:
    """The script at ``path`` as the module ``<prefix>_<its stem>`` (registered in
    ``sys.modules``: its dataclasses look their module up)."""
    spec = importlib.util.spec_from_file_location(f"{prefix}_{path.stem}", path)
    if spec is None or spec.loader is None:
        raise ImportError(f"{path} is not a Python file")
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module
    spec.loader.exec_module(module)
    return module
