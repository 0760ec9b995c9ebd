"""Each simulator effect changes a recording the way it should, and changes nothing at zero."""

from __future__ import annotations

import itertools

import cv2
import numpy as np
import pytest
from test_recordings import SPARSE_SPECKLE

from usdeform.errors import InputError
from usdeform.sim.effects import (
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


def palpate(effects=None, ramp="up-down", acoustics=SPARSE_SPECKLE, n_frames=12):
    """An up-down palpation to 6 N at sweep position 20 mm (2.4 s, 12 frames of 96 x 96)."""
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
        ImageLatency(0.0),
        ForceSensorError(0.0, 0.0, 0.0),
        Viscoelasticity(()),
        SoundSpeedMismatch(0.0),
        ProbeTilt(0.0),
        OutOfPlaneMotion(0.0, 0.0),
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
    # The vessel (18 mm deep, under the probe centre) appears 18 sin(tilt) mm to the side.
    shift_col = (
        _centroid_col_row(truth.zero_force_vessel_mask[0])[0]
        - _centroid_col_row(baseline[1].zero_force_vessel_mask[0])[0]
    )
    assert shift_col == pytest.approx(-18.0 * np.sin(np.radians(tilt)) / PIXEL_MM[0], abs=0.5)
    _assert_lumen_is_dark(recording.frames, truth.vessel_mask)
    # The controller holds the axial force: the tissue carries 1 / cos(tilt) more normal force and sinks deeper.
    assert truth.probe_displacement_mm.max() > baseline[1].probe_displacement_mm.max()


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
