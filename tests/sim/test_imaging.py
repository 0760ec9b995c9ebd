"""B-mode image formation: determinism, lumen masks, speckle that optical flow can track, true displacement.

These tests use a known smooth analytic compression field in place of the finite-element
mechanics, so that every expected value follows from a formula.
"""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from usdeform.errors import InputError
from usdeform.sim.imaging import (
    GriddedSolution,
    ImagingSettings,
    ProbeState,
    ScattererField,
    TissueAcoustics,
    render_frame,
    scatterer_jitter_mm,
    section_to_surface,
    surface_to_image,
    true_displacement_px,
    unit_complex_noise,
    vessel_mask,
)
from usdeform.sim.mechanics import SectionSpec
from usdeform.sim.tracking_cases import peak_patch_correlation

SECTION = SectionSpec(vessel_center_x_mm=2.0, vessel_depth_mm=18.0, vessel_radius_mm=5.0)


class AnalyticCompression:
    """Uniform axial compression of the section over its depth H plus a smooth lateral bulge:
    u_z = lambda (1 - z/H), u_x = 0.6 lambda x z (H - z) / H^3 (mm)."""

    probe_displacement_mm = np.linspace(0.0, 10.0, 6)  # "solved steps": the field is linear in lambda

    def __init__(self, section: SectionSpec):
        self.section = section

    def displacement(self, points_mm: np.ndarray, probe_displacement_mm: float) -> np.ndarray:
        x, z, depth = points_mm[:, 0], points_mm[:, 1], self.section.depth_mm
        lam = probe_displacement_mm
        return np.column_stack([0.6 * lam * x * z * (depth - z) / depth**3, lam * (1 - z / depth)])

    def lumen_boundary(self, probe_displacement_mm: float, n_points: int) -> np.ndarray:
        angles = 2 * np.pi * np.arange(n_points) / n_points
        circle = np.column_stack(
            [
                self.section.vessel_center_x_mm + self.section.vessel_radius_mm * np.cos(angles),
                self.section.vessel_depth_mm + self.section.vessel_radius_mm * np.sin(angles),
            ]
        )
        return circle + self.displacement(circle, probe_displacement_mm)


SOLUTION = AnalyticCompression(SECTION)
ACOUSTICS = TissueAcoustics()


def frame_at(probe_displacement_mm: float, settings: ImagingSettings, seed: int = 3, noise_seed: int = 4) -> np.ndarray:
    probe = ProbeState(0.0, probe_displacement_mm)
    field = ScattererField(seed, settings, ACOUSTICS)
    noise = unit_complex_noise(np.random.default_rng(noise_seed), settings)
    displacement = GriddedSolution(SOLUTION, SECTION, settings).at(probe_displacement_mm)
    return render_frame(field, SECTION, displacement, probe, settings, ACOUSTICS, noise)


def exact_motion_px(points_col_row: np.ndarray, from_mm: float, to_mm: float, settings: ImagingSettings) -> np.ndarray:
    """True motion (m, 2) in pixels of the tissue seen at ``points_col_row`` at lambda ``from_mm``
    when lambda becomes ``to_mm``."""
    lateral_px, axial_px = settings.pixel_size_mm
    seen = np.column_stack(
        [points_col_row[:, 0] * lateral_px - settings.width_mm / 2, points_col_row[:, 1] * axial_px + from_mm]
    )
    reference = seen.copy()
    for _ in range(100):  # fixed point X = x - u(X); the field is a contraction
        reference = seen - SOLUTION.displacement(reference, from_mm)
    moved = reference + SOLUTION.displacement(reference, to_mm)
    col_row, _, _ = surface_to_image(section_to_surface(moved, 0.0), ProbeState(0.0, to_mm), settings, ACOUSTICS)
    return col_row - points_col_row


def test_frames_are_deterministic_for_a_seed():
    settings = ImagingSettings(rows=128, cols=128)
    first, again = frame_at(2.0, settings), frame_at(2.0, settings)
    other_seed = frame_at(2.0, settings, seed=5)
    assert first.dtype == np.uint8 and first.shape == (128, 128)
    assert np.array_equal(first, again)
    assert not np.array_equal(first, other_seed)


