"""docs/development.md's layout table is the tree's (``python .ci/layout_table.py``)."""

import importlib.util
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent


def test_the_layout_table_matches_the_tree() -> None:
    spec = importlib.util.spec_from_file_location("layout_table", ROOT / ".ci" / "layout_table.py")
    assert spec is not None and spec.loader is not None
    layout_table = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(layout_table)
    page = (ROOT / "docs" / "development.md").read_text(encoding="utf-8")
    assert layout_table.with_table(page) == page, "run: python .ci/layout_table.py --write"
    assert "`python/usdeform/correction/`" in page and "`rust/core/src/warp.rs`" in page


def test_no_module_is_over_600_lines() -> None:
    spec = importlib.util.spec_from_file_location("module_lengths", ROOT / ".ci" / "module_lengths.py")
    assert spec is not None and spec.loader is not None
    module_lengths = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module_lengths)
    assert module_lengths.long_modules(ROOT / "python" / "usdeform") == []
