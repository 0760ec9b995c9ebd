"""A module of the package as it is at another git revision, for benchmarks that compare with it."""

from __future__ import annotations

import importlib.util
import subprocess
import sys
import tempfile
from pathlib import Path
from types import ModuleType

ROOT = Path(__file__).resolve().parents[1]


def _git(*arguments: str) -> str:
    return subprocess.run(["git", "-C", str(ROOT), *arguments], check=True, capture_output=True, text=True).stdout


def landed_module(revision: str, name: str) -> ModuleType:
    """``python/usdeform/<name>.py`` (or the package ``python/usdeform/<name>/``) at ``revision`` of this
    repository, imported as a module of the installed package (its relative imports resolve to this
    tree's modules; a package's own submodules to its files at ``revision``)."""
    folder = f"python/usdeform/{name}"
    files = _git("ls-tree", "-r", "--name-only", revision, f"{folder}/").split()
    module_name = f"usdeform._landed_{name}"
    if files:  # a package: its files written out, imported from there
        location = Path(tempfile.mkdtemp(prefix=f"landed_{name}_"))
        for file in files:
            (location / Path(file).relative_to(folder)).parent.mkdir(parents=True, exist_ok=True)
            (location / Path(file).relative_to(folder)).write_text(_git("show", f"{revision}:{file}"))
        spec = importlib.util.spec_from_file_location(
            module_name, location / "__init__.py", submodule_search_locations=[str(location)]
        )
        assert spec is not None and spec.loader is not None
        module = importlib.util.module_from_spec(spec)
        sys.modules[module_name] = module
        spec.loader.exec_module(module)
        return module
    source = _git("show", f"{revision}:{folder}.py")
    spec = importlib.util.spec_from_loader(module_name, loader=None)
    assert spec is not None
    module = importlib.util.module_from_spec(spec)
    module.__package__ = "usdeform"
    sys.modules[spec.name] = module  # dataclasses look their module up
    exec(compile(source, f"{revision}:{name}.py", "exec"), module.__dict__)
    return module
