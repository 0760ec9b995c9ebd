"""Lucas-Kanade tracking through a palpation, and the eq. 10 boundary constraints."""

from __future__ import annotations

import dataclasses
import warnings

import cv2
import numpy as np
import pytest

from usdeform.errors import InputError
from usdeform.optical_flow import (
    TrackedDisplacements,
    TrackingSettings,
    boundary_constraints,
    concatenate,
    track_palpation,
)
from usdeform.optical_flow._block_matching import _nanmedian
from usdeform.optical_flow._lucas_kanade import _LK_CRITERIA, _affine_lucas_kanade, _lucas_kanade

ROWS, COLS = 128, 128
LUMEN_CENTER = np.array([64.0, 60.0])  # (x, y) in the reference frame, pixels
LUMEN_RADIUS = 14.0


def compression(strain: float, points: np.ndarray) -> np.ndarray:
    """(N, 2) displacement (dx, dy), pixels, of reference points (x, y) under an axial ``strain``:
    depth y shrinks to y (1 - strain) towards the probe (y = 0) and the tissue bulges sideways
    by half the strain about the centre column."""
    center_x = (COLS - 1) / 2
    return np.column_stack([0.5 * strain * (points[:, 0] - center_x), -strain * points[:, 1]])


def speckle_palpation(strains: np.ndarray, seed: int = 0) -> np.ndarray:
    """(n, ROWS, COLS) uint8 frames: smoothed random speckle compressed by each of ``strains``
    (cv2.remap backward mapping of :func:`compression`), with an anechoic disc (the lumen) that
    moves with the tissue."""
    rng = np.random.default_rng(seed)
    texture = cv2.GaussianBlur(rng.standard_normal((ROWS, COLS)).astype(np.float32), (0, 0), 1.2)
    texture = np.clip(128 + 40 * texture / texture.std(), 0, 255)
    rows, cols = np.mgrid[0:ROWS, 0:COLS].astype(np.float32)
    in_lumen = np.hypot(cols - LUMEN_CENTER[0], rows - LUMEN_CENTER[1]) < LUMEN_RADIUS
    reference = np.where(in_lumen, 3.0, texture).astype(np.float32)
    center_x = (COLS - 1) / 2
    frames = []
    for strain in strains:
        # The deformed pixel (x', y') shows the reference pixel (x, y) with x' = x + dx(x), y' = y + dy(y).
        map_x = (center_x + (cols - center_x) / (1 + 0.5 * strain)).astype(np.float32)
        map_y = (rows / (1 - strain)).astype(np.float32)
        frames.append(cv2.remap(reference, map_x, map_y, cv2.INTER_CUBIC, borderMode=cv2.BORDER_REFLECT))
    return np.clip(np.rint(np.stack(frames)), 0, 255).astype(np.uint8)


STRAINS = np.linspace(0.0, 0.15, 10)  # up to 19 px of axial motion at the bottom row


@pytest.fixture(scope="module")
def synthetic():
    frames = speckle_palpation(STRAINS)
    return frames, track_palpation(frames, settings=TrackingSettings(grid_spacing_px=6))


def test_a_point_lucas_kanade_loses_has_an_infinite_error_not_opencvs_leftover():
    speckle = np.random.default_rng(0).integers(0, 256, (64, 64)).astype(np.uint8)
    points = np.array([[[32.0, 32.0]], [[60.0, 60.0]]], dtype=np.float32)
    start = points + np.array([[[2.0, 0.0]], [[300.0, 300.0]]], dtype=np.float32)  # the second starts off the frame
    _, found, error = _lucas_kanade(speckle, np.roll(speckle, 2, axis=1), points, start, (21, 21), 2)
    assert found.tolist() == [True, False]
    assert np.isfinite(error[0]) and error[1] == np.inf


