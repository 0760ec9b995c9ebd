"""``usdeform simulate``: PLUS sequence files with the ground truth beside them, effects from the command line."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from usdeform.cli import main
from usdeform.errors import FileFormatError, InputError
from usdeform.io import read_sequence
from usdeform.sim import GroundTruth
from usdeform.sim.command import _TRUTH_FIELDS, parse_effects, read_ground_truth, write_ground_truth

SMALL = ["--preset", "coarse", "--rows", "64", "--cols", "64"]


@pytest.fixture(autouse=True)
def _private_cache(tmp_path_factory, monkeypatch) -> None:
    monkeypatch.setenv("USDEFORM_CACHE_DIR", str(tmp_path_factory.getbasetemp() / "simulate-cache"))


def _palpate(output: Path, *extra: str) -> list[Path]:
    arguments = ["simulate", "palpation", "--output", str(output), "--at", "20", "40", "--force", "8"]
    assert main([*arguments, "--frames", "6", *SMALL, *extra]) == 0
    return sorted(output.glob("*.seq.nrrd"))


def test_palpations_are_written_with_their_ground_truth(tmp_path: Path, capsys) -> None:
    paths = _palpate(tmp_path / "p")
    assert [p.name for p in paths] == ["palpation_20mm_8N.seq.nrrd", "palpation_40mm_8N.seq.nrrd"]
    captured = capsys.readouterr()
    assert "palpation_40mm_8N.truth.npz" in captured.out
    assert "simulate palpations: 100%" in captured.err  # the progress bar
    for path in paths:
        recording = read_sequence(path)
        truth = read_ground_truth(path.with_name(path.name.replace(".seq.nrrd", ".truth.npz")))
        assert recording.frames.shape == truth.zero_force_frames.shape == (6, 64, 64)
        assert truth.displacement_px.shape == (6, 64, 64, 2)
        assert recording.force is not None and recording.probe_displacement is not None
        assert recording.force.max() == pytest.approx(8.0, abs=1.0)  # the ramp reaches the force asked
        assert np.all(np.diff(truth.probe_displacement_mm) >= -0.05)  # pressing in
        assert truth.vessel_mask.any() and truth.zero_force_vessel_mask.any()
    positions = [
        read_ground_truth(p.with_name(p.name.replace(".seq.nrrd", ".truth.npz"))).sweep_position_mm for p in paths
    ]
    assert np.allclose(positions[0], 20.0) and np.allclose(positions[1], 40.0)


def test_same_seed_same_files_and_effects_change_the_recording(tmp_path: Path) -> None:
    first = read_sequence(_palpate(tmp_path / "a")[0])
    again = read_sequence(_palpate(tmp_path / "b")[0])
    assert np.array_equal(first.frames, again.frames) and np.array_equal(first.force, again.force)
    other_seed = read_sequence(_palpate(tmp_path / "c", "--seed", "1")[0])
    assert not np.array_equal(first.frames, other_seed.frames)
    relaxing = read_sequence(_palpate(tmp_path / "d", "--effect", "viscoelasticity:g=0.4,tau_s=0.3")[0])
    assert relaxing.probe_displacement is not None and first.probe_displacement is not None
    # a relaxing tissue needs a deeper press for the same force
    assert relaxing.probe_displacement[-1] > first.probe_displacement[-1] + 0.1


def test_a_sweep_moves_along_the_phantom_at_the_force(tmp_path: Path) -> None:
    arguments = ["simulate", "sweep", "--output", str(tmp_path), "--at", "10", "--length", "12", "--force", "5"]
    assert main([*arguments, "--frames", "12", *SMALL, "--effect", "latency:image_delay_s=0.04"]) == 0
    (path,) = tmp_path.glob("*.seq.nrrd")
    recording = read_sequence(path)
    truth = read_ground_truth(tmp_path / "sweep_10mm_5N.truth.npz")
    assert len(recording) == 12
    assert truth.sweep_position_mm[0] == 10.0 and truth.sweep_position_mm[-1] > 19.0  # 12 mm less the latency's 2.2
    assert recording.force is not None and abs(np.median(recording.force) - 5.0) < 0.5
    assert np.allclose(truth.acquisition_time_s, recording.timestamps - 0.04)


def test_effects_parse_and_bad_ones_are_named(tmp_path: Path, capsys) -> None:
    effects = parse_effects(
        [
            "viscoelasticity:g=0.2,tau_s=0.5",
            "viscoelasticity:g=0.1,tau_s=20",
            "layer:thickness_mm=2,shear_modulus_kpa=80",
            "layer:thickness_mm=5,shear_modulus_kpa=3",
            "tilt:tilt_deg=4,surface_inclination_deg=2,travel_along_axis=1",
            "convex-face:radius_mm=60",
            "sliding",
        ]
    )
    assert effects.viscoelasticity.prony == ((0.2, 0.5), (0.1, 20.0))
    assert [layer.thickness_mm for layer in effects.layers.layers] == [2.0, 5.0]
    assert effects.tilt.tilt_deg == 4.0 and effects.tilt.relative_deg == 6.0 and effects.tilt.travel_along_axis == 1.0
    assert effects.face.radius_mm == 60.0 and effects.sliding.enabled
    for text, message in (
        ("wobble:x=1", "unknown effect 'wobble'"),
        ("tilt:angle=3", "parameter of tilt"),
        ("tilt:tilt_deg=three", "expected a number"),
        ("tilt", "give at least one"),
        ("tilt:travel_along_axis=2", "travel_along_axis"),
        ("convex-face:radius_mm=0", "radius_mm"),
        ("viscoelasticity:tau_s=1.5", "needs g"),
        ("latency:image_delay_s=0.1,image_delay_s=0.2", "given twice"),
    ):
        with pytest.raises(InputError, match=message):
            parse_effects([text])
    with pytest.raises(InputError, match="given twice"):
        parse_effects(["tilt:tilt_deg=1", "tilt:tilt_deg=2"])
    code = main(["simulate", "palpation", "--output", str(tmp_path), *SMALL, "--effect", "tilt:angle=3"])
    assert code == 2 and "tilt:angle=3" in capsys.readouterr().err
    assert not list(tmp_path.glob("*.seq.nrrd"))


def test_ground_truth_files_round_trip_and_bad_ones_are_refused(tmp_path: Path, small_palpation) -> None:
    _, truth = small_palpation
    write_ground_truth(tmp_path / "t.truth.npz", truth)
    loaded = read_ground_truth(tmp_path / "t.truth.npz")
    assert isinstance(loaded, GroundTruth)
    for name in ("zero_force_frames", "vessel_mask", "displacement_px", "force_n", "acquisition_time_s"):
        assert np.array_equal(getattr(loaded, name), getattr(truth, name), equal_nan=name == "displacement_px")
    # a file written before the probe's tilt and face height were recorded: untilted frames of a flat face
    older = {name: getattr(truth, name) for name in _TRUTH_FIELDS if name not in ("probe_tilt_deg", "face_height_mm")}
    np.savez(tmp_path / "older.truth.npz", **older)
    old = read_ground_truth(tmp_path / "older.truth.npz")
    assert np.array_equal(old.probe_tilt_deg, np.zeros(len(truth.force_n)))
    assert np.array_equal(old.face_height_mm, np.zeros(len(truth.force_n)))
    np.savez(tmp_path / "other.npz", frames=np.zeros(3))
    with pytest.raises(FileFormatError, match="missing"):
        read_ground_truth(tmp_path / "other.npz")
    (tmp_path / "junk.npz").write_bytes(b"not an archive")
    with pytest.raises(FileFormatError, match="not a ground-truth file"):
        read_ground_truth(tmp_path / "junk.npz")
