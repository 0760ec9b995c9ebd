"""The tracker (usdeform.optical_flow.track_palpation, default settings, as a black box) on speckle made as
real B-mode speckle is made.

* Simulated: RF compression pairs (usdeform.sim.rf_compression) in the regime of a real phantom pair on
  which the tracker was silently wrong (one step of 3-6 % axial strain, 15-25 px axial motion at depth,
  dim and noisy deep speckle), parameters drawn at random within the physical ranges; the truth is known.
* Real: the DeepUSE in-vivo RF sequences; the truth is the RF cross-correlation reference
  (tests/rf_reference.py), used only in the depth bands where it agrees with itself.
"""

from __future__ import annotations

import numpy as np
import pytest
from scipy.ndimage import map_coordinates, uniform_filter

from rf_reference import (
    DEEPUSE_PIXEL_MM,
    DEEPUSE_SAMPLE_MM,
    DEEPUSE_SEQUENCES,
    axial_displacement,
    band_summary,
    compose,
    deepuse_b_mode,
    load_deepuse_sequence,
)
from usdeform.optical_flow import track_palpation
from usdeform.sim.rf_compression import rf_compression_pair


def _draws(n: int, seed: int = 2026) -> list[dict]:
    """Parameter draws within the physical ranges of the real pair's regime (not chosen by hand)."""
    rng = np.random.default_rng(seed)
    draws = []
    for index in range(n):
        draws.append(
            dict(
                seed=int(100 + index),
                strain=round(float(rng.uniform(0.03, 0.06)), 4),
                centre_frequency_mhz=round(float(rng.uniform(5.0, 7.5)), 2),
                fractional_bandwidth=round(float(rng.uniform(0.5, 0.8)), 2),
                attenuation_db_cm_mhz=round(float(rng.uniform(0.5, 0.7)), 2),
                tgc_fraction=round(float(rng.uniform(0.0, 0.4)), 2),
                noise_db=round(float(rng.uniform(-44.0, -32.0)), 1),
                white_level_db=round(float(rng.uniform(-6.0, 6.0)), 1),
                strain_depth_gradient=round(float(rng.uniform(-0.3, 0.3)), 2),
                inclusion_contrast=round(float(rng.choice([0.0, rng.uniform(0.3, 0.6)])), 2),
                inclusion_centre_mm=(round(float(rng.uniform(-4, 4)), 1), round(float(rng.uniform(8, 22)), 1)),
                out_of_plane_decorrelation=round(float(rng.uniform(0.0, 0.15)), 3),
                line_pitch_mm=round(float(rng.uniform(0.149, 0.3)), 3),
            )
        )
    return draws


FULL_SIZE = dict(seed=1, rows=519, cols=508, white_level_db=5.0, line_pitch_mm=0.3)
SIMULATED_DRAWS = [
    dict(seed=1),  # the defaults: the real pair's regime at a test-friendly size (mid-depth grey about 180)
    # The real pair's full size (40 x 38 mm), its grey level at the bottom (about 55: a higher white level)
    # and the 128 lines of a common linear array across its 38 mm.
    pytest.param(
        FULL_SIZE,
        marks=pytest.mark.xfail(
            strict=True,
            reason="known: below 33 mm the speckle of 0.3 mm lines carries no lateral evidence (the true position "
            "correlates 0.19-0.29 over 51 x 51 px, chance 0.14-0.16 in median) and 1.5 % of the kept tracks are "
            "3-4.5 px wrong laterally, with the block matching's lateral bias (axial right, no wrong sign)",
        ),
    ),
    *_draws(3),
]
BAND_MM = 3.0