def test_chained_tracking_recovers_a_known_compression(synthetic):
    _, tracked = synthetic
    assert tracked.reference_index == 0 and np.array_equal(tracked.frame_indices, np.arange(1, 10))
    assert tracked.displacements_px.shape == (9, len(tracked.points_px), 2)
    in_lumen = np.hypot(*(tracked.points_px - LUMEN_CENTER).T) < LUMEN_RADIUS - 4
    outside = np.hypot(*(tracked.points_px - LUMEN_CENTER).T) > LUMEN_RADIUS + 12
    # The textureless lumen is dropped; the speckle around it is kept.
    assert in_lumen.sum() >= 5 and not tracked.valid[0, in_lumen].any()
    assert tracked.valid[-1, outside].mean() > 0.95
    for step, strain in enumerate(STRAINS[1:]):
        keep = tracked.valid[step] & outside
        error = np.linalg.norm(
            tracked.displacements_px[step, keep] - compression(strain, tracked.points_px[keep]), axis=1
        )
        assert np.median(error) < 0.25 and np.percentile(error, 90) < 0.45, (
            step,
            np.median(error),
            np.percentile(error, 90),
        )


def test_one_jump_beyond_the_capture_range_of_lucas_kanade_is_tracked(synthetic):
    """With a 2-level pyramid (capture range of a few pixels), Lucas-Kanade alone cannot follow the
    jump of up to 19 px straight to the highest force (the landed tracker: median error 16 px); the
    block-matching initial estimate can (measured: median 0.23 px), and so does the chain of steps."""
    frames, _ = synthetic
    direct = track_palpation(frames[[0, -1]], settings=TrackingSettings(grid_spacing_px=6, pyramid_levels=1))
    truth = compression(STRAINS[-1], direct.points_px)
    deep = direct.points_px[:, 1] > 96  # where the motion is largest
    direct_error = np.linalg.norm(direct.displacements_px[0] - truth, axis=1)[deep & direct.valid[0]]
    chained = track_palpation(frames, settings=TrackingSettings(grid_spacing_px=6, pyramid_levels=1))
    chained_error = np.linalg.norm(chained.displacements_px[-1] - truth, axis=1)[deep & chained.valid[-1]]
    assert np.median(direct_error) < 0.35 and direct_error.max() < 1.5 and direct.valid[0, deep].mean() > 0.8
    assert np.median(chained_error) < 0.2 and chained.valid[-1, deep].mean() > 0.8


def test_plain_frame_to_frame_chaining_also_tracks(synthetic):
    frames, _ = synthetic
    tracked = track_palpation(frames, settings=TrackingSettings(grid_spacing_px=6, key_frame_interval=1))
    keep = tracked.valid[-1]
    error = np.linalg.norm(
        tracked.displacements_px[-1, keep] - compression(STRAINS[-1], tracked.points_px[keep]), axis=1
    )
    assert keep.mean() > 0.7 and np.median(error) < 0.3


def test_frames_are_tracked_in_increasing_force_from_the_lowest(synthetic):
    frames, tracked = synthetic
    shuffle = np.random.default_rng(3).permutation(len(frames))
    shuffled = track_palpation(frames[shuffle], STRAINS[shuffle] * 100.0, TrackingSettings(grid_spacing_px=6))
    assert shuffle[shuffled.reference_index] == 0
    np.testing.assert_array_equal(shuffle[shuffled.frame_indices], tracked.frame_indices)
    np.testing.assert_array_equal(shuffled.valid, tracked.valid)
    np.testing.assert_allclose(shuffled.displacements_px, tracked.displacements_px, atol=1e-6)


def test_float32_frames_track_like_their_uint8_originals(synthetic):
    frames, tracked = synthetic
    as_float = track_palpation(frames.astype(np.float32) / 255.0, settings=TrackingSettings(grid_spacing_px=6))
    np.testing.assert_array_equal(as_float.valid, tracked.valid)
    np.testing.assert_allclose(as_float.displacements_px, tracked.displacements_px, atol=0.05)


def test_a_dropped_track_stays_dropped_and_reads_nan(synthetic):
    _, tracked = synthetic
    assert np.all(tracked.valid[1:] <= tracked.valid[:-1])
    assert np.isnan(tracked.displacements_px[~tracked.valid]).all()
    assert np.isfinite(tracked.displacements_px[tracked.valid]).all()
    np.testing.assert_array_equal(tracked.kept_per_frame, tracked.valid.sum(axis=1))
    assert tracked.kept_fraction == pytest.approx(tracked.valid[-1].mean())
    with pytest.raises(ValueError):
        tracked.valid[0, 0] = True  # read-only


