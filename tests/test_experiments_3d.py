"""The paper's 3D experiments run end to end on the simulator (quick configuration)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from usdeform.errors import InputError


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


def test_nuisance_table_runs_none_all_and_each_alone() -> None:
    from usdeform.experiments.paper_3d import NUISANCE_NAMES, ROBOT_QUICK
    from usdeform.experiments.paper_3d.robot_sweeps import nuisance_scenarios

    table = nuisance_scenarios(["table"], ROBOT_QUICK)
    assert [s.label for s in table] == ["none", "all", *NUISANCE_NAMES]
    none, every = table[0], table[1]
    assert none.controller.oscillation_n == 0 and none.path.max_tilt_deg == 0
    assert none.effects.latency.image_delay_s == 0 and none.effects.out_of_plane.jitter_mm == 0
    assert every.controller.oscillation_n == 0.8 and every.controller.tracking_ripple_n == 0.25
    assert every.effects.latency.image_delay_s == 0.1 and every.effects.out_of_plane.jitter_mm == 0.3
    assert every.path.max_tilt_deg == 15.0
    # The robot's nuisances leave the tissue, and so the palpations and fits, as without them.
    assert {s.phantom for s in table if s.label in ("none", "force", "delay", "jitter")} == {none.phantom}
    assert [s.label for s in nuisance_scenarios(["force", "delay", "force"], ROBOT_QUICK)] == ["force + delay"]
    for choices, message in ((["table", "force"], "give it alone"), (["all", "path"], "give it alone"), (["x"], "x")):
        with pytest.raises(InputError, match=message):
            nuisance_scenarios(choices, ROBOT_QUICK)


def test_tissue_nuisances_change_the_vessel_and_stiffness_along_the_path() -> None:
    from usdeform.experiments.paper_3d import ROBOT_QUICK
    from usdeform.experiments.paper_3d.robot_sweeps import nuisance_scenarios

    scenarios = {s.label: s.phantom for s in nuisance_scenarios(["table"], ROBOT_QUICK)}
    length = ROBOT_QUICK.length_mm

    def change(label: str, name: str) -> float:
        start, end = scenarios[label].section_at(0.0), scenarios[label].section_at(length)
        return getattr(end, name) - getattr(start, name)

    base_radius = scenarios["none"].section_at(0.0).vessel_radius_mm
    assert change("vessel", "vessel_depth_mm") == pytest.approx(5.0)
    assert change("vessel", "vessel_radius_mm") == pytest.approx(-0.3 * base_radius)
    # The path curves 5 mm sideways: the vessel moves 5 mm the other way in the image (on top of its own 3 mm).
    assert change("path", "vessel_center_x_mm") - change("none", "vessel_center_x_mm") == pytest.approx(-5.0)
    stiffness = scenarios["stiffness"]
    along = stiffness.stiffness_scale_at(np.linspace(0.0, length, 41))
    assert along.max() == pytest.approx(1.3, abs=0.01) and along.min() == pytest.approx(0.7, abs=0.01)
    across = stiffness.section_at(0.0).lateral_factor(np.array([-20.0, 20.0]))
    np.testing.assert_allclose(across, [0.7, 1.3])
    assert scenarios["none"].section_at(0.0).lateral_stiffness_gradient == 0


def test_nuisance_is_refused_for_paper_2d(capsys) -> None:
    from usdeform.cli import main

    assert main(["experiment", "paper-2d", "--nuisance", "force", "--output", "unused"]) == 2
    assert "--nuisance: only for paper-3d" in capsys.readouterr().err
