"""Reconstruction stages: correct-then-compound in one call equals the two steps; frame-shape checks."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest

from kernel_inputs import random_model
from usdeform._arrays import interpolate_in_time
from usdeform.correction import (
    STIFFNESS_SOURCE_FIELD,
    SampledProfiles,
    correct_recording,
    stiffness_source_for,
    sweep_profiles,
)
from usdeform.correction._sweep import correct_and_compound
from usdeform.errors import InputError
from usdeform.recording import Recording
from usdeform.regression import StiffnessProfile
from usdeform.volume import compound_recording, finish_volume

ROWS, COLS, N_FRAMES = 24, 20, 9


def sweep(rng: np.random.Generator, rows: int = ROWS, cols: int = COLS) -> Recording:
    probe_to_base = np.stack([np.eye(4)] * N_FRAMES)
    probe_to_base[:, 1, 3] = np.linspace(0.0, 8.0, N_FRAMES)  # the probe slides along y
    pose_valid = np.ones(N_FRAMES, bool)
    pose_valid[[2, 5]] = False  # tracking dropped out
    return Recording(
        frames=rng.integers(0, 256, (N_FRAMES, rows, cols), dtype=np.uint8),
        timestamps=np.arange(N_FRAMES) * 0.1,
        probe_to_base=probe_to_base,
        pose_valid=pose_valid,
        image_to_probe=np.diag([0.3, 0.3, 1.0, 1.0]),
        force=rng.uniform(1.0, 6.0, N_FRAMES),
    )


SAMPLED = SampledProfiles(
    np.array([[0.0, 0.0, 0.0], [0.0, 8.0, 0.0]]), (StiffnessProfile(0.1, 2.0, 0.0), StiffnessProfile(0.0, 4.0, 0.0))
)


def test_correct_and_compound_equals_the_two_steps() -> None:
    """The fused call equals correcting, then compounding (the corrected recording carries the mask of
    pixels holding data); without the mask the pixels sampled from outside the frames count as data."""
    rng = np.random.default_rng(3)
    recording, model = sweep(rng), random_model(rng, ROWS, COLS)
    fused = correct_and_compound(recording, model, SAMPLED, spacing_mm=0.4)
    corrected = correct_recording(recording, model, SAMPLED)
    valid = corrected.pixel_valid
    assert valid is not None and valid.shape == recording.frames.shape and 0 < valid.mean() < 1
    np.testing.assert_array_equal(corrected.frames[~valid], 0)
    two_steps, n_compounded = compound_recording(corrected, spacing_mm=0.4)
    assert n_compounded == N_FRAMES - 2
    assert fused.grid.shape == two_steps.grid.shape
    np.testing.assert_array_equal(fused.weight, two_steps.weight)
    np.testing.assert_allclose(fused.image, two_steps.image, atol=1e-4)
    unmasked, _ = compound_recording(dataclasses.replace(corrected, pixel_valid=None), spacing_mm=0.4)
    assert fused.weight is not None and unmasked.weight is not None
    assert unmasked.weight.sum() > fused.weight.sum()


def test_corrected_recording_marks_pixels_sampled_from_outside_and_keeps_the_marks_on_select() -> None:
    rng = np.random.default_rng(4)
    recording, model = sweep(rng), random_model(rng, ROWS, COLS)
    corrected = correct_recording(recording, model, SAMPLED)
    assert corrected.pixel_valid is not None and corrected.pixel_valid.shape == corrected.frames.shape
    assert not corrected.pixel_valid.all() and corrected.pixel_valid.any()
    picked = corrected.select([0, 2])
    assert picked.pixel_valid is not None
    np.testing.assert_array_equal(picked.pixel_valid, corrected.pixel_valid[[0, 2]])
    with pytest.raises(InputError, match="pixel_valid"):
        Recording(
            frames=recording.frames,
            timestamps=recording.timestamps,
            probe_to_base=recording.probe_to_base,
            pose_valid=recording.pose_valid,
            image_to_probe=recording.image_to_probe,
            pixel_valid=np.ones((1, ROWS, COLS), bool),
        )


def test_frames_without_a_pose_take_the_position_interpolated_in_time() -> None:
    profiles = sweep_profiles(sweep(np.random.default_rng(0)), SAMPLED)
    positions = interpolate_in_time(
        np.arange(N_FRAMES) * 0.1, np.arange(N_FRAMES) * 0.1, np.linspace(0, 8, N_FRAMES)[:, np.newaxis]
    )
    assert profiles.shape == (N_FRAMES, 3)
    np.testing.assert_allclose(profiles[0], SAMPLED.profiles[0].as_tuple())
    np.testing.assert_allclose(profiles[-1], SAMPLED.profiles[1].as_tuple())
    assert positions[2, 0] == pytest.approx(2.0)


def test_a_sweep_of_another_frame_shape_is_refused() -> None:
    rng = np.random.default_rng(1)
    model = random_model(rng, ROWS, COLS)
    wrong = sweep(rng, rows=ROWS + 4)
    with pytest.raises(InputError, match=f"sweep: frames of {ROWS + 4} x {COLS} pixels, but the model was fitted"):
        correct_recording(wrong, model, SAMPLED)
    with pytest.raises(InputError, match=f"frames: expected frames of the model's frame shape {ROWS} x {COLS}"):
        correct_and_compound(wrong, model, SAMPLED)


# A simulated sweep over a phantom whose stiffness varies along it, with the model fitted on two
# palpations: where the corrected volume puts the vessel against the zero-force truth.


@pytest.fixture(scope="module")
def simulated_sweep():
    from usdeform.fitting import measure_positions
    from usdeform.regression import fit_regression
    from usdeform.sim import coarse_phantom, simulate_palpation, simulate_sweep

    phantom = coarse_phantom()
    palpations = [
        simulate_palpation(phantom, position, 12.0, n_frames=20, seed=number, rows=96, cols=96)[0]
        for number, position in enumerate((10.0, 40.0))
    ]
    measured, sampled = measure_positions(palpations, phantom.base_section.depth_mm)
    model = fit_regression([m.observations for m in measured]).model
    recording, truth = simulate_sweep(phantom, 10.0, 30.0, 12.0, n_frames=40, seed=5, rows=96, cols=96)
    return recording, truth, model, sampled


def test_zero_force_poses_are_the_simulators_unloaded_probe(simulated_sweep) -> None:
    from usdeform.correction import zero_force_probe_to_base
    from usdeform.sim import truth_image_to_base

    recording, truth, _, _ = simulated_sweep
    assert recording.probe_displacement.min() > 4.0  # pressed in: the check below is not trivial
    moved = zero_force_probe_to_base(recording.probe_to_base, recording.probe_displacement)
    np.testing.assert_allclose(moved @ recording.image_to_probe, truth_image_to_base(truth, recording), atol=0.02)


def test_corrected_volume_puts_the_vessel_at_its_zero_force_depth(simulated_sweep) -> None:
    from usdeform.experiments.paper_3d import (
        centre_line_depth_mm,
        lumen_from_masks,
        segment_volume_lumen,
    )
    from usdeform.sim import truth_image_to_base
    from usdeform.volume import compound_frames, grid_for_frames

    recording, truth, model, sampled = simulated_sweep
    truth_poses = truth_image_to_base(truth, recording)
    grid = grid_for_frames(np.concatenate([truth_poses, recording.image_to_base]), recording.shape, 0.4, margin_mm=1.0)
    truth_lumen = lumen_from_masks(truth.zero_force_vessel_mask, truth_poses, grid)
    truth_depth = centre_line_depth_mm(truth_lumen, grid)

    def depth_error(frames: np.ndarray, image_to_base: np.ndarray) -> np.ndarray:
        lumen = segment_volume_lumen(compound_frames(frames, image_to_base, grid), truth_lumen)
        error = centre_line_depth_mm(lumen, grid) - truth_depth
        assert np.isfinite(error).sum() >= 0.9 * np.isfinite(truth_depth).sum()  # the lumen is found
        return error[np.isfinite(error)]

    corrected = correct_recording(recording, model, sampled)
    fused = correct_and_compound(recording, model, sampled, spacing_mm=0.4)
    np.testing.assert_allclose(
        fused.grid.index_to_world, grid_for_frames(corrected.image_to_base, recording.shape, 0.4).index_to_world
    )
    # Run: mean error -0.56 mm, worst 0.81 mm at the zero-force poses; -5.7 mm at the pressed-in poses
    # (the vessel lambda too deep); the zero-force frames themselves measure 0.04 mm.
    at_zero_force = depth_error(corrected.frames, corrected.image_to_base)
    at_pressed_pose = depth_error(corrected.frames, recording.image_to_base)
    assert abs(at_zero_force.mean()) < 1.0 and np.abs(at_zero_force).max() < 1.5, at_zero_force
    assert at_pressed_pose.mean() < -3.0, at_pressed_pose
    np.testing.assert_array_equal(corrected.force, 0.0)
    np.testing.assert_array_equal(corrected.probe_displacement, 0.0)


def test_sweep_stiffness_reproduces_the_recorded_displacement_at_the_recorded_force(simulated_sweep) -> None:
    recording, _, _, sampled = simulated_sweep
    interpolated = sweep_profiles(recording, sampled, stiffness_source="interpolated")
    from_sweep = sweep_profiles(recording, sampled, stiffness_source="sweep")
    lambdas = [StiffnessProfile(*p).lambda_at(f) for p, f in zip(from_sweep, recording.force, strict=True)]
    np.testing.assert_allclose(lambdas, recording.probe_displacement, atol=1e-9)
    interpolated_lambdas = [
        StiffnessProfile(*p).lambda_at(f) for p, f in zip(interpolated, recording.force, strict=True)
    ]
    assert np.abs(np.array(interpolated_lambdas) - recording.probe_displacement).max() > 0.01
    # Same profile shape, scaled:
    np.testing.assert_allclose(from_sweep / from_sweep[:, 1:2], interpolated / interpolated[:, 1:2], atol=1e-12)


def test_sweep_stiffness_needs_force_and_displacement() -> None:
    recording = sweep(np.random.default_rng(2))  # no ProbeDisplacement
    with pytest.raises(InputError, match="stiffness_source='sweep' needs each frame's ContactForce and Probe"):
        sweep_profiles(recording, SAMPLED, stiffness_source="sweep")
    with pytest.raises(InputError, match="stiffness_source: expected one of 'auto', 'interpolated', 'sweep'"):
        sweep_profiles(recording, SAMPLED, stiffness_source="nearest")  # type: ignore[arg-type]


def test_auto_stiffness_source_is_the_sweeps_where_every_frame_records_force_and_displacement(
    simulated_sweep,
) -> None:
    recording, truth, model, sampled = simulated_sweep
    without_displacement = dataclasses.replace(recording, probe_displacement=None)
    assert (stiffness_source_for(recording), stiffness_source_for(without_displacement)) == ("sweep", "interpolated")
    assert stiffness_source_for(recording, "interpolated") == "interpolated"
    np.testing.assert_array_equal(
        sweep_profiles(recording, sampled), sweep_profiles(recording, sampled, stiffness_source="sweep")
    )
    np.testing.assert_array_equal(
        sweep_profiles(without_displacement, sampled),
        sweep_profiles(recording, sampled, stiffness_source="interpolated"),
    )
    corrected = {
        source: correct_recording(recording, model, sampled, stiffness_source=source)
        for source in ("auto", "interpolated")
    }
    assert corrected["auto"].metadata[STIFFNESS_SOURCE_FIELD] == "sweep"
    assert corrected["interpolated"].metadata[STIFFNESS_SOURCE_FIELD] == "interpolated"
    assert correct_recording(without_displacement.select(slice(0, 3)), model, sampled).metadata[
        STIFFNESS_SOURCE_FIELD
    ] == ("interpolated")
    # The phantom's stiffness varies along the sweep: auto (the sweep's) is no worse than interpolated.
    # Run: mean Dice against the zero-force lumen 0.885 auto, 0.882 interpolated (0.708 uncorrected).
    mean_dice = {source: np.mean(frame_dice(c.frames, truth)) for source, c in corrected.items()}
    assert mean_dice["auto"] >= mean_dice["interpolated"] - 1e-3, mean_dice


def frame_dice(frames: np.ndarray, truth) -> list[float]:
    """Dice of each frame's segmented lumen against its zero-force frame's, as paper-3d measures it."""
    from usdeform.metrics import dice, segment_vessel

    scores = []
    for frame, zero_force in zip(frames, truth.zero_force_frames, strict=True):
        reference = segment_vessel(zero_force).mask
        row, col = np.argwhere(reference).mean(axis=0)
        try:
            mask = segment_vessel(frame, seed_px=(float(col), float(row))).mask
        except InputError:
            mask = np.zeros_like(reference)
        scores.append(dice(mask, reference) if mask.any() else 0.0)
    return scores


def test_correct_command_says_which_stiffness_source_it_used(tmp_path: Path, capsys) -> None:
    from usdeform.cli import main
    from usdeform.io import read_sequence, save_model, write_sequence

    rng = np.random.default_rng(5)
    recording, model = sweep(rng), random_model(rng, ROWS, COLS)
    save_model(tmp_path / "model.json", model, SAMPLED)
    with_displacement = dataclasses.replace(recording, probe_displacement=rng.uniform(0.5, 2.0, N_FRAMES))
    for name, sweep_recording, options, used in (
        ("auto-interpolated", recording, [], "interpolated (auto: the sweep does not record ProbeDisplacement)"),
        ("auto-sweep", with_displacement, [], "sweep (auto: every frame records ContactForce and ProbeDisplacement)"),
        ("interpolated", with_displacement, ["--stiffness-source", "interpolated"], "interpolated; wrote"),
    ):
        write_sequence(tmp_path / f"{name}.seq.nrrd", sweep_recording)
        output = tmp_path / f"{name}-corrected.seq.nrrd"
        arguments = [
            str(tmp_path / f"{name}.seq.nrrd"),
            "--model",
            str(tmp_path / "model.json"),
            "--output",
            str(output),
        ]
        assert main(["correct", *arguments, *options]) == 0
        assert f"stiffness source {used}" in capsys.readouterr().out
        assert read_sequence(output).metadata[STIFFNESS_SOURCE_FIELD] == used.split()[0].rstrip(";")


def test_without_probe_displacement_the_pose_moves_by_lambda_at_the_recorded_force() -> None:
    rng = np.random.default_rng(4)
    recording, model = sweep(rng), random_model(rng, ROWS, COLS)
    corrected = correct_recording(recording, model, SAMPLED)
    profiles = sweep_profiles(recording, SAMPLED)
    expected = [StiffnessProfile(*p).lambda_at(f) for p, f in zip(profiles, recording.force, strict=True)]
    # The probe axis is base +z here: the pose moves up (-z) by lambda.
    np.testing.assert_allclose(recording.probe_to_base[:, 2, 3] - corrected.probe_to_base[:, 2, 3], expected)


# Hole filling after compounding, from a PLUS configuration or given.


def test_reconstruction_fills_holes_as_the_plus_configuration_says(plus_data: Path) -> None:
    from usdeform.io import read_plus_config, read_sequence
    from usdeform.volume import HoleFillingElement

    config = read_plus_config(plus_data / "PlusDeviceSet_SpinePhantomFreehandReconstructionOnly.xml")
    settings = config.reconstruction
    assert settings is not None and settings.fill_holes
    recording = read_sequence(plus_data / "SpinePhantomFreehand.igs.mha", config=config).select(slice(0, 40))
    unfilled, _ = compound_recording(recording, settings=settings, spacing_mm=1.0, hole_filling=())
    filled, n_frames = compound_recording(recording, settings=settings, spacing_mm=1.0, voxel_type="uint8")
    assert n_frames == int(recording.pose_valid.sum())
    holes = unfilled.weight < 1.0 / 256
    assert holes.any() and filled.image.dtype == np.uint8
    np.testing.assert_array_equal(filled.image, finish_volume(unfilled, settings, voxel_type="uint8").image)
    assert np.count_nonzero(filled.image[holes]) > 100  # run: 518 holes between the frames take a value
    np.testing.assert_array_equal(filled.image[~holes], np.clip(np.floor(unfilled.image[~holes] + 0.5), 0, 255))
    stick = HoleFillingElement("stick", stick_length_limit=3)
    unconfigured = dataclasses.replace(settings, fill_holes=False)  # the same grid, holes filled only as given
    given, _ = compound_recording(recording, settings=unconfigured, spacing_mm=1.0, hole_filling=[stick])
    assert np.count_nonzero(given.image[holes]) > 0


def test_reconstruction_pastes_only_the_configurations_fan(plus_data: Path) -> None:
    """With a fan-shaped configuration (the TRUS one), pixels outside the fan reach no voxel: frames
    bright outside the fan and dark inside compound to a dark volume."""
    from usdeform.io import read_plus_config, read_sequence

    config = read_plus_config(plus_data / "PlusDeviceSet_VolumeReconstructionOnly_SonixRP_TRUS_D70mm_NN_LATE.xml")
    settings = config.reconstruction
    assert settings is not None and settings.fan_angles_deg is not None
    recording = read_sequence(plus_data / "SpinePhantomFreehand.igs.mha", config=config).select(slice(0, 6))
    fan = settings.pixel_mask(*recording.shape)
    frames = np.where(fan, 0, 255).astype(np.uint8)[np.newaxis].repeat(len(recording), axis=0)
    outside = dataclasses.replace(recording, frames=frames)
    volume, _ = compound_recording(outside, settings=settings, spacing_mm=1.0, hole_filling=())
    assert volume.weight is not None and volume.weight.sum() > 1000
    assert volume.image.max() == 0
    rectangle_only = dataclasses.replace(settings, fan_angles_deg=None)
    clipped, _ = compound_recording(outside, settings=rectangle_only, spacing_mm=1.0, hole_filling=())
    assert clipped.image.max() > 0  # the clip rectangle alone keeps pixels outside the fan
    valid = np.ones(frames.shape, bool)
    valid[:, :, : recording.shape[1] // 2] = False  # and the recording's pixel mask is combined with the fan
    half, _ = compound_recording(
        dataclasses.replace(outside, pixel_valid=valid), settings=settings, spacing_mm=1.0, hole_filling=()
    )
    assert half.weight is not None and 0 < half.weight.sum() < volume.weight.sum()


def test_reconstruct_command_fills_holes_from_the_configuration_or_the_flag(plus_data: Path, tmp_path: Path) -> None:
    from usdeform.cli import main
    from usdeform.io import read_volume

    sweep_path = plus_data / "SpinePhantomFreehand.igs.mha"
    config = plus_data / "PlusDeviceSet_SpinePhantomFreehandReconstructionOnly.xml"
    common = [str(sweep_path), "--config", str(config), "--voxel-type", "uint8"]
    for name, extra in (("configured", []), ("off", ["--fill-holes", "off"])):
        assert main(["reconstruct", *common, "--output", str(tmp_path / f"{name}.nrrd"), *extra]) == 0
    configured, off = read_volume(tmp_path / "configured.nrrd"), read_volume(tmp_path / "off.nrrd")
    assert configured.image.dtype == np.uint8 and off.image.dtype == np.uint8
    # run: 471395 non-zero voxels filled against 361442 unfilled
    assert np.count_nonzero(configured.image) > 1.05 * np.count_nonzero(off.image)  # the holes got values


def test_the_volume_reconstructor_in_batches_equals_compound_recording() -> None:
    """Configure, add frames in two batches, update, get: the volume compound_recording makes in one call, hole
    filling and voxel type included; frames added after an update are in the next volume."""
    from usdeform.volume import HoleFillingElement, VolumeReconstructor, output_grid

    recording = sweep(np.random.default_rng(7))
    steps = (HoleFillingElement("gaussian"),)
    whole, n_frames = compound_recording(recording, spacing_mm=0.6, hole_filling=steps, voxel_type="uint8")
    posed = recording.posed_indices()  # compound_recording leaves out the frames without a pose
    frames, image_to_base = recording.frames[posed], recording.image_to_base[posed]
    reconstructor = VolumeReconstructor(
        output_grid(image_to_base, recording.shape, spacing_mm=0.6), hole_filling=steps, voxel_type="uint8"
    )
    reconstructor.add_frames(frames[:4], image_to_base[:4])
    first = reconstructor.update()
    reconstructor.add_frames(frames[4:], image_to_base[4:])
    assert n_frames == len(posed) == N_FRAMES - 2
    assert reconstructor.volume() is not first
    np.testing.assert_array_equal(reconstructor.volume().image, whole.image)
    np.testing.assert_array_equal(reconstructor.volume().weight, whole.weight)
    assert reconstructor.volume() is reconstructor.volume()
