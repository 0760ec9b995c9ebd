"""Vessel segmentation and the paper's geometry metrics: Dice, centroid distance, area."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from usdeform.errors import InputError
from usdeform.metrics import area_mm2, centroid_distance_mm, centroid_mm, dice, pixel_size_mm, segment_vessel
from usdeform.recording import image_to_probe_from_geometry


def rectangle(shape: tuple[int, int], rows: slice, cols: slice) -> np.ndarray:
    mask = np.zeros(shape, dtype=bool)
    mask[rows, cols] = True
    return mask


def test_dice_of_known_overlaps():
    a = rectangle((20, 30), slice(2, 12), slice(5, 15))  # 100 pixels
    b = rectangle((20, 30), slice(2, 12), slice(10, 20))  # 100 pixels, 50 shared
    assert dice(a, a) == 1.0
    assert dice(a, b) == pytest.approx(0.5)
    assert dice(a, rectangle((20, 30), slice(14, 18), slice(20, 25))) == 0.0
    assert dice(a.astype(np.uint8), b.astype(np.int64)) == pytest.approx(0.5)


def test_centroid_and_area_use_the_anisotropic_pixel_size():
    mask = rectangle((40, 50), slice(10, 21), slice(4, 9))  # rows 10..20, cols 4..8: 55 pixels
    size = (0.2, 0.5)  # mm per pixel, (lateral, axial)
    np.testing.assert_allclose(centroid_mm(mask, size), [6.0 * 0.2, 15.0 * 0.5])
    assert area_mm2(mask, size) == pytest.approx(55 * 0.1)
    moved = np.roll(mask, (4, 3), axis=(0, 1))  # 4 rows down, 3 columns right
    assert centroid_distance_mm(mask, moved, size) == pytest.approx(np.hypot(3 * 0.2, 4 * 0.5))


def test_pixel_size_comes_from_image_to_probe():
    lateral, axial = pixel_size_mm(image_to_probe_from_geometry(256, 128, depth_mm=40.0, width_mm=37.5))
    assert lateral == pytest.approx(37.5 / 128) and axial == pytest.approx(40.0 / 256)


@pytest.mark.parametrize(
    "call, match",
    [
        (lambda m: dice(m, np.zeros_like(m)), "mask_b: the mask is empty"),
        (lambda m: dice(m, m[:-1]), "shapes differ"),
        (lambda m: dice(m.astype(float), m), "dtype"),
        (lambda m: dice(m * np.uint8(2), m), "bool"),
        (lambda m: dice(m[None], m[None]), "shape"),
        (lambda m: centroid_mm(np.zeros_like(m), (1.0, 1.0)), "empty"),
        (lambda m: centroid_mm(m, (1.0, 0.0)), "pixel_size_mm"),
        (lambda m: area_mm2(m, (1.0,)), "pixel_size_mm"),
        (lambda m: centroid_distance_mm(m, m.T, (1.0, 1.0)), "shapes differ"),
        (lambda m: pixel_size_mm(np.eye(3)), "image_to_probe"),
    ],
)
def test_bad_masks_and_sizes_are_rejected(call, match):
    with pytest.raises(InputError, match=match):
        call(rectangle((10, 12), slice(2, 5), slice(3, 7)).astype(np.uint8).astype(bool))


def bmode_frame(discs: list[tuple[float, float, float]], seed: int = 0) -> tuple[np.ndarray, list[np.ndarray]]:
    """(96, 128) uint8 B-mode-like frame with anechoic discs (x, y, radius), pixels, and their true masks.

    Complex Gaussian scatterers (none inside the discs) blurred by a Gaussian point-spread function,
    envelope-detected and log-compressed to 50 dB, as a scanner forms a B-mode image.
    """
    rng = np.random.default_rng(seed)
    rows, cols = np.mgrid[0:96, 0:128]
    masks = [np.hypot(cols - x, rows - y) <= radius for x, y, radius in discs]
    echogenicity = np.ones((96, 128), dtype=np.float32)
    for mask in masks:
        echogenicity[mask] = 0.0
    in_phase, quadrature = (
        cv2.GaussianBlur((rng.standard_normal((96, 128)) * echogenicity).astype(np.float32), (0, 0), 1.2)
        for _ in range(2)
    )
    amplitude = np.hypot(in_phase, quadrature)
    envelope = amplitude + 1e-3 * np.median(amplitude) * np.abs(rng.standard_normal((96, 128)))  # receiver noise
    decibels = 20 * np.log10(envelope / np.percentile(envelope, 99.9))
    return np.clip(np.rint(255 * (1 + decibels / 50.0)), 0, 255).astype(np.uint8), masks


def test_segmentation_picks_the_seeded_or_the_largest_inner_dark_region():
    """Measured: Dice 0.986 (large disc), 0.953 (small disc, radius 8 px)."""
    frame, (large, small, at_border) = bmode_frame([(40, 45, 14), (95, 50, 8), (125, 10, 12)])
    assert dice(segment_vessel(frame).mask, large) > 0.95  # the largest region away from the border
    seeded = segment_vessel(frame, seed_px=(96, 49))
    assert dice(seeded.mask, small) > 0.9
    np.testing.assert_allclose(seeded.ellipse_center_px, (95, 50), atol=1.0)
    np.testing.assert_allclose(seeded.ellipse_axes_px, (16, 16), atol=2.0)
    assert dice(segment_vessel(frame, seed_px=(80, 50)).mask, small) > 0.9  # nearest by centroid
    assert dice(segment_vessel(frame, seed_px=(120, 12)).mask, at_border) > 0.8  # a seed may pick a border region
    # The halfway threshold leaves out the edge that the point-spread function smears into the lumen.
    assert area_mm2(segment_vessel(frame, threshold_fraction=0.5).mask, (1, 1)) < 0.9 * large.sum()


def test_segmentation_fails_clearly_without_a_lumen():
    with pytest.raises(InputError, match="no anechoic region"):
        segment_vessel(np.full((64, 64), 120, dtype=np.uint8))
    speckle_only, _ = bmode_frame([])
    with pytest.raises(InputError, match="no anechoic region"):
        segment_vessel(speckle_only)
    frame, _ = bmode_frame([(0, 48, 15)])  # the only dark region touches the border
    with pytest.raises(InputError, match="away from the frame's border"):
        segment_vessel(frame)
    with pytest.raises(InputError, match="seed_px"):
        segment_vessel(frame, seed_px=(200, 10))
    with pytest.raises(InputError, match="frame"):
        segment_vessel(frame.astype(np.int32))
    with pytest.raises(InputError, match="non-negative"):
        segment_vessel(frame.astype(np.float32) - 10)


def test_segmentation_matches_the_simulated_lumen(small_palpation):
    """Measured: Dice 0.984 at 0 N and 0.972 at 7.6 N (ellipse: 0.983, 0.974); 256 x 256 frames: 0.962-0.964."""
    recording, truth = small_palpation
    size = pixel_size_mm(recording.image_to_probe)
    for index in (0, len(recording) - 1):
        found = segment_vessel(recording.frames[index])
        true_mask = truth.vessel_mask[index]
        assert dice(found.mask, true_mask) > 0.95
        assert dice(found.ellipse_mask(), true_mask) > 0.94
        assert centroid_distance_mm(found.mask, true_mask, size) < 0.2
        assert area_mm2(found.mask, size) == pytest.approx(area_mm2(true_mask, size), rel=0.08)
    # The metrics see the compression: the lumen moves up and shrinks under 7.6 N.
    first, last = truth.vessel_mask[0], truth.vessel_mask[-1]
    assert centroid_mm(last, size)[1] < centroid_mm(first, size)[1] - 1.0
    assert area_mm2(last, size) < 0.95 * area_mm2(first, size) and dice(first, last) < 0.9