def test_lumen_mask_lines_up_with_the_dark_lumen():
    settings = ImagingSettings()
    for lam in (0.0, 4.0):
        frame = frame_at(lam, settings)
        mask = vessel_mask(SOLUTION, ProbeState(0.0, lam), settings, ACOUSTICS)
        # The bright wall's point-spread function bleeds ~2 px into the lumen: look 3 px inside.
        inner = cv2.erode(mask.astype(np.uint8), np.ones((7, 7), np.uint8)).astype(bool)
        outer = ~cv2.dilate(mask.astype(np.uint8), np.ones((15, 15), np.uint8)).astype(bool)
        assert (frame[inner] < 40).mean() > 0.98
        assert np.median(frame[outer]) > 100
        # The largest dark blob (the rendered lumen) is centred on the mask to a fraction of a pixel.
        dark = cv2.morphologyEx((frame < 40).astype(np.uint8), cv2.MORPH_OPEN, np.ones((5, 5), np.uint8))
        _, _, stats, centroids = cv2.connectedComponentsWithStats(dark)
        lumen = 1 + np.argmax(stats[1:, cv2.CC_STAT_AREA])
        np.testing.assert_allclose(centroids[lumen], np.argwhere(mask).mean(axis=0)[::-1], atol=0.5)
        # The mask's area matches the deformed lumen: a circle of radius 5 mm squashed by (1 - lam/H).
        lateral_px, axial_px = settings.pixel_size_mm
        area_mm2 = mask.sum() * lateral_px * axial_px
        stretch = (
            1 + 0.6 * lam * SECTION.vessel_depth_mm * (SECTION.depth_mm - SECTION.vessel_depth_mm) / SECTION.depth_mm**3
        )
        expected = np.pi * 25 * (1 - lam / SECTION.depth_mm) * stretch
        assert area_mm2 == pytest.approx(expected, rel=0.03)


def test_lucas_kanade_recovers_the_true_motion():
    """Measured: median LK error 0.035 px, 90th percentile 0.071 px, for motions up to 1.2 px (704 points)."""
    settings = ImagingSettings()
    before, after = frame_at(3.0, settings), frame_at(3.3, settings)
    rows, cols = np.mgrid[16:240:8, 16:240:8]
    points = np.column_stack([cols.ravel(), rows.ravel()]).astype(np.float32)
    tracked, status, _ = cv2.calcOpticalFlowPyrLK(before, after, points[:, None, :], None, winSize=(21, 21), maxLevel=2)
    lumen = cv2.dilate(
        vessel_mask(SOLUTION, ProbeState(0.0, 3.0), settings, ACOUSTICS).astype(np.uint8), np.ones((15, 15), np.uint8)
    )
    usable = (status.ravel() == 1) & (lumen[rows.ravel(), cols.ravel()] == 0)
    measured = tracked[:, 0, :] - points
    truth = exact_motion_px(points.astype(np.float64), 3.0, 3.3, settings)
    error = np.linalg.norm(measured - truth, axis=1)[usable]
    assert usable.sum() > 500
    assert np.abs(truth).max() > 1.0
    assert np.median(error) < 0.06
    assert np.percentile(error, 90) < 0.15


def test_true_displacement_maps_zero_force_pixels_into_the_deformed_frame():
    settings = ImagingSettings()
    lam = 3.0
    probe = ProbeState(0.0, lam)
    fields = GriddedSolution(SOLUTION, SECTION, settings)
    displacement = true_displacement_px(SECTION, fields.at(0.0), fields.at(lam), probe, settings, ACOUSTICS)
    assert displacement.shape == (256, 256, 2) and displacement.dtype == np.float32
    # Analytic: zero-force pixel at depth z moves up by lam * z / H, minus the probe's lam.
    axial_px = settings.pixel_size_mm[1]
    depth_mm = np.arange(256) * axial_px
    expected_rows = (-lam * depth_mm / SECTION.depth_mm) / axial_px
    np.testing.assert_allclose(displacement[:, 128, 1], expected_rows, atol=0.01)
    # Backward mapping of the deformed frame reproduces the zero-force frame.
    deformed, zero_force = frame_at(lam, settings), frame_at(0.0, settings)
    rows, cols = np.mgrid[0:256, 0:256].astype(np.float32)
    warped = cv2.remap(deformed, cols + displacement[..., 0], rows + displacement[..., 1], cv2.INTER_LINEAR)
    inner = (slice(10, 200), slice(10, 246))
    correlation = np.corrcoef(warped[inner].ravel(), zero_force[inner].ravel())[0, 1]
    unwarped = np.corrcoef(deformed[inner].ravel(), zero_force[inner].ravel())[0, 1]
    assert correlation > 0.9 and correlation > unwarped + 0.25


def test_depth_attenuation_darkens_deep_tissue_without_time_gain_compensation():
    settings = ImagingSettings(rows=128, cols=128, tgc_db_per_cm=0.0)
    frame = frame_at(0.0, settings).astype(float)
    assert frame[5:30].mean() - frame[-30:].mean() > 40  # ~26 dB of round-trip loss over 3.5 cm at 60 dB / 255


def test_settings_reject_bad_values():
    with pytest.raises(InputError, match="rows"):
        ImagingSettings(rows=0)
    with pytest.raises(InputError, match="axial_resolution_mm"):
        ImagingSettings(axial_resolution_mm=-1.0)
    with pytest.raises(InputError, match="sound_speed_m_s"):
        TissueAcoustics(sound_speed_m_s=0.0)
    with pytest.raises(InputError, match="noise"):
        settings = ImagingSettings(rows=16, cols=16)
        render_frame(
            ScattererField(0, settings, ACOUSTICS),
            SECTION,
            lambda points: np.zeros_like(points),
            ProbeState(0.0, 0.0),
            settings,
            ACOUSTICS,
            np.zeros((8, 8), complex),
        )


