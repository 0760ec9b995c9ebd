"""``usdeform demo --quick``: the real pipeline on the simulator writes its files, and the correction beats
the deformed frames and volume against the simulator's zero-force truth."""

from __future__ import annotations

import base64
import html
import re
import shlex
from pathlib import Path

import numpy as np
import pytest

from usdeform.cli import build_parser, main
from usdeform.demo import DemoConfig, pipeline, run_demo
from usdeform.errors import InputError
from usdeform.fitting import FIT_METHODS
from usdeform.io import load_model, read_sequence, read_volume
from usdeform.regression import BSplineDisplacementModel, VesselAnchoredModel
from usdeform.sim.mechanics import cache_dir, solution


def test_writes_the_recordings_the_model_and_the_volumes(quick_demo) -> None:
    result, output, _ = quick_demo
    for number in range(len(result.config.palpation_positions_mm)):
        palpation = read_sequence(output / f"palpation_{number}.seq.nrrd")
        assert len(palpation) == result.config.palpation_frames
        assert palpation.force is not None and palpation.probe_displacement is not None
    sweep = read_sequence(output / "sweep.seq.nrrd")
    assert len(sweep) == result.config.sweep_frames
    assert np.array_equal(sweep.frames, result.sweep.frames)
    corrected = read_sequence(output / "corrected.seq.nrrd")
    assert not np.array_equal(corrected.frames, sweep.frames)

    model_file = load_model(output / "model.json")
    # The recommended settings: B-splines, the collapse anchored to the phantom's vessel.
    assert isinstance(model_file.model, VesselAnchoredModel)
    assert isinstance(model_file.model.image_model, BSplineDisplacementModel)
    assert model_file.model.integration == FIT_METHODS["recommended"].integration == "displacement"
    assert model_file.sampled is not None and len(model_file.sampled.profiles) == 3

    volumes = {name: read_volume(output / f"{name}.nrrd") for name in ("deformed", "corrected", "truth")}
    shapes = {volume.image.shape for volume in volumes.values()}
    assert len(shapes) == 1
    assert all(np.array_equal(v.index_to_world, volumes["truth"].index_to_world) for v in volumes.values())
    for name, volume in volumes.items():
        assert volume.image.max() > 50, name  # speckle landed in every volume


def test_the_correction_beats_the_deformed_frames_against_the_truth(quick_demo) -> None:
    result, _, _ = quick_demo
    frames = result.frame_metrics
    method = result.config.method
    assert frames.dice[method].shape == (result.config.sweep_frames,)
    assert frames.mean("dice", method) > frames.mean("dice", "deformed") + 0.1
    assert frames.mean("dice", method) > 0.85
    assert frames.mean("area", method) < 0.6 * frames.mean("area", "deformed")
    assert frames.mean("centroid", method) < 0.5 * frames.mean("centroid", "deformed")
    # frame by frame, not only on average
    assert np.all(frames.dice[method] > frames.dice["deformed"])

    vessel = result.volume_metrics.vessel_volume_mm3
    assert vessel["truth"] > 0
    assert abs(vessel["corrected"] - vessel["truth"]) < abs(vessel["deformed"] - vessel["truth"])


def test_the_stiffness_fits_follow_the_phantom(quick_demo) -> None:
    result, _, _ = quick_demo
    stiffness = [m.stiffness.stiffness_mean_sd_n_per_m[0] for m in result.measured]
    scale = result.phantom.stiffness_scale_at(np.array(result.config.palpation_positions_mm))
    assert np.all(np.diff(scale) < 0) and np.all(np.diff(stiffness) < 0)  # stiffer where the phantom is stiffer
    assert all(m.stiffness.r_squared[2] > 0.99 for m in result.measured)
    assert set(result.timings_s) >= {"FEM solves", "simulate sweep", "correction", "compounding"}


