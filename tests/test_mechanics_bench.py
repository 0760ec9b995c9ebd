"""The FEM benchmark runs, and its NumPy and SciPy contenders solve the same sections to the same forces."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

BENCH = Path(__file__).resolve().parents[1] / "benches" / "bench_mechanics.py"


def test_mechanics_bench_contenders_agree() -> None:
    output = subprocess.run(
        [sys.executable, str(BENCH), "--quick", "--json"], check=True, capture_output=True, text=True
    ).stdout
    results = json.loads(output)
    assert set(results) == {
        "rust-loop+rust-ldlt",
        "numpy-loop+rust-ldlt",
        "rust-loop+scipy-superlu-symmetric",
        "numpy-loop+scipy-splu",
    }
    for result in results.values():
        assert result["seconds"] > 0
        assert result["max_force_difference_n"] < 1e-9
