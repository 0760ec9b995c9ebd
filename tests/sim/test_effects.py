"""Each simulator effect changes a recording the way it should, and changes nothing at zero."""

from __future__ import annotations

import itertools

import cv2
import numpy as np
import pytest
from test_recordings import SPARSE_SPECKLE

from usdeform.errors import InputError
from usdeform.sim.effects import (
    ConvexProbeFace,
    Effects,
    ForceSensorError,
    ImageLatency,
    LayeredTissue,
    LumenPressure,
    OutOfPlaneMotion,
    ProbeTilt,
    SlidingContact,
    SoundSpeedMismatch,
    Viscoelasticity,
)
from usdeform.sim.mechanics import Layer
from usdeform.sim.phantoms import coarse_phantom
from usdeform.sim.recordings import simulate_palpation

ROWS = COLS = 96
PIXEL_MM = (37.5 / COLS, 40.0 / ROWS)


def palpate(effects=None, ramp="up-down", acoustics=SPARSE_SPECKLE, n_frames=12, hold_s=0.0):
    """An up-down palpation to 6 N at sweep position 20 mm (2.4 s, 12 frames of 96 x 96; ``hold_s`` at the top
    with ramp "up-hold-down")."""
    return simulate_palpation(
        PHANTOM,
        20.0,
        6.0,
        n_frames=n_frames,
        ramp=ramp,
        seed=7,
        effects=effects,
        rows=ROWS,
        cols=COLS,
        acoustics=acoustics,
        hold_s=hold_s,
    )


PHANTOM = coarse_phantom()


@pytest.fixture(scope="module")
def baseline():
    return palpate()


def _centroid_col_row(mask: np.ndarray) -> np.ndarray:
    return np.argwhere(mask).mean(axis=0)[::-1]


def _assert_lumen_is_dark(frames: np.ndarray, masks: np.ndarray) -> None:
    for frame, mask in zip(frames, masks, strict=False):
        inner = cv2.erode(mask.astype(np.uint8), np.ones((5, 5), np.uint8)).astype(bool)
        assert (frame[inner] < 40).mean() > 0.95


def test_every_effect_at_zero_leaves_the_recording_bit_identical(baseline):
    zero = [
        ImageLatency(0.0, 0.0, 0.0),
        ForceSensorError(0.0, 0.0, 0.0, 0.0),
        Viscoelasticity(()),
        SoundSpeedMismatch(0.0),
        ProbeTilt(0.0, 0.0, 0.0),
        ConvexProbeFace(float("inf")),
        OutOfPlaneMotion(0.0, 0.0, 0.0),
        LayeredTissue(()),
        SlidingContact(False),
        LumenPressure(0.0),
    ]
    recording, truth = palpate(zero)
    expected, expected_truth = baseline
    for name in ("frames", "timestamps", "probe_to_base", "force", "probe_displacement", "image_to_probe"):
        assert np.array_equal(getattr(recording, name), getattr(expected, name)), name
    for name in ("zero_force_frames", "vessel_mask", "zero_force_vessel_mask", "force_n", "probe_displacement_mm"):
        assert np.array_equal(getattr(truth, name), getattr(expected_truth, name)), name
    assert np.array_equal(truth.displacement_px, expected_truth.displacement_px, equal_nan=True)
    assert recording.metadata == {}


def test_image_latency_shows_an_earlier_tissue_state(baseline):
    delay = 0.1
    recording, truth = palpate([ImageLatency(delay)])
    np.testing.assert_allclose(truth.acquisition_time_s, recording.timestamps - delay)
    np.testing.assert_array_equal(recording.force, baseline[0].force)  # force and pose streams are unchanged
    loading = slice(2, 5)  # frames at 0.4-0.9 s, lambda rising steadily
    lag_mm = recording.probe_displacement[loading] - truth.probe_displacement_mm[loading]
    lambda_rate = np.gradient(recording.probe_displacement, recording.timestamps)[loading]
    np.testing.assert_allclose(lag_mm, lambda_rate * delay, rtol=0.25)
    # The image lags: its lumen is less squashed than the undelayed frame at the same timestamp.
    assert np.all(truth.vessel_mask[loading].sum(axis=(1, 2)) > baseline[1].vessel_mask[loading].sum(axis=(1, 2)))