def _evaluate(pair, tracked) -> tuple[dict, str]:
    """Errors of the tracks against the truth, and a table per BAND_MM depth band."""
    points = tracked.points_px
    rows, cols = pair.pre.shape
    truth = np.stack(
        [map_coordinates(pair.displacement_px[..., i], [points[:, 1], points[:, 0]], order=1) for i in range(2)], axis=1
    )
    moved = truth + points
    d = tracked.displacements_px[0]
    kept = tracked.valid[0]
    error = np.linalg.norm(d - truth, axis=1)
    wrong_sign = kept & (np.abs(truth[:, 1]) > 2) & (np.sign(d[:, 1]) != np.sign(truth[:, 1]))
    # Textured, defined from the frames alone: the local mean grey is 3 dB (15 grey levels) above what the
    # electronic noise alone would show there, and the tissue stays 8 px inside both frames.
    local_mean = uniform_filter(pair.pre.astype(float), 15)
    r, c = (
        np.clip(np.rint(points[:, 1]).astype(int), 0, rows - 1),
        np.clip(np.rint(points[:, 0]).astype(int), 0, cols - 1),
    )
    inside = np.all(
        (points >= 8) & (points <= [cols - 9, rows - 9]) & (moved >= 8) & (moved <= [cols - 9, rows - 9]), axis=1
    )
    textured = inside & (local_mean[r, c] >= pair.noise_grey[r] + 15)
    depth = (points[:, 1] + 0.5) * pair.pixel_mm[0]
    lines = ["band_mm  tracked_dy  true_dy  kept/total  >3px  wrong_sign  median_err"]
    for top in np.arange(0, depth.max() + 1e-9, BAND_MM):
        s = (depth >= top) & (depth < top + BAND_MM)
        k = s & kept
        tracked_dy = f"{np.median(d[k, 1]):+8.2f}" if k.any() else "     nan"
        median_error = f"{np.median(error[k]):6.2f}" if k.any() else "   nan"
        lines.append(
            f"{top:4.0f}-{top + BAND_MM:<3.0f} {tracked_dy}  {np.median(truth[s, 1]):+8.2f}  {k.sum():4d}/{s.sum():<4d}"
            f"  {np.sum(k & (error > 3)):4d}  {np.sum(wrong_sign & s):6d}      {median_error}"
        )
    stats = dict(
        median_error=float(np.median(error[kept])) if kept.any() else float("inf"),
        wrong_3px=float(np.mean(error[kept] > 3)) if kept.any() else 1.0,
        wrong_3px_axial=float(np.mean(np.abs(d[kept, 1] - truth[kept, 1]) > 3)) if kept.any() else 1.0,
        wrong_sign=int(wrong_sign.sum()),
        textured_kept=float(np.mean(kept[textured])),
        textured=int(textured.sum()),
    )
    return stats, "\n".join(lines)


@pytest.mark.parametrize(
    "params", SIMULATED_DRAWS, ids=lambda p: f"seed{p['seed']}-{p.get('rows', 456)}x{p.get('cols', 256)}"
)
def test_tracker_on_rf_speckle_large_step(params):
    """Targets on one large compression step of RF-made speckle: median error <= 0.3 px over kept tracks, at
    most 0.1 % of kept tracks more than 3 px wrong, no kept track of the wrong axial sign where the true
    axial motion exceeds 2 px, and at least 80 % of the textured tracks kept."""
    pair = rf_compression_pair(**params)
    tracked = track_palpation(pair.frames, np.array([0.0, 1.0]))
    stats, table = _evaluate(pair, tracked)
    message = f"{params}\n{stats}\n{table}"
    assert stats["textured"] > 500, message
    assert stats["median_error"] <= 0.3, message
    assert stats["wrong_3px"] <= 0.001, message
    assert stats["wrong_sign"] == 0, message
    assert stats["textured_kept"] >= 0.8, message


def test_tracker_on_the_full_size_rf_pair_is_right_axially():
    """The full-size case that fails above on lateral errors: axially it meets the targets (median error
    <= 0.3 px, at most 0.1 % of the kept tracks more than 3 px wrong axially, no wrong sign, 80 % of the
    textured tracks kept)."""
    pair = rf_compression_pair(**FULL_SIZE)
    stats, table = _evaluate(pair, track_palpation(pair.frames, np.array([0.0, 1.0])))
    message = f"{FULL_SIZE}\n{stats}\n{table}"
    assert stats["median_error"] <= 0.3, message
    assert stats["wrong_3px_axial"] <= 0.001, message
    assert stats["wrong_sign"] == 0, message
    assert stats["textured_kept"] >= 0.8, message


DARK_BOTTOM = dict(seed=7, rows=519, cols=508, white_level_db=8.0, line_pitch_mm=0.3)
"""The real pair's failure reproduced: grey falling to about 40 at the bottom. The tracker before the fix kept
deep bands at +0.0 to +2.0 px where the truth is -20 to -25 px (29 kept tracks of the wrong sign)."""


def test_tracker_on_a_dark_bottom_rf_pair_meets_the_real_pairs_targets():
    """The targets of the real compression pair: every 3 mm band from 8 to 35 mm with tracks kept has its
    median axial step within 10 % of the truth, no kept track has the wrong sign, at least 80 % of the
    textured tracks are kept, and no kept track is more than 3 px wrong axially."""
    pair = rf_compression_pair(**DARK_BOTTOM)
    tracked = track_palpation(pair.frames, np.array([0.0, 1.0]))
    stats, table = _evaluate(pair, tracked)
    message = f"{DARK_BOTTOM}\n{stats}\n{table}"
    depth = (tracked.points_px[:, 1] + 0.5) * pair.pixel_mm[0]
    truth = pair.displacement_px[
        np.rint(tracked.points_px[:, 1]).astype(int), np.rint(tracked.points_px[:, 0]).astype(int)
    ]
    kept = tracked.valid[0]
    for top in np.arange(8.0, 35.0, 3.0):
        band = kept & (depth >= top) & (depth < top + 3.0)
        if band.sum() >= 10:
            tracked_dy, true_dy = np.median(tracked.displacements_px[0, band, 1]), np.median(truth[band, 1])
            assert abs(tracked_dy - true_dy) <= 0.1 * abs(true_dy), f"band {top:.0f} mm\n{message}"
    assert stats["wrong_sign"] == 0, message
    assert stats["wrong_3px_axial"] == 0, message
    assert stats["textured_kept"] >= 0.8, message


