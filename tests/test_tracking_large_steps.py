"""The tracker on the cases that break trackers: one large step, decorrelated speckle, low texture.

The pairs come from :func:`usdeform.sim.tracking_cases.compression_pair`: the simulator's image
formation under a known analytic motion at 0.077 mm pixels, 464 x 256 (35.7 mm deep), like the
real phantom pair of issue 14 (5 % strain, the bottom moving 23 px). "Real decorrelation" is
scatterer jitter of 0.02 mm (1 mm correlation length), at which 25 x 25 patches of the pair
correlate as well as consecutive frames of the real PLUS freehand sweep (0.53; tested below, with
what that number does and does not say). Measured numbers (seeds 1-3) are in each test's docstring.
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

from usdeform.io import read_plus_config, read_sequence
from usdeform.optical_flow import TrackedDisplacements, track_palpation
from usdeform.sim.imaging import ImagingSettings, TissueAcoustics
from usdeform.sim.tracking_cases import CompressionPair, compression_pair, peak_patch_correlation

REAL_DECORRELATION = TissueAcoustics(scatterer_jitter_mm=0.02, jitter_correlation_mm=1.0)


def errors(pair: CompressionPair, tracked: TrackedDisplacements) -> tuple[float, np.ndarray, np.ndarray]:
    """(kept fraction of the points in textured tissue whose true end point stays in the frame,
    errors (px) of the kept tracks, true displacements of the kept tracks)."""
    points = np.rint(tracked.points_px).astype(int)
    truth = pair.displacement_px[points[:, 1], points[:, 0]]
    end = tracked.points_px + truth
    rows, cols = pair.frames.shape[1:]
    margin = 10
    inside = (end >= margin).all(axis=1) & (end[:, 0] <= cols - 1 - margin) & (end[:, 1] <= rows - 1 - margin)
    near_lumen = cv2.dilate(pair.lumen.astype(np.uint8), np.ones((15, 15), np.uint8)).astype(bool)
    textured = inside & ~near_lumen[points[:, 1], points[:, 0]]
    kept = tracked.valid[0]
    error = np.linalg.norm(tracked.displacements_px[0, kept] - truth[kept], axis=1)
    return float(kept[textured].mean()), error, truth[kept]


@pytest.mark.parametrize(
    "strain, offset_px, lumen",
    [(0.05, 0.0, False), (0.05, 17.0, False), (0.086, 0.0, True)],
    ids=["real pair 23 px", "40 px with offset", "40 px strain with lumen"],
)
def test_single_large_steps_meet_the_targets(strain, offset_px, lumen):
    """Steps of 23 and 40 px at the bottom, speckle decorrelated only by the motion and the noise.
    Measured: kept 98.4-98.5 %, median 0.10-0.15 px, p99 0.33-0.63 px, no kept track > 3 px wrong
    (before the affine refinement of strained windows: median 0.13-0.26 px, p99 0.37-0.85 px).
    The landed tracker kept 13 % of its tracks more than 3 px wrong on the 40 px offset pair."""
    pair = compression_pair(strain, offset_px=offset_px, lumen=lumen, seed=2)
    assert abs(pair.displacement_px[-1, :, 1]).max() == pytest.approx(offset_px + strain * 463, rel=0.02)
    kept, error, _ = errors(pair, track_palpation(np.stack([pair.frames[0], pair.frames[1]]), [0, 1]))
    assert kept >= 0.9
    assert np.median(error) <= 0.2
    assert np.percentile(error, 99) <= 1.0
    assert np.mean(error > 3.0) <= 0.001


@pytest.mark.parametrize("offset_px", [0.0, 17.0], ids=["real pair 23 px", "40 px with offset"])
def test_real_decorrelation_is_right_or_rejected(offset_px):
    """The issue's failure: at the decorrelation of real data the landed tracker's deep tracks go
    wrong. Here every kept track has the right sign and none is more than 3 px wrong; 99 % are
    kept. The median error is larger than the 0.2 px target: measured 0.23 px (p99 0.74-0.85 px;
    with translation-only windows 0.28-0.29 px and 0.93-0.96 px). Affine Lucas-Kanade started at
    the true position has nearly that error with the same 51 x 51 window (0.16-0.17 px away from
    the frame's edges, benches/bench_tracking.py): the second frame's speckle is partly new."""
    pair = compression_pair(0.05, offset_px=offset_px, acoustics=REAL_DECORRELATION, seed=1)
    tracked = track_palpation(np.stack([pair.frames[0], pair.frames[1]]), [0, 1])
    kept, error, truth = errors(pair, tracked)
    measured = tracked.displacements_px[0, tracked.valid[0]]
    deep = truth[:, 1] < -5.0
    assert kept >= 0.95
    assert np.all(np.sign(measured[deep, 1]) == -1)
    assert np.mean(error > 3.0) <= 0.001
    assert np.median(error) <= 0.25 and np.percentile(error, 99) <= 1.0
    assert sum(tracked.rejection_summary().values()) == int((~tracked.valid[0]).sum())


def test_stronger_compression_at_real_decorrelation_rejects_rather_than_errs():
    """8.6 % strain (40 px) decorrelates the speckle further (patch correlation 0.43): the tracker
    keeps 91 % of the tracks (89 % with translation-only windows, 82 % without the decorrelated-track
    refinement) and none more than 3 px wrong (median error 0.26 px, p99 1.1-1.3 px)."""
    pair = compression_pair(0.086, lumen=True, acoustics=REAL_DECORRELATION, seed=3)
    kept, error, _ = errors(pair, track_palpation(pair.frames, [0, 1]))
    assert kept >= 0.9
    assert np.mean(error > 3.0) <= 0.001 and np.median(error) <= 0.3


def test_the_real_decorrelation_level_matches_the_real_plus_sweep(plus_data: Path):
    """Consecutive frames of the real PLUS SpinePhantom freehand sweep (0.6-2.7 mm apart in elevation,
    0.3-0.8 mm in plane): median peak correlation of 25 x 25 patches 0.53. The simulated pair at the
    jitter called real decorrelation: 0.52-0.54 (without jitter 0.82).

    What the number says: unrelated frames do not correlate at 0 by this measure but at its floor,
    0.33 for the sweep (frames 5 or more apart: 0.35; another frame mirrored: 0.33) and 0.20 for the
    simulator's speckle. Above their floors the simulated pair (0.52) keeps more of its correlation
    than the sweep (0.53), so the real level is not harsher than its reference. That reference is a
    freehand sweep whose speckle decorrelates mostly by out-of-plane motion, which a palpation does
    not have: it bounds the decorrelation of a palpation from above rather than measuring it."""
    recording = read_sequence(
        plus_data / "SpinePhantomFreehand.igs.mha",
        config=read_plus_config(plus_data / "PlusDeviceSet_SpinePhantomFreehandReconstructionOnly.xml"),
    )
    frames = recording.frames
    real = np.median([peak_patch_correlation(frames[i], frames[i + 1]) for i in range(len(frames) - 1)])
    far_apart = np.median([peak_patch_correlation(frames[i], frames[i + 5]) for i in range(len(frames) - 5)])
    real_floor = np.median(
        [peak_patch_correlation(frames[i], frames[(i + 10) % len(frames)][:, ::-1]) for i in range(len(frames))]
    )
    pair = compression_pair(0.05, acoustics=REAL_DECORRELATION, seed=1)
    simulated = peak_patch_correlation(pair.frames[0], pair.frames[1], pair.displacement_px)
    plain = compression_pair(0.05, seed=1)
    simulated_floor = peak_patch_correlation(plain.frames[0], compression_pair(0.05, seed=2).frames[0][:, ::-1])
    assert real == pytest.approx(0.53, abs=0.02)
    assert simulated == pytest.approx(real, abs=0.04)
    assert far_apart == pytest.approx(real_floor, abs=0.04) and real_floor < real - 0.15
    assert (simulated - simulated_floor) / (1 - simulated_floor) > (real - real_floor) / (1 - real_floor)
    assert peak_patch_correlation(plain.frames[0], plain.frames[1], plain.displacement_px) > 0.75


def test_low_texture_is_rejected_not_tracked():
    """Lumen (no speckle) and a noise-dominated bottom (1 dB/cm time-gain compensation, 0.7 dB/cm/MHz):
    no track more than half a window inside the lumen survives (closer to the wall, the window sees
    the bright wall and follows it); in the dark depth tracks are kept only where right (measured:
    0-1 of ~1500 more than 3 px wrong)."""
    pair = compression_pair(0.086, lumen=True, seed=3)
    tracked = track_palpation(pair.frames, [0, 1])
    points = np.rint(tracked.points_px).astype(int)
    deep_in_lumen = cv2.erode(pair.lumen.astype(np.uint8), np.ones((21, 21), np.uint8)).astype(bool)
    inside = deep_in_lumen[points[:, 1], points[:, 0]]
    assert inside.sum() >= 10 and not tracked.valid[0, inside].any()
    assert tracked.rejected["texture"][0] >= inside.sum()

    dark = ImagingSettings(rows=464, cols=256, depth_mm=464 * 0.077, width_mm=256 * 0.077, tgc_db_per_cm=1.0)
    pair = compression_pair(0.05, settings=dark, acoustics=TissueAcoustics(attenuation_db_per_cm_mhz=0.7), seed=3)
    assert pair.frames[0, -60:].mean() < 0.5 * pair.frames[0, :60].mean()  # the bottom is dark
    kept, error, _ = errors(pair, track_palpation(pair.frames, [0, 1]))
    assert kept >= 0.9 and np.mean(error > 3.0) <= 0.001


def test_frames_skipped_in_a_simulated_palpation(small_palpation):
    """The finite-element palpation (8 frames to 8 N) tracked straight from the first to the last
    frame (all frames in between skipped) agrees with the tracking through every frame (measured:
    median difference 0.20 px, p99 0.67 px, 92 % of the chain's tracks kept; with translation-only
    windows 0.22 px and 0.78 px). The one large step decorrelates the speckle of this coarse
    128 x 128 phantom, so the decorrelated-track refinement (wide window, neighbourhood median) acts;
    the jump's median error against the true motion is 0.23 px (p99 0.63 px). Every step of the chain
    decorrelates too, so it takes a key frame at every frame: its own median error is 0.25 px (0.20 px
    with a key frame every 5 frames, which a long palpation pays for: tests/test_optical_flow.py)."""
    recording, _ = small_palpation
    chained = track_palpation(recording.frames, recording.force)
    first, last = int(chained.reference_index), int(chained.frame_indices[-1])
    skipped = recording.select([first, last])
    jump = track_palpation(skipped.frames, skipped.force)
    both = chained.valid[-1] & jump.valid[0]
    difference = np.linalg.norm(chained.displacements_px[-1, both] - jump.displacements_px[0, both], axis=1)
    assert both.sum() >= 0.9 * chained.valid[-1].sum()
    assert np.median(difference) <= 0.25 and np.percentile(difference, 99) <= 1.0