def jittered_frame(probe_displacement_mm: float, acoustics: TissueAcoustics, settings: ImagingSettings) -> np.ndarray:
    """Like :func:`frame_at` (same scatterers and noise) with other acoustics."""
    probe = ProbeState(0.0, probe_displacement_mm)
    field = ScattererField(3, settings, acoustics)
    noise = unit_complex_noise(np.random.default_rng(4), settings)
    displacement = GriddedSolution(SOLUTION, SECTION, settings).at(probe_displacement_mm)
    return render_frame(field, SECTION, displacement, probe, settings, acoustics, noise)


def test_scatterer_jitter_has_the_stated_rms_and_correlation():
    """rms per axis ``rms_mm``; correlation between two displacements exp(-d^2 / (2 l^2))."""
    rng = np.random.default_rng(0)
    parameters = np.empty((40000, 3, 6), dtype=np.float32)
    parameters[:, :, :5] = rng.standard_normal((40000, 3, 5))
    parameters[:, :, 5] = rng.uniform(0, 2 * np.pi, (40000, 3))
    start = rng.uniform(-5, 5, (40000, 2))
    first = scatterer_jitter_mm(parameters, start, 0.02, 1.0)
    np.testing.assert_allclose(first.std(axis=0), 0.02, rtol=0.03)
    for distance_mm in (0.5, 1.0, 2.0):
        second = scatterer_jitter_mm(parameters, start + np.array([0.0, distance_mm]), 0.02, 1.0)
        correlation = np.mean(first * second) / np.mean(first * first)
        assert correlation == pytest.approx(np.exp(-(distance_mm**2) / 2), abs=0.03)


def test_jitter_decorrelates_speckle_with_compression_and_leaves_it_alone_without():
    """No jitter: the frame is exactly the default one. With jitter: the same tissue state renders
    the same frame; the speckle of two states decorrelates more than without jitter, the more the
    larger the step (measured 25 x 25 patch correlation, lambda 0 -> 1 mm / 0 -> 3 mm: 0.64 / 0.50
    without jitter, 0.63 / 0.34 with 0.02 mm; the tissue compresses by lambda z / 60 mm here)."""
    settings = ImagingSettings(rows=128, cols=128)
    jittered = TissueAcoustics(scatterer_jitter_mm=0.02)
    assert np.array_equal(
        jittered_frame(1.0, TissueAcoustics(scatterer_jitter_mm=0.0), settings), frame_at(1.0, settings)
    )
    assert np.array_equal(jittered_frame(1.0, jittered, settings), jittered_frame(1.0, jittered, settings))
    correlations = {}
    for name, acoustics in (("plain", ACOUSTICS), ("jittered", jittered)):
        reference = jittered_frame(0.0, acoustics, settings)
        for step in (1.0, 3.0):
            points = np.mgrid[0:128, 0:128][::-1].reshape(2, -1).T.astype(np.float64)
            truth = exact_motion_px(points, 0.0, step, settings).reshape(128, 128, 2)
            after = jittered_frame(step, acoustics, settings)
            correlations[name, step] = peak_patch_correlation(reference, after, truth, min_mean=60)
    assert correlations["jittered", 1.0] < correlations["plain", 1.0]
    assert correlations["jittered", 3.0] < correlations["plain", 3.0] - 0.1
    assert correlations["jittered", 3.0] < correlations["jittered", 1.0] - 0.2


def test_a_reflector_fixed_in_the_world_is_displayed_at_its_depth_scaled_by_the_sound_speed():
    settings = ImagingSettings(rows=160, cols=96, depth_mm=40.0)
    axial_px = settings.pixel_size_mm[1]
    for speed, lam in ((1540.0, 0.0), (1540.0, 6.0), (1607.0, 6.0), (1460.0, 3.0)):
        acoustics = TissueAcoustics(sound_speed_m_s=speed, reference_depth_mm=30.0)
        frame = jittered_frame(lam, acoustics, settings).astype(float)
        profile = frame.mean(axis=1)
        expected_row = (30.0 - lam) * 1540.0 / speed / axial_px
        assert abs(int(np.argmax(profile)) - expected_row) <= 1.5
        assert profile.max() > 1.5 * np.median(profile)
    plain = jittered_frame(6.0, TissueAcoustics(), settings)
    assert np.array_equal(plain, jittered_frame(6.0, TissueAcoustics(reference_depth_mm=None), settings))
    with pytest.raises(InputError, match="reference_depth_mm"):
        TissueAcoustics(reference_depth_mm=-3.0)
