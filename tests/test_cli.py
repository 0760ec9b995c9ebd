"""The command line: PLUS reconstruction, and fitting a model file to
simulated palpations then correcting a simulated sweep with it, end to end."""

from __future__ import annotations

import dataclasses
import json
import re
from pathlib import Path

import numpy as np
import pytest

from usdeform.cli import main
from usdeform.correction import zero_force_probe_to_base
from usdeform.errors import InputError
from usdeform.io import load_model, read_sequence, read_volume, save_model, write_sequence
from usdeform.metrics import dice, segment_vessel
from usdeform.regression import VesselAnchoredModel


def test_reconstruct_the_real_plus_sweep(plus_data: Path, tmp_path: Path, capsys) -> None:
    output, coverage = tmp_path / "spine.nrrd", tmp_path / "coverage.nrrd"
    code = main(
        [
            "reconstruct",
            str(plus_data / "SpinePhantomFreehand.igs.mha"),
            "--config",
            str(plus_data / "PlusDeviceSet_VolumeReconstructionOnly_SpinePhantom_NN_MEAN.xml"),
            "--output",
            str(output),
            "--coverage",
            str(coverage),
        ]
    )
    assert code == 0
    assert "compounded 21 of 21 frames" in capsys.readouterr().out
    volume, weight = read_volume(output), read_volume(coverage)
    assert volume.image.shape == weight.image.shape
    assert (weight.image > 0).sum() > 10_000
    assert volume.image[weight.image > 0].mean() > 1.0


def test_missing_file_is_a_clear_error_not_a_traceback(tmp_path: Path, capsys) -> None:
    assert main(["reconstruct", str(tmp_path / "missing.mha"), "--output", str(tmp_path / "v.nrrd")]) == 2
    assert "usdeform: error:" in capsys.readouterr().err
    assert not (tmp_path / "v.nrrd").exists()


def test_bad_option_exits_with_usage() -> None:
    with pytest.raises(SystemExit):
        main(["reconstruct", "x.mha", "--output", "v.nrrd", "--compounding", "median"])


@pytest.fixture(scope="module")
def scans(tmp_path_factory):
    """Two palpations (s = 15 and 45 mm, up to 8 N) and a 10-frame sweep at 8 N over s = 20-40 mm of
    the small test phantom, 96 x 96 pixels, written as PLUS sequence files: (folder, sweep truth)."""
    from usdeform.sim import coarse_phantom, simulate_palpation, simulate_sweep

    phantom = coarse_phantom()
    folder = tmp_path_factory.mktemp("scans")
    with pytest.MonkeyPatch.context() as patch:
        patch.setenv("USDEFORM_CACHE_DIR", str(tmp_path_factory.mktemp("usdeform-cache")))
        for name, s_mm, seed in (("palpation-15.seq.nrrd", 15.0, 11), ("palpation-45.mha", 45.0, 12)):
            palpation, _ = simulate_palpation(phantom, s_mm, 8.0, n_frames=8, seed=seed, rows=96, cols=96)
            write_sequence(folder / name, palpation)
        sweep, truth = simulate_sweep(phantom, 20.0, 20.0, 8.0, n_frames=10, seed=3, rows=96, cols=96)
    write_sequence(folder / "sweep.mha", sweep)
    return folder, truth


def _palpations(folder: Path) -> list[str]:
    return [str(folder / "palpation-15.seq.nrrd"), str(folder / "palpation-45.mha")]


def _vessel_dice(frames: np.ndarray, truth_masks: np.ndarray) -> float:
    return float(
        np.mean([dice(segment_vessel(frame).mask, mask) for frame, mask in zip(frames, truth_masks, strict=False)])
    )