@pytest.mark.parametrize(
    "sensor, expected_offset",
    [
        (ForceSensorError(bias_n=0.5), lambda t: 0.5 + 0 * t),
        (ForceSensorError(drift_n_per_s=0.3), lambda t: 0.3 * t),
        (ForceSensorError(uncompensated_weight_n=3.0), lambda t: -3.0 + 0 * t),
    ],
)
def test_force_sensor_errors_offset_the_measured_force(sensor, expected_offset):
    recording, truth = palpate([sensor], ramp="up", n_frames=6)
    offset = recording.force - truth.force_n  # measured minus true, at the image timestamps
    np.testing.assert_allclose(offset, expected_offset(recording.timestamps), atol=0.12)


def test_a_force_sensor_gain_error_grows_with_the_force():
    recording, truth = palpate([ForceSensorError(gain_error=0.1)], ramp="up", n_frames=6)
    np.testing.assert_allclose(recording.force - truth.force_n, 0.1 * truth.force_n, atol=0.12)
    assert np.ptp(recording.force - truth.force_n) > 0.3  # an error with load, not an offset


def test_a_gain_error_of_minus_one_or_less_is_refused():
    with pytest.raises(InputError, match="gain_error"):
        ForceSensorError(gain_error=-1.0)


def _loading_minus_unloading(lam_mm: np.ndarray, force_n: np.ndarray) -> np.ndarray:
    """Force on loading minus force on unloading, N, at 30-80 % of the top indentation (a loop is positive)."""
    peak = int(np.argmax(lam_mm))
    lam = np.linspace(0.3, 0.8, 5) * lam_mm[: peak + 1].max()
    up = np.interp(lam, lam_mm[: peak + 1], force_n[: peak + 1])
    down = np.interp(lam, lam_mm[peak:][::-1], force_n[peak:][::-1])
    return up - down


def test_a_delayed_force_stream_draws_a_loop_without_creep(baseline):
    # the recorded force is the sensor's reading 0.15 s before the frame's stamp; images and pose are on time
    recording, truth = palpate([ImageLatency(force_delay_s=0.15)], n_frames=24)
    on_time, on_time_truth = palpate(n_frames=24)
    np.testing.assert_array_equal(recording.probe_displacement, on_time.probe_displacement)
    np.testing.assert_array_equal(recording.frames, on_time.frames)
    rate = np.gradient(on_time.force, on_time.timestamps)
    lagging = (recording.timestamps > 0.3) & (recording.timestamps < 2.1)
    # the residual of the force follows the rate of loading, -delay * dF/dt (but at the turn, where dF/dt jumps)
    residual, expected = (recording.force - on_time.force)[lagging], -0.15 * rate[lagging]
    assert np.corrcoef(residual, expected)[0, 1] > 0.9 and np.median(np.abs(residual - expected)) < 0.15
    # force against displacement: loading below unloading (the force arrives late), where relaxation is above
    assert np.all(_loading_minus_unloading(recording.probe_displacement, recording.force) < -0.3)
    assert np.all(np.abs(_loading_minus_unloading(on_time.probe_displacement, on_time.force)) < 0.3)
    np.testing.assert_array_equal(truth.force_n, on_time_truth.force_n)  # the tissue is not touched


def test_a_delayed_pose_stream_stamps_lambda_late(baseline):
    recording, _ = palpate([ImageLatency(pose_delay_s=0.1)])
    np.testing.assert_array_equal(recording.force, baseline[0].force)
    loading = slice(2, 5)
    rate = np.gradient(baseline[0].probe_displacement, baseline[0].timestamps)[loading]
    lag = baseline[0].probe_displacement[loading] - recording.probe_displacement[loading]
    np.testing.assert_allclose(lag, 0.1 * rate, rtol=0.25)


