"""A module of the package as it is at another git revision, for benchmarks that compare with it."""

from __future__ import annotations

import importlib.util
import subprocess
import sys
from pathlib import Path
from types import ModuleType


def landed_module(revision: str, name: str) -> ModuleType:
    """``python/usdeform/<name>.py`` at ``revision`` of this repository, imported as a module of the
    installed package (its relative imports resolve to this tree's modules)."""
    root = Path(__file__).resolve().parents[1]
    source = subprocess.run(
        ["git", "-C", str(root), "show", f"{revision}:python/usdeform/{name}.py"],
        check=True,
        capture_output=True,
        text=True,
    ).stdout
    spec = importlib.util.spec_from_loader(f"usdeform._landed_{name}", loader=None)
    assert spec is not None
    module = importlib.util.module_from_spec(spec)
    module.__package__ = "usdeform"
    sys.modules[spec.name] = module  # dataclasses look their module up
    exec(compile(source, f"{revision}:{name}.py", "exec"), module.__dict__)
    return module
