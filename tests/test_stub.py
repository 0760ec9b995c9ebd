"""The shipped type stub matches the compiled module, and the package ships its typing markers."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import usdeform


def test_stub_matches_the_compiled_module() -> None:
    result = subprocess.run(
        [sys.executable, "-m", "mypy.stubtest", "usdeform._core"], capture_output=True, text=True, timeout=300
    )
    assert result.returncode == 0, result.stdout + result.stderr


def test_package_ships_py_typed_and_the_stub() -> None:
    package = Path(usdeform.__file__).parent
    assert (package / "py.typed").is_file()
    assert (package / "_core.pyi").is_file()