def test_the_report_is_self_contained_and_starts_with_the_summary(quick_demo) -> None:
    result, output, _ = quick_demo
    page = (output / "report.html").read_text()
    body = page[page.index("<body>") :]
    assert body.index('id="summary"') < body.index("<img")
    summary = re.search(r'<p id="summary">(.*?)</p>', page, re.S)
    assert summary and "Dice" in summary.group(1) and f"{result.sweep_force_n:g} N" in summary.group(1)
    images = re.findall(r'<img src="data:image/png;base64,([^"]+)"', page)
    assert len(images) == 5
    assert all(base64.b64decode(image)[:8] == b"\x89PNG\r\n\x1a\n" for image in images)
    assert 'src="http' not in page and "<script" not in page


def test_the_command_ends_with_a_short_summary_and_the_report(quick_demo) -> None:
    result, output, printed = quick_demo
    lines = printed.strip().splitlines()
    assert len(lines) <= 6
    assert lines[-1] == f"report: {output / 'report.html'}"
    dice = re.search(r"Dice ([\d.]+) -> ([\d.]+)", printed)
    assert dice, printed
    assert float(dice.group(1)) == pytest.approx(result.frame_metrics.mean("dice", "deformed"), abs=1e-3)
    assert float(dice.group(2)) == pytest.approx(result.frame_metrics.mean("dice", "recommended"), abs=1e-3)
    assert "time per stage: FEM solves" in printed


def test_bad_options_are_refused_before_any_work(tmp_path: Path, capsys) -> None:
    assert main(["demo", "--output", str(tmp_path / "d"), "--quick", "--force", "40"]) == 2
    assert "force_n" in capsys.readouterr().err
    assert not (tmp_path / "d" / "report.html").exists()
    with pytest.raises(InputError, match="seed"):
        DemoConfig(seed=-1)
    with pytest.raises(InputError, match="preset"):
        run_demo(tmp_path, DemoConfig(preset="gel"))  # type: ignore[arg-type]


def test_the_shipped_fem_solutions_are_the_default_demos() -> None:
    config = DemoConfig()
    positions = config.palpation_positions_mm
    needed = set(pipeline.solution_keys(config.phantom(), positions[0], positions[-1]))
    shipped = {path.stem for path in pipeline.SHIPPED_SOLUTIONS.glob("*.npz")}
    assert shipped == needed, (
        "the phantom or the solver changed: run `usdeform demo` with an empty USDEFORM_CACHE_DIR and copy "
        f"{sorted(needed)} from its mechanics folder into {pipeline.SHIPPED_SOLUTIONS} (remove the others)"
    )


def test_a_fresh_cache_takes_the_shipped_solutions_without_solving(tmp_path: Path, monkeypatch) -> None:
    monkeypatch.setenv("USDEFORM_CACHE_DIR", str(tmp_path))

    def no_solve(*args, **kwargs):
        raise AssertionError("solved although a shipped solution was in the cache")

    monkeypatch.setattr(solution, "_solve_uncached", no_solve)
    config = DemoConfig()
    phantom, positions = config.phantom(), config.palpation_positions_mm
    pipeline._seed_solution_cache(pipeline.solution_keys(phantom, positions[0], positions[-1]))
    assert sorted(path.name for path in cache_dir().iterdir()) == sorted(
        path.name for path in pipeline.SHIPPED_SOLUTIONS.glob("*.npz")
    )
    at_middle = phantom.solution_at(positions[1])
    assert np.all(np.diff(at_middle.force_n) > 0) and at_middle.force_n[-1] > phantom.max_force_n


def test_the_next_steps_are_commands_on_the_demos_files(quick_demo) -> None:
    _, output, _ = quick_demo
    page = (output / "report.html").read_text()
    block = html.unescape(re.search(r"<h2>Next</h2>.*?<pre>(.*?)</pre>", page, re.S).group(1))
    commands = block.replace("\\\n", " ").splitlines()
    assert [shlex.split(command)[1] for command in commands] == ["fit", "correct"]
    fit, correct = (build_parser().parse_args(shlex.split(command)[1:]) for command in commands)
    assert all((output / path).exists() for path in fit.palpations) and (output / correct.sweep).exists()
    assert fit.method == "recommended" and fit.basis is None and fit.integration is None  # the method's settings
