"""The fit's report (``usdeform fit --report DIR``, :mod:`usdeform.fitting`): tracks per depth band and why
they were dropped, the cross-validated residual by region, the warnings, and the command line and batch doors."""

from __future__ import annotations

import dataclasses
import json
import re
from pathlib import Path

import numpy as np
import pytest

from usdeform.batch import read_manifest
from usdeform.batch.stages import fit_position
from usdeform.batch.tasks import plan_tasks
from usdeform.cli import main
from usdeform.fitting import HELD_OUT_WARNING_PX, assess_fit, fit_measured, fit_palpations, write_fit_report
from usdeform.io import write_sequence
from usdeform.metrics import pixel_size_mm
from usdeform.optical_flow import REJECTION_REASONS

CUT_ROW = 80  # frames are zeroed from this row down: no speckle to track there
LAYER_MM = "50"  # the coarse phantom's depth


@pytest.fixture(scope="module")
def cut_palpation(small_palpation):
    """The small palpation with every frame black below ``CUT_ROW``, and the depth of that row, mm."""
    recording, _ = small_palpation
    frames = recording.frames.copy()
    frames[:, CUT_ROW:, :] = 0
    return dataclasses.replace(recording, frames=frames), CUT_ROW * pixel_size_mm(recording.image_to_probe)[1]


@pytest.fixture(scope="module")
def cut_fit(cut_palpation):
    recording, _ = cut_palpation
    fitted = fit_palpations([recording], float(LAYER_MM))
    return fitted, assess_fit(fitted, names=["cut.seq.nrrd"])


def _written(folder: Path, name: str, recording) -> Path:
    path = folder / name
    write_sequence(path, recording)
    return path


def test_a_deep_band_without_speckle_is_warned_about_at_its_depth(cut_palpation, cut_fit) -> None:
    _, cut_mm = cut_palpation
    _, report = cut_fit
    below = [w for w in report.warnings if w.startswith("below ")]
    assert len(below) == 1, report.warnings
    named = re.match(r"below ([\d.]+) mm", below[0])
    assert named, below
    depth = float(named.group(1))
    # The band edge at or above the cut (tracks just above it lose their window's lower half too).
    assert cut_mm - 2 * report.band_mm <= depth <= cut_mm, (depth, cut_mm)
    assert "extrapolated" in below[0] and "too little texture" in below[0]
    for band in report.bands:
        if band.tracks and band.depth_mm[0] >= cut_mm:  # wholly below the cut: every track dropped, for texture
            assert band.kept == 0 and max(band.dropped, key=band.dropped.__getitem__) == "texture"
        if band.tracks and band.depth_mm[1] <= 15.0:  # well above the cut and the vessel: all kept
            assert band.kept == band.tracks


def test_report_numbers_agree_with_the_tracker(cut_fit, tmp_path: Path) -> None:
    fitted, report = cut_fit
    html_path, json_path = write_fit_report(report, tmp_path / "report")
    document = json.loads(json_path.read_text())
    assert document["warnings"] == list(report.warnings)
    tracked = fitted.measured[0].tracked
    palpation = document["palpations"][0]
    assert palpation["tracks"] == len(tracked.points_px) == sum(band["tracks"] for band in palpation["bands"])
    assert palpation["kept"] == int(tracked.valid[-1].sum()) == int(np.sum(tracked.dropped_reason < 0))
    for index, reason in enumerate(REJECTION_REASONS):
        in_bands = sum(band["reasons"][reason] for band in palpation["bands"])
        assert in_bands == palpation["rejected"][reason] == int(tracked.rejected[reason].sum())
        assert in_bands == int(np.sum(tracked.dropped_reason == index))
    assert palpation["bands"] == document["depth_bands"]  # one palpation: the pooled bands are its own
    assert sum(region["points"] for region in document["cross_validation"]["regions"]) == palpation["tracks"]
    assert set(palpation["stiffness"]["r_squared"]) == {"1", "2", "3"}
    page = html_path.read_text()
    assert page.count("data:image/png;base64,") == 4 and 'id="summary"' in page
    assert all(f"<li>{warning}</li>" in page for warning in report.warnings if "&" not in warning)


def test_a_region_of_wrong_tracks_has_a_large_held_out_residual(cut_palpation, cut_fit) -> None:
    """Tracks 4 px off in one region (a tracking error the others do not share): the model refitted without
    that region's fold predicts the true motion there, so the held-out residual flags it, at its depth."""
    recording, _ = cut_palpation
    fitted, clean = cut_fit
    measured = fitted.measured[0]
    axial_mm = pixel_size_mm(recording.image_to_probe)[1]
    n_tracks = len(measured.tracked.points_px)
    y_mm = measured.observations.points_px[:, 1] * axial_mm
    x = measured.observations.points_px[:, 0]
    wrong = (np.arange(len(x)) < n_tracks) & (y_mm >= 9.0) & (y_mm < 12.0) & (x < 128 / 3)
    assert wrong.sum() >= 3
    displacements = measured.observations.displacements_px.copy()
    displacements[:, wrong, 1] += 4.0
    observations = dataclasses.replace(measured.observations, displacements_px=displacements)
    corrupted = [dataclasses.replace(measured, observations=observations)]
    refitted = dataclasses.replace(fitted, measured=corrupted, fit=fit_measured(corrupted, fitted.method))
    report = assess_fit(refitted)
    region = next(r for r in report.regions if r.depth_mm == (9.0, 12.0) and r.lateral == "left")
    before = next(r for r in clean.regions if r.depth_mm == (9.0, 12.0) and r.lateral == "left")
    assert before.held_out_px < HELD_OUT_WARNING_PX < region.held_out_px
    assert region.held_out_px > region.fitted_px  # the fit bends towards them; held out, it does not
    warning = next(w for w in report.warnings if "held-out" in w)
    assert "at 9-12 mm deep on the left third" in warning