def test_a_lagging_force_sensor_reads_a_low_pass_of_the_force():
    recording, truth = palpate([ForceSensorError(lag_s=0.2)], n_frames=24)
    error = recording.force - truth.force_n
    peak = int(np.argmax(truth.force_n))
    assert np.mean(error[2:peak]) < -0.2  # loading: the reading trails the rising force
    assert np.mean(error[peak + 2 : -2]) > 0.2  # unloading: it trails the falling force
    with pytest.raises(InputError, match="lag_s"):
        ForceSensorError(lag_s=-0.1)


def test_out_of_plane_drift_decorrelates_frames_in_time_at_constant_indentation():
    # a hold at 6 N: lambda stays, so only a drift in time moves the tissue across the slice
    held = palpate(ramp="up-hold-down", n_frames=30, hold_s=2.0)[0]
    drifting = palpate([OutOfPlaneMotion(drift_mm_per_s=0.5)], ramp="up-hold-down", n_frames=30, hold_s=2.0)[0]

    def hold_correlation(recording):
        force, times = recording.force, recording.timestamps
        hold = np.flatnonzero((force > 0.9 * force.max()) & (times > times[np.argmax(force)] - 1.0))
        a, b = recording.frames[hold[0]][:40], recording.frames[hold[-1]][:40]
        return np.corrcoef(a.ravel(), b.ravel())[0, 1]

    assert hold_correlation(drifting) < hold_correlation(held) - 0.2
    assert OutOfPlaneMotion(0.1, 0.0, 0.2).shift_mm(2.0, 0.0, time_s=3.0) == pytest.approx(0.2 + 0.6)


def test_viscoelastic_tissue_unloads_at_lower_force_and_relaxes():
    _recording, truth = palpate([Viscoelasticity(((0.3, 1.0),))], n_frames=24)
    _elastic_recording, elastic_truth = palpate(n_frames=24)

    def loading_minus_unloading(truth):
        peak = int(np.argmax(truth.probe_displacement_mm))
        lam_up, force_up = truth.probe_displacement_mm[: peak + 1], truth.force_n[: peak + 1]
        lam_down, force_down = truth.probe_displacement_mm[peak:][::-1], truth.force_n[peak:][::-1]
        lam = np.linspace(0.3, 0.8, 5) * lam_up.max()
        return np.interp(lam, lam_up, force_up) - np.interp(lam, lam_down, force_down)

    assert np.all(loading_minus_unloading(truth) > 0.5)
    assert np.all(np.abs(loading_minus_unloading(elastic_truth)) < 0.3)
    # Under force control the creeping tissue lets the probe sink deeper than the elastic tissue.
    assert truth.probe_displacement_mm.max() > elastic_truth.probe_displacement_mm.max() + 0.1
    # At constant lambda the force relaxes to (1 - sum g) of the elastic force, with time constant tau.
    relaxation = Effects(viscoelasticity=Viscoelasticity(((0.3, 1.0),))).relaxation(0.001)
    relaxation.step(10.0)
    held = [relaxation.step(10.0) for _ in range(5000)]
    assert held[0] == pytest.approx(10.0, abs=0.01)
    assert held[999] == pytest.approx(7.0 + 3.0 * np.exp(-1.0), abs=0.01)
    assert held[-1] == pytest.approx(7.0, abs=0.03)


def test_sound_speed_mismatch_scales_depths(baseline):
    recording, truth = palpate([SoundSpeedMismatch(60.0)])
    scale = 1540.0 / 1600.0
    for index in (0, 5):
        row = _centroid_col_row(truth.vessel_mask[index])[1]
        base_row = _centroid_col_row(baseline[1].vessel_mask[index])[1]
        assert row == pytest.approx(scale * base_row, rel=0.01)
    _assert_lumen_is_dark(recording.frames, truth.vessel_mask)


