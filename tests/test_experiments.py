"""The paper's 2D experiments run end to end on the simulator (quick configuration)."""

from __future__ import annotations

import json
from pathlib import Path

import pytest


@pytest.fixture(scope="module")
def quick_run(quick_experiment) -> Path:
    return quick_experiment("paper-2d")


def test_writes_tables_and_figures(quick_run: Path) -> None:
    for name in (
        "results.md",
        "results.json",
        "fig4_stiffness.png",
        "fig6-8_vessel_boundaries.png",
        "residual_maps.png",
    ):
        assert (quick_run / name).stat().st_size > 1000, name
    text = (quick_run / "results.md").read_text()
    for heading in ("TABLE I", "TABLE II", "same position", "other position", "unseen soft tissue", "Diagnosis"):
        assert heading in text


def test_correction_improves_dice_and_exact_loss_is_not_above_adam(quick_run: Path) -> None:
    results = json.loads((quick_run / "results.json").read_text())
    assert results["table_1"]["exact"]["loss"] <= results["table_1"]["adam"]["loss"]
    for case in results["cases"]:
        if case["target_force_n"] >= 10:
            assert case["dice"]["paper"] > case["dice"]["deformed"] + 0.03, case
            assert case["dice"]["spline"] > case["dice"]["deformed"] + 0.03, case
    stiff = [row for name, row in results["stiffness"].items() if name.startswith("stiff")]
    assert all(row["r2"]["2"] > 0.99 for row in stiff)
