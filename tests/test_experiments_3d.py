"""The paper's 3D experiments run end to end on the simulator (quick configuration)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest


@pytest.fixture(scope="module")
def quick_run(quick_experiment) -> Path:
    return quick_experiment("paper-3d")


def test_writes_tables_and_figures(quick_run: Path) -> None:
    for name in ("results.md", "results.json", "fig9_views.png", "fig10_bars.png"):
        assert (quick_run / name).stat().st_size > 1000, name
    text = (quick_run / "results.md").read_text()
    for heading in ("Per frame (Fig. 10)", "Volume (Fig. 9)", "Area reduction", "Stiffness", "by region"):
        assert heading in text


def test_correction_puts_the_vessel_back_in_place(quick_run: Path) -> None:
    results = json.loads((quick_run / "results.json").read_text())
    assert {case["phantom"] for case in results["cases"]} == {"stiff", "soft"}
    for case in results["cases"]:
        volume, frames = case["volume"], case["frames"]
        # Run (quick): deformed centre line 4.6-4.8 mm too deep; paper model within 0.4 mm, B-spline 0.2 mm.
        assert volume["deformed"]["depth_error_mean_mm"] < -2.0, case["phantom"]
        for variant in ("paper", "spline-lambda", "spline-lambda/sweep"):
            assert abs(volume[variant]["depth_error_mean_mm"]) < 1.0, (case["phantom"], variant)
            assert volume[variant]["dice"] > volume["deformed"]["dice"] + 0.1, (case["phantom"], variant)
            assert np.nanmax(frames[variant]["centroid_mm"]) < np.nanmax(frames["deformed"]["centroid_mm"])
            assert np.nanmean(np.abs(frames[variant]["area_diff_mm2"])) < np.nanmean(
                np.abs(frames["deformed"]["area_diff_mm2"])
            )
        assert volume["truth"]["dice"] == 1.0
        # The deformed lumen is squashed: its bottom wall moved up more than its top.
        assert case["walls"]["deformed"]["height_error_mm"] < -1.0
        assert abs(case["walls"]["spline-lambda"]["height_error_mm"]) < abs(
            case["walls"]["deformed"]["height_error_mm"]
        )
        # The sweep's own stiffness reproduces the recorded displacement at the recorded force.
        assert case["stiffness"]["sweep"]["max_mm"] < 1e-6
