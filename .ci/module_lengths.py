"""Fail when a module of the package is longer than 600 lines: print each one with its length.

    python .ci/module_lengths.py [FOLDER]   (default: python/usdeform)
"""

import sys
from pathlib import Path

MAX_LINES = 600


def long_modules(folder: Path) -> list[tuple[Path, int]]:
    """The modules under ``folder`` with more than :data:`MAX_LINES` lines, with their lengths."""
    lengths = ((path, len(path.read_text(encoding="utf-8").splitlines())) for path in sorted(folder.rglob("*.py")))
    return [(path, n) for path, n in lengths if n > MAX_LINES]


if __name__ == "__main__":
    found = long_modules(Path(sys.argv[1] if len(sys.argv) > 1 else "python/usdeform"))
    for path, n in found:
        print(f"{path}: {n} lines (at most {MAX_LINES})")
    sys.exit(1 if found else 0)
