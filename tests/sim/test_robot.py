"""The nuisances of a robot's sweep in the simulator: force tracking, image delay, probe jitter, a tilting
path, laterally varying stiffness (a small, coarse phantom and small frames: seconds each)."""

from __future__ import annotations

import numpy as np
import pytest

from usdeform.errors import InputError
from usdeform.sim import (
    ForceController,
    ImageLatency,
    OutOfPlaneMotion,
    SectionSpec,
    SweepPath,
    coarse_phantom,
    simulate_palpation,
    simulate_sweep,
    solve_section,
    truth_image_to_base,
)
from usdeform.sim.imaging import TissueAcoustics
from usdeform.sim.recordings import DEFAULT_SURFACE_TO_BASE

SPARSE_SPECKLE = TissueAcoustics(scatterer_density_per_mm3=6.0)
TARGET_N = 6.0


def sweep(frames: int = 12, **options):
    """A sweep of 6 mm at 6 N, every third frame of 50 fps (0.06 s apart, 8.3 mm/s at 12 frames)."""
    options = {"n_frames": frames, "seed": 3, "rows": 48, "cols": 48, "acoustics": SPARSE_SPECKLE} | options
    return simulate_sweep(coarse_phantom(), 30.0, 6.0, TARGET_N, frame_step=3, **options)


def test_force_controller_holds_the_target_within_its_band() -> None:
    # 40 frames: 2.3 s, most of a period of the 0.3 Hz oscillation. Run: +/-0.2 N without, 1.2 N with.
    controller = ForceController(oscillation_n=0.8, tracking_ripple_n=0.25)
    _, steady = sweep(40)
    _, held = sweep(40, controller=controller)
    steady_error, held_error = np.abs(steady.force_n - TARGET_N), np.abs(held.force_n - TARGET_N)
    assert steady_error.max() < 0.4
    assert 0.5 <= held_error.max() <= 1.5, held_error.max()
    assert np.mean(held.force_n > TARGET_N) > 0.2 and np.mean(held.force_n < TARGET_N) > 0.2  # both sides


def test_default_controller_draws_nothing_for_the_tracking_error() -> None:
    error = ForceController().tracking_error_n(np.random.default_rng(0), np.arange(10) / 1000, 1000.0)
    np.testing.assert_array_equal(error, 0.0)
    with pytest.raises(InputError, match="oscillation_n"):
        ForceController(oscillation_n=-1.0)


def test_image_delay_shows_the_tissue_where_the_probe_was_earlier() -> None:
    recording, truth = sweep(effects=[ImageLatency(0.1)])
    np.testing.assert_allclose(recording.timestamps - truth.acquisition_time_s, 0.1)
    recorded_position = recording.probe_to_base[:, 1, 3] - DEFAULT_SURFACE_TO_BASE[1, 3]
    speed = 6.0 / (recording.timestamps[-1] - recording.timestamps[0])
    # After the first 0.1 s the frames lag their poses by speed * delay along the path (0.83 mm).
    moving = truth.acquisition_time_s > recording.timestamps[0]
    np.testing.assert_allclose((recorded_position - truth.sweep_position_mm)[moving], speed * 0.1, atol=0.02)


def test_out_of_plane_jitter_changes_the_frames_not_the_poses() -> None:
    still, _ = sweep(4)
    jittered, truth = sweep(4, effects=[OutOfPlaneMotion(jitter_mm=0.3)])
    np.testing.assert_array_equal(jittered.probe_to_base, still.probe_to_base)  # the robot does not see it
    differs = [not np.array_equal(a, b) for a, b in zip(jittered.frames, still.frames, strict=True)]
    assert all(differs)
    np.testing.assert_array_equal(truth.zero_force_frames, sweep(4)[1].zero_force_frames)  # the truth is unmoved


def test_path_tilts_the_probe_about_its_elevation_axis() -> None:
    recording, truth = sweep(path=SweepPath(15.0))
    assert truth.probe_tilt_deg.max() == pytest.approx(15.0, abs=0.3)
    assert abs(truth.probe_tilt_deg[0]) < 0.5 and abs(truth.probe_tilt_deg[-1]) < 0.5
    # The recorded image x axis turns about the elevation (base y) axis by the tilt; y stays put.
    image_x = recording.probe_to_base[:, :3, 0]
    angle = np.degrees(np.arctan2(image_x[:, 2], image_x[:, 0]))
    np.testing.assert_allclose(angle, truth.probe_tilt_deg, atol=0.3)
    np.testing.assert_allclose(recording.probe_to_base[:, :3, 1], np.broadcast_to([0.0, -1.0, 0.0], (12, 3)))
    # The zero-force poses carry the tilt too.
    truth_x = truth_image_to_base(truth, recording)[:, :3, 0]
    np.testing.assert_allclose(np.degrees(np.arctan2(truth_x[:, 2], truth_x[:, 0])), truth.probe_tilt_deg, atol=1e-9)
    with pytest.raises(InputError, match="max_tilt_deg"):
        SweepPath(45.0)