# --- DeepUSE: real in-vivo RF --------------------------------------------------------------------------

RELATIVE_TOLERANCE = 0.10
FLOOR_PX = 0.5
"""Absolute floor of the tolerance, B-mode pixels (0.5 x 0.08 mm). The DeepUSE motions are small (0.03-0.4
mm in 5 frames), so 10 % of them is a few micrometres, below what B-mode (envelope, no RF phase, 0.08 mm
pixels) can resolve. Half a pixel still fails any band tracked with the wrong sign or a lost step once the
motion exceeds it, while it leaves room for the B-mode's own bias; the reference's band medians are
consistent to about 0.1 px (the chain criterion below), and the comparison uses the same points on both
sides, so neither the reference nor the sampling takes up the floor."""


def _consistent(band) -> bool:
    """A band where the RF reference agrees with itself: RF correlation and neighbour agreement at least
    0.5, and the direct frame 1 -> 6 estimate within 5 % (or 8 um, 0.1 px) of the chain of five steps."""
    return (
        band.correlation >= 0.5
        and band.neighbour_agreement >= 0.5
        and band.chain_difference_mm <= max(0.05 * abs(band.median_mm), 0.008)
    )


@pytest.fixture(scope="module")
def deepuse_cases(deepuse_rf_data):
    """Per sequence: B-mode frames 1..6, the RF reference frame 1 -> 6 and its consistent 5 mm bands."""
    cases = {}
    for sequence in DEEPUSE_SEQUENCES:
        rf = load_deepuse_sequence(deepuse_rf_data, sequence)
        direct = axial_displacement(rf[0], rf[5], DEEPUSE_SAMPLE_MM, max_shift_mm=1.0)
        chain = compose([axial_displacement(rf[k], rf[k + 1], DEEPUSE_SAMPLE_MM, max_shift_mm=1.0) for k in range(5)])
        bands = band_summary(direct, 5.0, chain=chain)
        cases[sequence] = (deepuse_b_mode(rf), direct, bands)
    return cases


@pytest.mark.parametrize("palpation", ["frames_1_to_6", "frame_1_and_6"])
@pytest.mark.parametrize("sequence", DEEPUSE_SEQUENCES)
def test_tracker_on_deepuse_matches_the_rf_reference(deepuse_cases, sequence, palpation):
    """In every 5 mm band where the RF reference is consistent, the tracker's median axial displacement from
    frame 1 to frame 6 (as the last frame of a six-frame palpation, or as a two-frame palpation) is within
    max(10 %, 0.5 px) of the reference at the same points."""
    frames, reference, bands = deepuse_cases[sequence]
    if palpation == "frame_1_and_6":
        frames = frames[[0, 5]]
    tracked = track_palpation(frames, np.arange(frames.shape[0], dtype=float))
    points = tracked.points_px
    dy_mm = tracked.displacements_px[-1][:, 1] * DEEPUSE_PIXEL_MM[0]
    kept = tracked.valid[-1]
    depth = (points[:, 1] + 0.5) * DEEPUSE_PIXEL_MM[0]
    line = points[:, 0] * DEEPUSE_PIXEL_MM[1] / 0.2  # B-mode column c lies at line c / 2
    reference_mm = reference.at(depth, line)
    consistent = [band for band in bands if _consistent(band)]
    rows, failures = [], []
    for band in consistent:
        s = kept & (depth >= band.top_mm) & (depth < band.bottom_mm)
        tracker_median = float(np.median(dy_mm[s])) if s.sum() >= 10 else float("nan")
        reference_median = float(np.median(reference_mm[s])) if s.any() else band.median_mm
        tolerance = max(RELATIVE_TOLERANCE * abs(reference_median), FLOOR_PX * DEEPUSE_PIXEL_MM[0])
        row = (
            f"{band.top_mm:4.0f}-{band.bottom_mm:<3.0f} tracker {tracker_median:+.4f} reference {reference_median:+.4f}"
            f" mm (tolerance {tolerance:.4f}) kept {s.sum()} corr {band.correlation:.2f}"
        )
        rows.append(row)
        if not abs(tracker_median - reference_median) <= tolerance:
            failures.append(row)
    message = f"sequence {sequence}, {palpation}:\n" + "\n".join(rows)
    assert len(consistent) >= 3, message
    assert not failures, message