@pytest.mark.parametrize("basis", ["quadratic", "bspline:6x5"])
def test_fit_then_correct_restores_the_zero_force_vessel(scans, tmp_path: Path, capsys, basis: str) -> None:
    folder, truth = scans
    model_path = tmp_path / "model.json"
    assert (
        main(["fit", *_palpations(folder), "--output", str(model_path), "--flexible-layer-mm", "60", "--basis", basis])
        == 0
    )
    captured = capsys.readouterr()
    printed = captured.out
    assert "fit: " in captured.err and "regression" in captured.err  # the progress bar, at its last stage
    stiffness = [float(k) for k in re.findall(r"stiffness (\d+) \+/- \d+ N/m \(R\^2 (?:[\d.]+)\)", printed)]
    assert len(stiffness) == 2 and stiffness[0] > stiffness[1] > 0, printed  # the phantom softens along s
    assert re.search(r"loss [\d.e-]+; wrote", printed), printed

    model_file = load_model(model_path)
    expected_shape = (2, 10) if basis == "quadratic" else (2, 3, 5, 6)
    assert isinstance(model_file.model, VesselAnchoredModel)  # the recommended method; the phantom has a vessel
    assert model_file.model.image_model.coefficients.shape == expected_shape
    assert model_file.sampled.positions_mm.shape == (2, 3)
    assert model_file.sampled.positions_mm[1, 1] - model_file.sampled.positions_mm[0, 1] == pytest.approx(30.0)
    assert model_file.provenance["solver"] == "exact" and model_file.provenance["flexible_layer_mm"] == 60.0

    corrected_path, volume_path = tmp_path / "corrected.seq.nrrd", tmp_path / "corrected.nrrd"
    assert (
        main(
            [
                "correct",
                str(folder / "sweep.mha"),
                "--model",
                str(model_path),
                "--output",
                str(corrected_path),
                "--volume",
                str(volume_path),
                "--coverage",
                str(tmp_path / "coverage.nrrd"),
                "--spacing",
                "0.6",
                "--interpolation",
                "linear",
            ]
        )
        == 0
    )
    assert "wrote" in capsys.readouterr().out
    sweep, corrected = read_sequence(folder / "sweep.mha"), read_sequence(corrected_path)
    for name in ("timestamps", "pose_valid", "image_to_probe"):
        assert np.array_equal(getattr(corrected, name), getattr(sweep, name)), name
    # Corrected frames sit at the zero-force poses: moved back against the probe axis by lambda.
    zero_force = zero_force_probe_to_base(sweep.probe_to_base, sweep.probe_displacement)
    np.testing.assert_allclose(corrected.probe_to_base, zero_force, atol=1e-9)
    assert np.array_equal(corrected.force, np.zeros(len(sweep)))
    assert np.array_equal(corrected.probe_displacement, np.zeros(len(sweep)))
    assert not np.array_equal(corrected.frames, sweep.frames)
    deformed_dice = _vessel_dice(sweep.frames, truth.zero_force_vessel_mask)
    corrected_dice = _vessel_dice(corrected.frames, truth.zero_force_vessel_mask)
    assert corrected_dice > deformed_dice + 0.05, (deformed_dice, corrected_dice)

    volume, coverage = read_volume(volume_path), read_volume(tmp_path / "coverage.nrrd")
    assert volume.image.shape == coverage.image.shape
    assert np.allclose(np.abs(volume.index_to_world[:3, :3]).sum(axis=0), 0.6)
    assert (coverage.image > 0).sum() > 1000 and volume.image[coverage.image > 0].mean() > 1.0


def test_fit_records_every_option(scans, tmp_path: Path) -> None:
    folder, _ = scans
    model_path = tmp_path / "model.json"
    assert (
        main(
            [
                "fit",
                *_palpations(folder),
                "--output",
                str(model_path),
                "--flexible-layer-mm",
                "50",
                "--basis",
                "bspline:4x4",
                "--smoothness",
                "0.001",
                "--coupling",
                "force",
                "--integration",
                "displacement",
            ]
        )
        == 0
    )
    document = json.loads(model_path.read_text())
    assert document["basis"] == {"name": "bspline", "n_y": 4, "n_x": 4}
    assert (document["coupling"], document["integration"]) == ("force", "displacement")
    assert document["provenance"]["smoothness"] == 0.001
    assert (document["provenance"]["method"], document["provenance"]["wall"]) == ("recommended", "auto")
    assert (
        main(
            [
                "fit",
                _palpations(folder)[0],
                "--output",
                str(model_path),
                "--flexible-layer-mm",
                "50",
                "--method",
                "paper",
                "--solver",
                "adam",
            ]
        )
        == 0
    )
    paper = load_model(model_path)
    assert (paper.provenance["solver"], paper.provenance["method"], paper.provenance["wall"]) == (
        "adam",
        "paper",
        "off",
    )
    assert (paper.model.coupling, paper.model.integration) == ("stiffness", "force")


@pytest.mark.parametrize("option", [["--basis", "bspline:3x8"], ["--basis", "cubic"], ["--solver", "newton"]])
def test_bad_fit_options_exit_with_usage(option: list[str]) -> None:
    with pytest.raises(SystemExit):
        main(["fit", "p.mha", "--output", "m.json", "--flexible-layer-mm", "60", *option])