def test_lateral_stiffness_gradient_makes_the_indentation_asymmetric() -> None:
    uniform = coarse_phantom().base_section
    graded = SectionSpec(**{**uniform.__dict__, "lateral_stiffness_gradient": 0.3})
    assert graded.cache_key(np.array([0.0, 4.0])) != uniform.cache_key(np.array([0.0, 4.0]))
    np.testing.assert_allclose(graded.lateral_factor(np.array([-50.0, 0.0, 9.375, 50.0])), [0.7, 1.0, 1.15, 1.3])
    points = np.array([[-12.0, 8.0], [12.0, 8.0]])  # beside the vessel, mirrored
    steps = np.array([0.0, 4.0])

    def lateral_displacements(spec: SectionSpec) -> np.ndarray:
        return solve_section(spec, steps).displacement(points, 4.0)[:, 0]

    symmetric, skewed = lateral_displacements(uniform), lateral_displacements(graded)
    assert symmetric[0] == pytest.approx(-symmetric[1], abs=1e-3)
    # The softer left side bulges out more than the stiffer right side.
    assert abs(skewed[0]) - abs(skewed[1]) > 0.02, skewed
    with pytest.raises(InputError, match="lateral_stiffness_gradient"):
        SectionSpec(lateral_stiffness_gradient=1.0)


def test_a_curved_surface_turns_the_probe_about_its_lateral_axis_and_bends_the_tissue() -> None:
    radius = 60.0
    path = SweepPath(surface_radius_mm=radius)
    bend = path.surface_bend(40.0, 30.0)
    depth = 12.0
    point = bend @ np.array([3.0, 40.0, -depth, 1.0])  # 12 mm under the surface at s = 40 mm
    assert np.hypot(point[1] - 30.0, point[2] + radius) == pytest.approx(radius - depth)
    assert point[0] == 3.0
    assert np.degrees(np.arccos(bend[2, 2])) == pytest.approx(np.degrees(10.0 / radius))
    assert np.array_equal(SweepPath().surface_bend(40.0, 30.0), np.eye(4))
    recording, truth = sweep(4, path=path)
    axes = recording.probe_to_base[:, :3, 2]  # the probe axis in the base, one per frame
    turned = np.degrees(np.arccos(np.clip(axes[0] @ axes[-1], -1.0, 1.0)))
    covered = truth.sweep_position_mm[-1] - truth.sweep_position_mm[0]
    assert turned == pytest.approx(np.degrees(covered / radius), abs=0.05)
    # The zero-force poses are the pressed-in ones moved back along each frame's own axis by its lambda.
    pulled = recording.probe_to_base.copy()
    pulled[:, :3, 3] -= axes * recording.probe_displacement[:, None]
    truth_poses = truth_image_to_base(truth, recording) @ np.linalg.inv(recording.image_to_probe)
    assert np.abs(truth_poses[:, :3, 3] - pulled[:, :3, 3]).max() < 0.05
    with pytest.raises(InputError, match="surface_radius_mm"):
        SweepPath(surface_radius_mm=5.0)


def test_a_palpation_on_a_curved_surface_presses_along_the_local_normal() -> None:
    bend = SweepPath(surface_radius_mm=50.0).surface_bend(40.0, 30.0)
    options = {"n_frames": 3, "seed": 1, "rows": 32, "cols": 32, "acoustics": SPARSE_SPECKLE}
    flat, _ = simulate_palpation(coarse_phantom(), 40.0, 4.0, **options)
    curved, _ = simulate_palpation(coarse_phantom(), 40.0, 4.0, surface_bend=bend, **options)
    expected = DEFAULT_SURFACE_TO_BASE @ bend @ np.linalg.inv(DEFAULT_SURFACE_TO_BASE) @ flat.probe_to_base
    assert np.allclose(curved.probe_to_base, expected)
    assert np.array_equal(curved.frames, flat.frames)
    with pytest.raises(InputError, match="surface_bend"):
        simulate_palpation(coarse_phantom(), 40.0, 4.0, surface_bend=np.eye(3), **options)