OFF = {
    "max_forward_backward_px": 1e9,
    "max_lk_error": 1e9,
    "min_correlation": -1.0,
    "max_neighbour_residual": np.inf,
    "max_neighbour_deviation_px": np.inf,
    "decorrelated_below": -1.0,  # no wide window or neighbourhood median either: plain Lucas-Kanade
    "max_translation_spread_px": np.inf,
    "block_matching_margin_px": np.inf,
}


@pytest.mark.parametrize(
    "check, reason",
    [
        ({"max_forward_backward_px": 1.0}, "forward_backward"),
        ({"max_lk_error": 30.0}, "lucas_kanade_error"),
        ({"min_correlation": 0.2}, "correlation"),
    ],
)
def test_each_check_alone_drops_untrackable_points(check, reason):
    """A frame whose upper half is new speckle: the points there cannot be tracked. With every
    check off they are kept (but for the few that Lucas-Kanade carries out of the frame); each of
    these checks alone drops a good part of them and says so in ``rejected``; with the default
    checks all of them are dropped."""
    frames = speckle_palpation(np.array([0.0, 0.02, 0.04]))
    frames[2, :50] = speckle_palpation(np.array([0.0]), seed=99)[0, :50]

    def kept(**thresholds: float) -> tuple[float, float, float, dict[str, int]]:
        tracked = track_palpation(
            frames, settings=TrackingSettings(grid_spacing_px=6, min_texture_ratio=0.0, **thresholds)
        )
        upper, lower = tracked.points_px[:, 1] < 30, tracked.points_px[:, 1] > 80
        return (
            tracked.valid[0, upper].mean(),
            tracked.valid[1, upper].mean(),
            tracked.valid[1, lower].mean(),
            tracked.rejection_summary(),
        )

    first, upper, lower, rejected = kept(**OFF)
    assert (first, lower) == (1.0, 1.0) and upper > 0.95 and set(rejected) <= {"left_frame"}
    first, upper, lower, rejected = kept(**{**OFF, **check})
    assert first == 1.0 and upper < 0.75 and lower > 0.95
    assert set(rejected) - {"left_frame"} == {reason}
    first, upper, lower, _ = kept()
    assert first == 1.0 and upper == 0.0 and lower > 0.95


def test_a_track_that_disagrees_with_its_neighbours_is_dropped():
    """A 10 x 10 pixel block of the last frame moved 3 px sideways against the tissue around it: its
    track follows the block (the other checks pass) but disagrees with its neighbours' median."""
    frames = speckle_palpation(np.array([0.0, 0.02]))
    block_rows, block_cols = slice(55, 65), slice(35, 45)  # around the grid point (x, y) = (40, 60)
    moved = frames[1].copy()
    moved[block_rows, block_cols] = frames[1][block_rows, slice(32, 42)]
    frames[1] = moved
    point = np.array([40.0, 60.0])
    loose = track_palpation(frames, settings=TrackingSettings(grid_spacing_px=5, border_px=0, window_px=9, **OFF))
    strict = track_palpation(frames, settings=TrackingSettings(grid_spacing_px=5, border_px=0, window_px=9))
    index = int(np.argmin(np.linalg.norm(loose.points_px - point, axis=1)))
    assert np.allclose(loose.points_px[index], point)
    assert loose.valid[0, index] and abs(loose.displacements_px[0, index, 0] - (0.01 * (40 - 63.5) + 3.0)) < 1.0
    assert not strict.valid[0, index] and strict.rejected["neighbours"][0] >= 1
    assert strict.valid[0].mean() > 0.85