def test_probe_tilt_rotates_pose_image_and_force_axis(baseline):
    tilt = 8.0
    recording, truth = palpate([ProbeTilt(tilt)])
    probe_axis = recording.probe_to_base[0, :3, 2]
    assert np.degrees(np.arccos(-probe_axis[2])) == pytest.approx(tilt)
    np.testing.assert_allclose(
        recording.probe_to_base[:, :3, 1], np.broadcast_to([0.0, -1.0, 0.0], (12, 3)), atol=1e-12
    )
    # The face touches first with its lower edge: its centre is then half the face's width times tan(tilt) above
    # the surface, and the vessel (18 mm deep, under the probe centre) appears (18 + that) sin(tilt) mm to the side.
    face_height = PHANTOM.base_section.probe_width_mm / 2 * np.tan(np.radians(tilt))
    np.testing.assert_allclose(truth.face_height_mm, face_height)
    shift_col = (
        _centroid_col_row(truth.zero_force_vessel_mask[0])[0]
        - _centroid_col_row(baseline[1].zero_force_vessel_mask[0])[0]
    )
    assert shift_col == pytest.approx(-(18.0 + face_height) * np.sin(np.radians(tilt)) / PIXEL_MM[0], abs=0.5)
    _assert_lumen_is_dark(recording.frames, truth.vessel_mask)
    # The controller holds the axial force: the tissue carries 1 / cos(tilt) more normal force and sinks deeper.
    assert truth.probe_displacement_mm.max() > baseline[1].probe_displacement_mm.max()


def test_a_tilted_face_meets_the_surface_progressively(baseline):
    _recording, truth = palpate([ProbeTilt(8.0)])
    base_truth = baseline[1]
    # At the same indentation a tilted face presses less tissue: the force rises more slowly at first.
    early = truth.probe_displacement_mm < 0.5 * truth.probe_displacement_mm.max()
    assert np.all(truth.force_n[early] < np.interp(truth.probe_displacement_mm[early], *_rising(base_truth)) + 1e-9)


def _rising(truth):
    """(lambda, force) of the loading half of a palpation's ground truth, sorted by lambda."""
    top = int(np.argmax(truth.probe_displacement_mm))
    order = np.argsort(truth.probe_displacement_mm[: top + 1])
    return truth.probe_displacement_mm[: top + 1][order], truth.force_n[: top + 1][order]


def test_a_surface_inclined_under_a_level_probe_images_as_a_tilted_probe_with_a_level_pose():
    tilted, _tilted_truth = palpate([ProbeTilt(tilt_deg=6.0)])
    inclined, _inclined_truth = palpate([ProbeTilt(surface_inclination_deg=6.0)])
    np.testing.assert_array_equal(inclined.frames, tilted.frames)  # the palpation cannot tell them apart
    np.testing.assert_array_equal(inclined.force, tilted.force)
    np.testing.assert_allclose(
        inclined.probe_to_base[:, :3, :3], np.broadcast_to(np.diag([1.0, -1.0, -1.0]), (12, 3, 3)), atol=1e-12
    )
    probe_axis = tilted.probe_to_base[0, :3, 2]
    assert np.degrees(np.arccos(-probe_axis[2])) == pytest.approx(6.0)


def test_a_probe_pressing_along_its_tilted_axis_travels_sideways_and_drags_the_tissue():
    _normal, normal_truth = palpate([ProbeTilt(tilt_deg=6.0)])
    axial, axial_truth = palpate([ProbeTilt(tilt_deg=6.0, travel_along_axis=1.0)])
    travel = axial.probe_to_base[:, :3, 3] - axial.probe_to_base[0, :3, 3]
    depth = axial.probe_displacement - axial.probe_displacement[0]
    # along its own axis: sideways by tan(6 deg) per mm of indentation, in the surface frame (base x = surface x)
    np.testing.assert_allclose(travel[:, 0], np.tan(np.radians(6.0)) * depth, atol=1e-9)
    top = int(np.argmax(axial_truth.probe_displacement_mm))
    lateral = np.nanmedian(
        axial_truth.displacement_px[top, 10:30, 30:66, 0] - normal_truth.displacement_px[top, 10:30, 30:66, 0]
    )
    assert abs(lateral) > 0.5  # pixels: the tissue under the face moves with it, unlike a push along the normal


