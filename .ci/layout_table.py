"""The layout table of docs/development.md, generated from the tree: one row per package and root module of
python/usdeform and per Rust source file, each with the first line of its docstring (``//!`` in Rust).

    python .ci/layout_table.py            print the table
    python .ci/layout_table.py --write    replace the table in docs/development.md (between its markers)
    python .ci/layout_table.py --check    exit 1 when docs/development.md's table differs from the tree's
"""

import ast
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
DOC = ROOT / "docs" / "development.md"
BEGIN, END = "<!-- layout: begin (python .ci/layout_table.py --write) -->", "<!-- layout: end -->"


def _python_line(path: Path) -> str:
    docstring = ast.get_docstring(ast.parse(path.read_text(encoding="utf-8"))) or ""
    return docstring.strip().split("\n")[0].strip()


def _rust_line(path: Path) -> str:
    for line in path.read_text(encoding="utf-8").splitlines():
        if line.startswith("//!"):
            return line[3:].strip()
    return ""


def rows() -> list[tuple[str, str]]:
    """``(path, first docstring line)`` of every package and root module of the package, then every Rust file."""
    package = ROOT / "python" / "usdeform"
    found = []
    for entry in sorted(package.iterdir()):
        if entry.is_dir() and (entry / "__init__.py").exists():
            found.append((f"python/usdeform/{entry.name}/", _python_line(entry / "__init__.py")))
        elif entry.suffix == ".py":
            found.append((f"python/usdeform/{entry.name}", _python_line(entry)))
    for crate in ("core", "python"):
        for path in sorted((ROOT / "rust" / crate / "src").glob("*.rs")):
            found.append((f"rust/{crate}/src/{path.name}", _rust_line(path)))
    return found


def table() -> str:
    lines = ["| path | what |", "|---|---|"]
    lines += [f"| `{path}` | {what.replace('|', '/')} |" for path, what in rows()]
    return "\n".join(lines)


def with_table(text: str) -> str:
    """``text`` (docs/development.md) with the table between its markers replaced by :func:`table`."""
    start, stop = text.index(BEGIN) + len(BEGIN), text.index(END)
    return text[:start] + "\n" + table() + "\n" + text[stop:]


if __name__ == "__main__":
    current = DOC.read_text(encoding="utf-8")
    if "--write" in sys.argv:
        DOC.write_text(with_table(current), encoding="utf-8")
    elif "--check" in sys.argv:
        if with_table(current) != current:
            sys.exit("docs/development.md: the layout table differs from the tree; run python .ci/layout_table.py --write")
    else:
        print(table())