def sample(field: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Bilinear samples (N, 2) of a (rows, cols, 2) field at (x, y) points."""
    x, y = (points[:, i].astype(np.float32)[None] for i in (0, 1))
    return cv2.remap(field.astype(np.float32), x, y, cv2.INTER_LINEAR)[0].astype(np.float64)


def true_motion_to_the_last_frame(tracked: TrackedDisplacements, displacement_px: np.ndarray) -> np.ndarray:
    """(N, 2) true motion, px, from the reference frame to the tracker's last frame of the tissue seen at each tracked
    point, from the ground truth's backward maps (n, rows, cols, 2): p = q + D_ref(q) for the zero-force pixel q,
    which is at q + D_last(q) in the last frame."""
    points = tracked.points_px
    zero_force = points.copy()
    for _ in range(50):
        zero_force = points - sample(displacement_px[tracked.reference_index], zero_force)
    return zero_force + sample(displacement_px[tracked.frame_indices[-1]], zero_force) - points


def test_tracking_matches_the_simulated_displacement_at_the_highest_force(small_palpation):
    """Measured: 196 points, 188 kept to 7.6 N; motions up to 8.4 px; median error 0.20 px,
    90th percentile 0.38 px (with translation-only windows: 0.23 px and 0.53 px; frame-to-frame
    chaining alone: 0.58 px and 1.04 px)."""
    recording, truth = small_palpation
    tracked = track_palpation(recording.frames, recording.force)
    last = tracked.frame_indices[-1]
    assert last == int(np.argmax(recording.force))
    points = tracked.points_px
    expected = true_motion_to_the_last_frame(tracked, truth.displacement_px)
    keep = tracked.valid[-1] & np.isfinite(expected).all(axis=1)
    error = np.linalg.norm(tracked.displacements_px[-1, keep] - expected[keep], axis=1)
    assert np.abs(expected[keep]).max() > 7.0
    assert tracked.kept_fraction > 0.8
    assert np.median(error) < 0.25 and np.percentile(error, 90) < 0.5
    # Points deep inside the lumen are dropped.
    lumen = cv2.erode(truth.vessel_mask[tracked.reference_index].astype(np.uint8), np.ones((9, 9), np.uint8))
    in_lumen = lumen[points[:, 1].astype(int), points[:, 0].astype(int)] == 1
    assert in_lumen.sum() >= 4 and tracked.valid[-1, in_lumen].mean() < 0.25


def test_many_frames_do_not_add_up_key_frame_errors(tmp_path, monkeypatch):
    """150 frames of the coarse phantom to 8 N (2.5 N/s): every key frame passes on its own tracking error, so key
    frames taken only once the speckle decorrelates track the highest-force frame closer to the true motion than a
    key frame every 5 frames (measured: median error 0.30 px against 0.96 px, mean axial error 0.26 against 1.48 px,
    109 against 76 of 196 tracks kept)."""
    from usdeform.sim.phantoms import coarse_phantom
    from usdeform.sim.recordings import simulate_palpation

    monkeypatch.setenv("USDEFORM_CACHE_DIR", str(tmp_path))
    recording, truth = simulate_palpation(
        coarse_phantom(), 20.0, 8.0, n_frames=150, seed=11, rows=128, cols=128, ramp_rate_n_per_s=2.5
    )
    adaptive = track_palpation(recording.frames, recording.force)
    every_five = track_palpation(
        recording.frames, recording.force, TrackingSettings(key_frame_interval=5, key_frame_correlation=-1)
    )
    errors = []
    for tracked in (adaptive, every_five):
        error = tracked.displacements_px[-1] - true_motion_to_the_last_frame(tracked, truth.displacement_px)
        errors.append(error[tracked.valid[-1] & np.isfinite(error).all(axis=1)])
    adaptive_error, every_five_error = errors
    adaptive_median = np.median(np.linalg.norm(adaptive_error, axis=1))
    assert adaptive_median <= 0.4 and np.median(np.linalg.norm(every_five_error, axis=1)) >= 2 * adaptive_median
    assert abs(adaptive_error[:, 1].mean()) <= 0.5 * abs(every_five_error[:, 1].mean())
    assert len(adaptive_error) >= len(every_five_error)


def affinely_warped_speckle(gradient: np.ndarray, seed: int = 4) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A 160 x 160 speckle frame, the same frame moved by u(p) = (3.2, -2.7) + gradient @ (p - (80, 80))
    (forward mapping, inverted for cv2.remap), and the (N, 2) grid points (x, y) of the first frame."""
    rng = np.random.default_rng(seed)
    texture = cv2.GaussianBlur(rng.standard_normal((160, 160)).astype(np.float32), (0, 0), 1.2)
    before = np.clip(128 + 40 * texture / texture.std(), 0, 255).astype(np.float32)
    rows, cols = np.mgrid[0:160, 0:160].astype(np.float64)
    moved = np.stack([cols - 80.0, rows - 80.0], axis=-1)
    inverse = np.linalg.inv(np.eye(2) + gradient)
    source = (moved - np.array([3.2, -2.7])) @ inverse.T + 80.0
    after = cv2.remap(before, source[..., 0].astype(np.float32), source[..., 1].astype(np.float32), cv2.INTER_CUBIC)
    grid_y, grid_x = np.mgrid[8:153:12, 8:153:12].astype(np.float32)
    return (
        np.clip(np.rint(before), 0, 255).astype(np.uint8),
        np.clip(np.rint(after), 0, 255).astype(np.uint8),
        np.column_stack([grid_x.ravel(), grid_y.ravel()]),
    )


def test_affine_lucas_kanade_follows_a_strained_and_sheared_window():
    """8 % axial compression, 4 % lateral spread and 3 % shear: across a 41-pixel window the motion
    varies by 3.3 px. The affine window finds every point (also where the window is cut by the frame's
    edge) within 0.05 px from 1.5 px away; OpenCV's translation-only window started at the truth
    strays (measured: affine median 0.006 px, max 0.024 px; translation-only median 0.15 px, max 0.8 px).
    The warped window matches (correlation 0.997)."""
    gradient = np.array([[0.04, 0.03], [0.0, -0.08]])
    before, after, points = affinely_warped_speckle(gradient)
    truth = points + np.array([3.2, -2.7]) + (points - 80.0) @ gradient.T
    start = (truth + np.random.default_rng(1).uniform(-1.5, 1.5, truth.shape)).astype(np.float32)
    inside = (truth > 2).all(axis=1) & (truth < 157).all(axis=1)
    found, ok, correlation = _affine_lucas_kanade(before, after, points, start, (41, 41))
    error = np.linalg.norm(found - truth, axis=1)[inside]
    assert ok[inside].all() and np.max(error) < 0.05
    assert np.median(correlation[inside]) > 0.97
    translation, _, _ = cv2.calcOpticalFlowPyrLK(
        before,
        after,
        points[:, None],
        truth[:, None].astype(np.float32),
        winSize=(41, 41),
        maxLevel=0,
        criteria=_LK_CRITERIA,
        flags=cv2.OPTFLOW_USE_INITIAL_FLOW,
    )
    assert np.median(np.linalg.norm(translation[:, 0] - truth, axis=1)[inside]) > 3 * np.median(error)


def test_affine_lucas_kanade_says_when_a_window_has_no_texture():
    """A flat window does not determine the warp: not ok, the initial position returned, correlation 0."""
    before, after, points = affinely_warped_speckle(np.zeros((2, 2)))
    before[:60, :60] = 128
    start = points + np.array([3.2, -2.7], dtype=np.float32)
    found, ok, correlation = _affine_lucas_kanade(before, after, points, start, (21, 21))
    flat = (points < 45).all(axis=1)
    assert flat.sum() >= 4 and not ok[flat].any() and (correlation[flat] == 0).all()
    np.testing.assert_array_equal(found[flat], start[flat])
    assert ok[~flat].mean() > 0.95


def test_boundary_constraints_follow_eq_10_with_y_down():
    lambdas = np.array([0.5, 1.0, 2.0])
    boundary = boundary_constraints(100, 64, lambdas, flexible_layer_mm=40.0, n_points=5)
    assert boundary.points_px.shape == (10, 2) and boundary.valid.all()
    np.testing.assert_allclose(boundary.points_px[:5], np.column_stack([np.linspace(0, 63, 5), np.zeros(5)]))
    np.testing.assert_allclose(boundary.points_px[5:, 1], 99.0)
    np.testing.assert_array_equal(boundary.displacements_px[:, :5], 0.0)
    np.testing.assert_array_equal(boundary.displacements_px[:, 5:, 0], 0.0)
    # The bottom row moves up (negative y) by lambda / L_T of its depth: 2 mm / 40 mm * 99 px.
    np.testing.assert_allclose(boundary.displacements_px[:, 5:, 1], -(lambdas / 40.0 * 99.0)[:, None] * np.ones(5))
    np.testing.assert_array_equal(boundary.frame_indices, [1, 2, 3])


def test_with_boundary_appends_the_boundary_rows_using_lambda_from_the_reference(synthetic):
    _, tracked = synthetic
    lambdas = 1.0 + STRAINS * 10.0  # one per input frame; the reference frame's is 1 mm
    joined = tracked.with_boundary(lambdas, flexible_layer_mm=30.0, n_points=8)
    n = len(tracked.points_px)
    assert joined.points_px.shape == (n + 16, 2) and joined.displacements_px.shape == (9, n + 16, 2)
    np.testing.assert_array_equal(joined.valid[:, :n], tracked.valid)
    np.testing.assert_allclose(joined.displacements_px[-1, -1], [0.0, -(1.5 / 30.0) * (ROWS - 1)])
    assert isinstance(joined, TrackedDisplacements) and joined.frame_shape == (ROWS, COLS)
    with pytest.raises(InputError, match="frame_indices"):
        concatenate([tracked, boundary_constraints(ROWS, COLS, np.zeros(9), 30.0, 4, reference_index=1)])
    with pytest.raises(InputError, match="probe_displacement_mm"):
        tracked.with_boundary(lambdas[:5], flexible_layer_mm=30.0, n_points=8)


@pytest.mark.parametrize(
    "frames, match",
    [
        (np.zeros((4, 32), dtype=np.uint8), "shape"),
        (np.zeros((4, 32, 32), dtype=np.int16), "dtype"),
        (np.zeros((1, 32, 32), dtype=np.uint8), "at least 2"),
        (np.full((3, 32, 32), np.nan, dtype=np.float32), "non-finite"),
    ],
)
def test_bad_frames_are_rejected(frames, match):
    with pytest.raises(InputError, match=match):
        track_palpation(frames)


def test_bad_arguments_are_rejected(synthetic):
    frames, _ = synthetic
    with pytest.raises(InputError, match="force"):
        track_palpation(frames, np.arange(3.0))
    with pytest.raises(InputError, match="force"):
        track_palpation(frames, np.r_[np.arange(9.0), np.inf])
    with pytest.raises(InputError, match="grid"):
        track_palpation(frames, settings=TrackingSettings(border_px=70))
    with pytest.raises(InputError, match="flexible_layer_mm"):
        boundary_constraints(ROWS, COLS, np.zeros(3), 0.0, 4)
    with pytest.raises(InputError, match="frame_indices"):
        boundary_constraints(ROWS, COLS, np.zeros(3), 30.0, 4, frame_indices=np.arange(2))


@pytest.mark.parametrize(
    ("field", "value"),
    [
        ("window_px", 20),
        ("window_px", (21, 20)),
        ("window_px", (21, 21, 21)),
        ("wide_window_px", (51, 30)),
        ("texture_window_px", 8),
        ("pyramid_levels", -1),
        ("key_frame_interval", 0),
        ("grid_spacing_px", 0.0),
        ("max_step_px", np.inf),
        ("max_lk_error", float("nan")),
        ("max_translation_spread_px", 0.0),
        ("min_texture_ratio", -0.1),
        ("min_correlation", 1.5),
        ("decorrelated_below", 1.5),
        ("key_frame_correlation", float("nan")),
        ("border_px", -1.0),
    ],
)
def test_bad_settings_are_rejected_naming_the_field(field, value):
    with pytest.raises(InputError, match=f"^{field}: "):
        TrackingSettings(**{field: value})


def test_tracking_settings_are_frozen():
    with pytest.raises(dataclasses.FrozenInstanceError):
        TrackingSettings().window_px = 31


def test_nanmedian_equals_numpys_on_random_neighbourhoods():
    rng = np.random.default_rng(5)
    for shape in ((6, 7, 2, 8), (40, 24), (3, 9), (2, 1)):
        values = rng.standard_normal(shape)
        values[rng.random(shape) < 0.4] = np.nan
        values[0] = np.nan  # a neighbourhood with nothing alive
        with warnings.catch_warnings():  # numpy warns of the all-NaN neighbourhood
            warnings.simplefilter("ignore", RuntimeWarning)
            expected = np.nanmedian(values, axis=-1)
        np.testing.assert_array_equal(_nanmedian(values), expected)