def test_fit_prints_the_warnings_with_or_without_report(cut_palpation, small_palpation, tmp_path: Path, capsys) -> None:
    recording, _ = cut_palpation
    cut = _written(tmp_path, "cut.seq.nrrd", recording)
    model = tmp_path / "model.json"
    assert main(["fit", str(cut), "--output", str(model), "--flexible-layer-mm", LAYER_MM, "--method", "paper"]) == 0
    printed = capsys.readouterr()
    assert re.search(r"usdeform: warning: below [\d.]+ mm, \d+ % of tracks were dropped", printed.err)
    assert "usdeform: warning" not in printed.out and not (tmp_path / "report").exists()

    whole = _written(tmp_path, "whole.seq.nrrd", small_palpation[0])
    folder = tmp_path / "reports" / "whole"  # created, parents too
    arguments = ["fit", str(whole), "--output", str(model), "--flexible-layer-mm", LAYER_MM, "--method", "paper"]
    assert main([*arguments, "--report", str(folder)]) == 0
    printed = capsys.readouterr()
    assert "below" not in printed.err  # every depth band of the whole palpation kept its tracks
    assert f"{folder / 'report.html'}, {folder / 'report.json'}" in printed.out
    document = json.loads((folder / "report.json").read_text())
    assert document["format"] == "usdeform-fit-report" and document["fit"]["basis"] == "quadratic"
    assert not list(folder.glob(".*.part"))


@pytest.mark.parametrize("kind", ["existing file", "not writable"])
def test_a_bad_report_folder_is_refused_before_any_work(kind: str, tmp_path: Path, capsys) -> None:
    target = tmp_path / "taken.json" if kind == "existing file" else Path("/proc/usdeform-report")
    if kind == "existing file":
        target.write_text("{}")
    model = tmp_path / "model.json"
    # The palpation does not exist: were it read first, the error would name it.
    arguments = ["fit", str(tmp_path / "missing.seq.nrrd"), "--output", str(model), "--flexible-layer-mm", "50"]
    assert main([*arguments, "--report", str(target)]) == 2
    error = capsys.readouterr().err.strip()
    assert error.startswith("usdeform: error: --report: ") and "\n" not in error
    assert not model.exists() and sorted(tmp_path.iterdir()) == ([target] if kind == "existing file" else [])


def test_batch_writes_the_report_with_the_manifest_key(small_palpation, tmp_path: Path) -> None:
    _written(tmp_path, "p1.seq.nrrd", small_palpation[0])
    manifest = tmp_path / "cohort.toml"
    manifest.write_text(
        '[options]\nflexible_layer_mm = 50.0\nmethod = "paper"\n\n'
        '[[subjects]]\nid = "a"\npalpations = ["p1.seq.nrrd"]\noptions = { report = true }\n\n'
        '[[subjects]]\nid = "b"\npalpations = ["p1.seq.nrrd"]\n'
    )
    csv = tmp_path / "cohort.csv"
    csv.write_text(
        "subject,palpations,flexible_layer_mm,method,report\na,p1.seq.nrrd,50,paper,true\nb,p1.seq.nrrd,50,paper,\n"
    )
    for path in (manifest, csv):
        with_report, without = (subject.options for subject in read_manifest(path).subjects)
        assert with_report.report and not without.report
        assert with_report.fit_options()["report"] is True and "report" not in without.fit_options()
    fits = {task.subject: task for task in plan_tasks(read_manifest(manifest), tmp_path / "out") if task.kind == "fit"}
    assert [p.name for p in fits["a"].outputs] == ["model.json", "report.html", "report.json"]
    assert [p.name for p in fits["b"].outputs] == ["model.json"]
    task = fits["a"]
    task.outputs[1].parent.mkdir(parents=True)
    details = fit_position(task.recordings, task.options, task.outputs[0], task.outputs[1].parent)
    assert all(path.is_file() for path in task.outputs)
    assert json.loads(task.outputs[2].read_text())["warnings"] == details["warnings"]


def test_the_report_lists_the_palpated_lumen_that_correct_checks_sweeps_against(
    small_palpation, tmp_path: Path
) -> None:
    recording, _ = small_palpation
    fitted = fit_palpations([recording], float(LAYER_MM))
    report = assess_fit(fitted, names=["p.seq.nrrd"])
    (lumen,) = report.to_json()["palpated_lumens"]
    # The coarse phantom's vessel: 18 mm below the surface, radius 5 mm (a little less as segmented at contact).
    assert lumen["palpation"] == "p.seq.nrrd" and lumen["vessel"] == 0
    assert lumen["depth_mm"] == pytest.approx(18.0, abs=1.0) and lumen["radius_mm"] == pytest.approx(5.0, abs=0.8)
    html_path, _ = write_fit_report(report, tmp_path)
    assert "Palpated lumens" in html_path.read_text() and f"{lumen['depth_mm']:.1f}" in html_path.read_text()