def test_fit_and_correct_errors_are_clear(scans, tmp_path: Path, capsys) -> None:
    folder, _ = scans
    sweep = read_sequence(folder / "sweep.mha")
    write_sequence(tmp_path / "no-force.mha", dataclasses.replace(sweep, force=None))
    model_path = tmp_path / "model.json"
    assert main(["fit", str(tmp_path / "no-force.mha"), "--output", str(model_path), "--flexible-layer-mm", "60"]) == 2
    assert f"{tmp_path / 'no-force.mha'}: a palpation needs per-frame ContactForce" in capsys.readouterr().err
    assert (
        main(
            [
                "fit",
                _palpations(folder)[0],
                "--output",
                str(model_path),
                "--flexible-layer-mm",
                "60",
                "--method",
                "paper",
                "--smoothness",
                "0.1",
            ]
        )
        == 2
    )  # smoothness needs a B-spline basis
    assert "smoothness" in capsys.readouterr().err
    assert not model_path.exists()

    fit = ["fit", _palpations(folder)[0], "--output", str(model_path), "--flexible-layer-mm", "60"]
    assert main([*fit, "--method", "paper"]) == 0  # the quadratic's (2, 10) coefficients are cut below
    without_positions = tmp_path / "bare.json"
    save_model(without_positions, load_model(model_path).model)
    corrected = tmp_path / "corrected.mha"
    assert (
        main(["correct", str(folder / "sweep.mha"), "--model", str(without_positions), "--output", str(corrected)]) == 2
    )
    assert "sampled_positions" in capsys.readouterr().err
    assert (
        main(["correct", str(tmp_path / "no-force.mha"), "--model", str(model_path), "--output", str(corrected)]) == 2
    )
    assert "ContactForce" in capsys.readouterr().err
    write_sequence(
        tmp_path / "cropped.mha", dataclasses.replace(sweep, frames=np.ascontiguousarray(sweep.frames[:, :80]))
    )
    assert main(["correct", str(tmp_path / "cropped.mha"), "--model", str(model_path), "--output", str(corrected)]) == 2
    assert "frames of 80 x 96 pixels, but the model was fitted on 96 x 96 frames" in capsys.readouterr().err
    document = json.loads(model_path.read_text())
    document["coefficients"][1] = document["coefficients"][1][:9]
    model_path.write_text(json.dumps(document))
    assert main(["correct", str(folder / "sweep.mha"), "--model", str(model_path), "--output", str(corrected)]) == 2
    assert f"usdeform: error: {model_path}: coefficients: expected shape (2, 10)" in capsys.readouterr().err
    assert not corrected.exists()


def test_the_plus_clip_rectangle_keeps_pixels_where_they_were() -> None:
    from usdeform.volume import clip_frames

    frames = np.arange(2 * 6 * 8, dtype=np.uint8).reshape(2, 6, 8)
    image_to_base = np.stack([np.diag([0.5, 0.4, 1.0, 1.0])] * 2)
    image_to_base[:, :3, 3] = [10.0, 20.0, 30.0]
    clipped, clipped_to_base = clip_frames(frames, image_to_base, origin=(3, 2), size=(4, 3))
    assert clipped.shape == (2, 3, 4) and clipped[1, 0, 0] == frames[1, 2, 3]
    np.testing.assert_allclose(clipped_to_base[1] @ [0, 0, 0, 1], image_to_base[1] @ [3, 2, 0, 1])
    with pytest.raises(InputError, match="ClipRectangle"):
        clip_frames(frames, image_to_base, origin=(6, 0), size=(4, 3))


def test_stiffness_weights_ignore_how_deep_the_probe_pressed() -> None:
    from usdeform.correction import probe_surface_positions

    probe_to_base = np.stack([np.eye(4)] * 2)
    probe_to_base[:, :3, :3] = np.diag([1.0, -1.0, -1.0])  # probe pointing down the base z axis
    probe_to_base[0, :3, 3] = [5.0, 7.0, 100.0]
    probe_to_base[1, :3, 3] = [5.0, 7.0, 92.0]  # same spot, pressed 8 mm deeper
    positions = probe_surface_positions(probe_to_base)
    np.testing.assert_allclose(positions, [[5.0, 7.0, 0.0], [5.0, 7.0, 0.0]])