def test_a_convex_face_meets_the_surface_progressively(baseline):
    _recording, truth = palpate([ConvexProbeFace(radius_mm=50.0)])
    np.testing.assert_allclose(truth.face_height_mm, 0.0, atol=1e-12)  # the arc's apex is the face centre
    early = truth.probe_displacement_mm < 0.5 * truth.probe_displacement_mm.max()
    assert np.all(truth.force_n[early] < np.interp(truth.probe_displacement_mm[early], *_rising(baseline[1])) + 1e-9)
    with pytest.raises(InputError, match="radius_mm"):
        ConvexProbeFace(-5.0)
    with pytest.raises(InputError, match="travel_along_axis"):
        ProbeTilt(5.0, travel_along_axis=2.0)


def test_out_of_plane_motion_decorrelates_consecutive_frames(baseline):
    recording, truth = palpate([OutOfPlaneMotion(jitter_mm=0.4)], acoustics=SPARSE_SPECKLE)

    def consecutive_correlation(frames):
        tissue = (slice(0, 40), slice(None))  # above the vessel
        return np.mean([np.corrcoef(a[tissue].ravel(), b[tissue].ravel())[0, 1] for a, b in itertools.pairwise(frames)])

    assert consecutive_correlation(recording.frames) < consecutive_correlation(baseline[0].frames) - 0.1
    np.testing.assert_array_equal(truth.zero_force_frames[0], baseline[1].zero_force_frames[0])


def test_soft_top_layer_lets_the_probe_sink_deeper(baseline):
    soft_fat = LayeredTissue((Layer(thickness_mm=6.0, shear_modulus_kpa=4.0),))
    _recording, truth = palpate([soft_fat], ramp="up", n_frames=4)
    elastic_lambda = baseline[1].probe_displacement_mm.max()
    assert truth.probe_displacement_mm.max() > elastic_lambda + 0.3


def test_sliding_contact_lets_the_surface_spread_under_the_probe(baseline):
    _recording, truth = palpate([SlidingContact(True)], ramp="up", n_frames=4)
    stick_truth = palpate(ramp="up", n_frames=4)[1]
    sliding_face = truth.displacement_px[-1, 0, :, 0]  # lateral motion of the tissue at the probe face, px
    sticking_face = stick_truth.displacement_px[-1, 0, :, 0]
    assert np.abs(sticking_face).max() < 0.01
    assert sliding_face[: COLS // 4].mean() < -0.2 and sliding_face[-COLS // 4 :].mean() > 0.2  # spreads outward


def test_lumen_pressure_keeps_the_vessel_open(baseline):
    recording, truth = palpate([LumenPressure(3.0)])
    area = truth.vessel_mask.sum(axis=(1, 2))
    base_area = baseline[1].vessel_mask.sum(axis=(1, 2))
    assert truth.zero_force_vessel_mask[0].sum() > baseline[1].zero_force_vessel_mask[0].sum()
    peak = int(np.argmax(baseline[1].force_n))
    assert area[peak] / area[0] > base_area[peak] / base_area[0]
    _assert_lumen_is_dark(recording.frames, truth.vessel_mask)


def test_effects_validate_their_parameters():
    with pytest.raises(InputError, match="prony"):
        Viscoelasticity(((0.7, 1.0), (0.5, 10.0)))
    with pytest.raises(InputError, match="tilt_deg"):
        ProbeTilt(45.0)
    with pytest.raises(InputError, match="jitter_mm"):
        OutOfPlaneMotion(jitter_mm=-1.0)
    with pytest.raises(InputError, match="given twice"):
        Effects.of([ImageLatency(0.1), ImageLatency(0.2)])
    with pytest.raises(InputError, match="effects"):
        Effects.of(["latency"])


def test_the_command_line_takes_the_new_effect_forms():
    from usdeform.sim.command import parse_effects

    effects = parse_effects(
        ["latency:force_delay_s=0.15,pose_delay_s=0.02", "force-sensor:lag_s=0.1", "out-of-plane:drift_mm_per_s=0.2"]
    )
    assert (effects.latency.image_delay_s, effects.latency.force_delay_s, effects.latency.pose_delay_s) == (
        0,
        0.15,
        0.02,
    )
    assert effects.force_sensor.lag_s == 0.1 and effects.out_of_plane.drift_mm_per_s == 0.2
