"""Evaluation of vessel geometry (paper Sec. IV): segmentation, Dice, centroid distance, area.

Masks are (rows, cols) bool arrays (0/1 integer arrays are accepted) on the B-mode pixel grid, pixel
(col, row) at ``mask[row, col]``. Physical sizes take ``pixel_size_mm = (lateral, axial)``, the mm per
pixel along columns and rows; :func:`pixel_size_mm` reads it from an ``image_to_probe`` calibration.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import cv2
import numpy as np

from .errors import InputError

__all__ = [
    "MIN_AREA_PX",
    "MIN_CONTRAST",
    "SMOOTHING_SIGMA_PX",
    "THRESHOLD_FRACTION",
    "VesselSegmentation",
    "area_mm2",
    "centroid_distance_mm",
    "centroid_mm",
    "dice",
    "lumen_seeds",
    "pixel_size_mm",
    "segment_vessel",
]


#: :func:`segment_vessel`'s default settings (the compiled lumen search of the vessel-anchored
#: correction takes the same): smoothing (pixels), threshold fraction, contrast, smallest region (pixels).
SMOOTHING_SIGMA_PX = 2.0
THRESHOLD_FRACTION = 0.8
MIN_CONTRAST = 0.5
MIN_AREA_PX = 20


@dataclass(frozen=True, eq=False)
class VesselSegmentation:
    """A segmented vessel lumen.

    mask: (rows, cols) bool lumen (the filled outer contour of the dark region).
    ellipse_center_px: (x, y) centre of the ellipse fitted to the contour (``cv2.fitEllipse``), pixels.
    ellipse_axes_px: full lengths of the ellipse's two axes, pixels, as OpenCV orders them.
    ellipse_angle_deg: rotation of the first axis from the x (column) axis, degrees, as OpenCV gives it.
    """

    mask: np.ndarray
    ellipse_center_px: tuple[float, float]
    ellipse_axes_px: tuple[float, float]
    ellipse_angle_deg: float

    def ellipse_mask(self) -> np.ndarray:
        """(rows, cols) bool: the fitted ellipse rasterised on the frame's pixel grid."""
        canvas = np.zeros(self.mask.shape, dtype=np.uint8)
        cv2.ellipse(canvas, (self.ellipse_center_px, self.ellipse_axes_px, self.ellipse_angle_deg), 1, thickness=-1)
        return canvas.astype(bool)


def segment_vessel(
    frame: np.ndarray,
    seed_px: Sequence[float] | None = None,
    *,
    smoothing_sigma_px: float = SMOOTHING_SIGMA_PX,
    threshold_fraction: float = THRESHOLD_FRACTION,
    min_contrast: float = MIN_CONTRAST,
    min_area_px: int = MIN_AREA_PX,
) -> VesselSegmentation:
    """Segment the anechoic (dark) lumen of a vessel in one B-mode frame.

    Parameters
    ----------
    frame : ndarray
        (rows, cols) uint8 or non-negative float32 B-mode image.
    seed_px : sequence of float, optional
        Expected (x, y) position of the lumen, pixels.
    smoothing_sigma_px, threshold_fraction, min_contrast, min_area_px
        The method's settings (below).

    Returns
    -------
    VesselSegmentation
        The mask and its fitted ellipse.

    Raises
    ------
    InputError
        Bad frame or arguments, no anechoic region, or no dark region that fits.

    Notes
    -----

    1. Gaussian smoothing (``smoothing_sigma_px``) averages out the speckle.
    2. Levels: ``tissue`` is the median of the smoothed frame (the surrounding speckle fills most
       of it), ``dark`` its minimum (the lumen). The frame must hold an anechoic region:
       ``dark <= (1 - min_contrast) * tissue``.
    3. Hysteresis threshold: a pixel is dark below ``dark + threshold_fraction * (tissue - dark)``,
       and a dark region counts only if it holds a core below the halfway level
       ``dark + 0.5 * (tissue - dark)``. B-mode is log-compressed and blurred by the imaging
       point-spread function, so the echo at the lumen's edge reaches half the tissue level (in
       gray levels) a few pixels inside the true wall: the halfway level alone under-segments
       (simulated vessels: area -15 %, Dice 0.92); 0.8 recovers the wall (Dice 0.96-0.98).
    4. A 3 x 3 opening removes isolated dark specks; among the 8-connected dark regions of at least
       ``min_area_px`` pixels with a core, the vessel is the one containing ``seed_px`` (x, y) or
       else nearest to it by centroid; without a seed, the largest region that does not touch the
       frame's border.
    5. Its outer contour (``cv2.findContours``) is filled as the mask (holes closed) and fitted
       with an ellipse (``cv2.fitEllipse``).
    """
    image = np.asarray(frame)
    if image.dtype not in (np.uint8, np.float32) or image.ndim != 2 or min(image.shape) < 3:
        raise InputError(f"frame: expected a (rows, cols) uint8 or float32 image, got {image.dtype} {image.shape}")
    if not np.all(np.isfinite(image)) or image.min() < 0:
        raise InputError("frame: B-mode intensities must be finite and non-negative")
    if not (np.isfinite(smoothing_sigma_px) and smoothing_sigma_px > 0):
        raise InputError(f"smoothing_sigma_px: expected a positive number of pixels, got {smoothing_sigma_px!r}")
    if not (np.isfinite(threshold_fraction) and 0.5 <= threshold_fraction < 1):
        raise InputError(f"threshold_fraction: expected a number in [0.5, 1), got {threshold_fraction!r}")
    if not (np.isfinite(min_contrast) and 0 < min_contrast <= 1):
        raise InputError(f"min_contrast: expected a number in (0, 1], got {min_contrast!r}")
    if int(min_area_px) != min_area_px or min_area_px < 5:
        raise InputError(f"min_area_px: expected an integer >= 5 (an ellipse needs 5 points), got {min_area_px!r}")

    labels, stats, centroids, candidates = _dark_regions(
        image, smoothing_sigma_px, threshold_fraction, min_contrast, min_area_px
    )
    rows, cols = image.shape
    if seed_px is not None:
        seed = np.asarray(seed_px, dtype=np.float64)
        if seed.shape != (2,) or not np.all(np.isfinite(seed)):
            raise InputError(f"seed_px: expected a finite (x, y) position in pixels, got {seed_px!r}")
        column, row = round(float(seed[0])), round(float(seed[1]))
        if not (0 <= column < cols and 0 <= row < rows):
            raise InputError(f"seed_px: {seed_px!r} lies outside the {rows} x {cols} frame")
        if labels[row, column] in candidates:
            chosen = int(labels[row, column])
        elif candidates:
            chosen = min(candidates, key=lambda label: float(np.hypot(*(centroids[label] - seed))))
        else:
            chosen = 0
    else:
        inside = _inside(candidates, stats, rows, cols)
        chosen = max(inside, key=lambda label: stats[label, cv2.CC_STAT_AREA]) if inside else 0
    if chosen == 0:
        raise InputError(
            f"frame: no dark region of at least {min_area_px} pixels"
            + (" away from the frame's border" if seed_px is None else "")
            + " (is the lumen collapsed or out of view?)"
        )

    contours, _ = cv2.findContours((labels == chosen).astype(np.uint8), cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)
    contour = max(contours, key=len)
    mask = np.zeros((rows, cols), dtype=np.uint8)
    cv2.drawContours(mask, [contour], -1, 1, thickness=-1)
    if len(contour) < 5:
        raise InputError(f"frame: the lumen's contour has {len(contour)} points, an ellipse needs 5")
    (center_x, center_y), (axis_a, axis_b), angle = cv2.fitEllipse(contour)
    return VesselSegmentation(
        mask=mask.astype(bool),
        ellipse_center_px=(float(center_x), float(center_y)),
        ellipse_axes_px=(float(axis_a), float(axis_b)),
        ellipse_angle_deg=float(angle),
    )


def _dark_regions(
    image: np.ndarray, smoothing_sigma_px: float, threshold_fraction: float, min_contrast: float, min_area_px: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray, list[int]]:
    """Steps 1-4 of :func:`segment_vessel`: the labels of the dark regions (rows, cols), their
    ``cv2.connectedComponentsWithStats`` stats and centroids, and the labels that qualify as lumens."""
    smoothed = cv2.GaussianBlur(image.astype(np.float32), (0, 0), float(smoothing_sigma_px))
    dark_level, tissue_level = float(smoothed.min()), float(np.median(smoothed))
    if not dark_level <= (1 - min_contrast) * tissue_level or tissue_level <= 0:
        raise InputError(
            f"frame: no anechoic region: the darkest smoothed level {dark_level:.3g} is not below "
            f"{1 - min_contrast:.3g} times the typical level {tissue_level:.3g}"
        )
    below = (smoothed < dark_level + threshold_fraction * (tissue_level - dark_level)).astype(np.uint8)
    dark = cv2.morphologyEx(below, cv2.MORPH_OPEN, np.ones((3, 3), np.uint8))
    core = smoothed < dark_level + 0.5 * (tissue_level - dark_level)
    count, labels, stats, centroids = cv2.connectedComponentsWithStats(dark, connectivity=8)
    has_core = np.bincount(labels[core], minlength=count) > 0
    candidates = [
        label for label in range(1, count) if stats[label, cv2.CC_STAT_AREA] >= min_area_px and has_core[label]
    ]
    return labels, stats, centroids, candidates


def _inside(candidates: list[int], stats: np.ndarray, rows: int, cols: int) -> list[int]:
    """The candidate regions that do not touch the border of a (rows, cols) frame."""
    return [
        label
        for label in candidates
        if stats[label, cv2.CC_STAT_LEFT] > 0
        and stats[label, cv2.CC_STAT_TOP] > 0
        and stats[label, cv2.CC_STAT_LEFT] + stats[label, cv2.CC_STAT_WIDTH] < cols
        and stats[label, cv2.CC_STAT_TOP] + stats[label, cv2.CC_STAT_HEIGHT] < rows
    ]


#: Smallest area of a further lumen that :func:`lumen_seeds` reports, as a fraction of the largest's.
MIN_LUMEN_AREA_FRACTION = 0.2


def lumen_seeds(frame: np.ndarray) -> list[tuple[float, float]]:
    """The (x, y) centroids, pixels, of the lumens of one B-mode frame, the largest first, then left to
    right: the dark regions :func:`segment_vessel` (default settings) would choose from away from the
    border, of at least :data:`MIN_LUMEN_AREA_FRACTION` of the largest's area (a vein beside an artery,
    not a dark speck). Empty where the frame shows no anechoic region."""
    image = np.asarray(frame)
    try:
        _, stats, centroids, candidates = _dark_regions(
            image, SMOOTHING_SIGMA_PX, THRESHOLD_FRACTION, MIN_CONTRAST, MIN_AREA_PX
        )
    except InputError:
        return []
    inside = _inside(candidates, stats, *image.shape)
    if not inside:
        return []
    areas = {label: int(stats[label, cv2.CC_STAT_AREA]) for label in inside}
    largest = max(inside, key=lambda label: areas[label])
    others = sorted(
        (label for label in inside if label != largest and areas[label] >= MIN_LUMEN_AREA_FRACTION * areas[largest]),
        key=lambda label: float(centroids[label][0]),
    )
    return [(float(centroids[label][0]), float(centroids[label][1])) for label in [largest, *others]]


def _checked_mask(name: str, mask: np.ndarray) -> np.ndarray:
    """``mask`` as a non-empty (rows, cols) bool array; 0/1 integers accepted."""
    array = np.asarray(mask)
    if array.ndim != 2:
        raise InputError(f"{name}: expected a (rows, cols) mask, got shape {array.shape}")
    if array.dtype != np.bool_:
        if not np.issubdtype(array.dtype, np.integer) or not np.isin(array, (0, 1)).all():
            raise InputError(f"{name}: expected a bool mask (or integers 0/1), got dtype {array.dtype}")
        array = array.astype(bool)
    if not array.any():
        raise InputError(f"{name}: the mask is empty (no pixel set)")
    return array


def _checked_pixel_size(pixel_size_mm: Sequence[float]) -> np.ndarray:
    size = np.asarray(pixel_size_mm, dtype=np.float64)
    if size.shape != (2,) or not np.all(np.isfinite(size)) or np.any(size <= 0):
        raise InputError(f"pixel_size_mm: expected (lateral, axial) positive mm per pixel, got {pixel_size_mm!r}")
    return size


def pixel_size_mm(image_to_probe: np.ndarray) -> tuple[float, float]:
    """(lateral, axial) mm per pixel: the lengths of the column and row axes of a (4, 4) ``image_to_probe``."""
    transform = np.asarray(image_to_probe, dtype=np.float64)
    if transform.shape != (4, 4) or not np.all(np.isfinite(transform)):
        raise InputError(f"image_to_probe: expected a finite (4, 4) transform, got shape {transform.shape}")
    lateral, axial = np.linalg.norm(transform[:3, :2], axis=0)
    if lateral <= 0 or axial <= 0:
        raise InputError("image_to_probe: a pixel axis has zero length")
    return float(lateral), float(axial)


def dice(mask_a: np.ndarray, mask_b: np.ndarray) -> float:
    """Dice coefficient 2 |A & B| / (|A| + |B|) of two non-empty masks of the same shape, in [0, 1]."""
    a, b = _checked_mask("mask_a", mask_a), _checked_mask("mask_b", mask_b)
    if a.shape != b.shape:
        raise InputError(f"mask_a, mask_b: shapes differ, {a.shape} and {b.shape}")
    return float(2.0 * np.count_nonzero(a & b) / (np.count_nonzero(a) + np.count_nonzero(b)))


def centroid_mm(mask: np.ndarray, pixel_size_mm: Sequence[float]) -> np.ndarray:
    """(2,) float64 centroid (lateral, axial) of a non-empty mask, mm from the top-left pixel's centre."""
    rows, cols = np.nonzero(_checked_mask("mask", mask))
    return np.array([cols.mean(), rows.mean()]) * _checked_pixel_size(pixel_size_mm)


def centroid_distance_mm(mask_a: np.ndarray, mask_b: np.ndarray, pixel_size_mm: Sequence[float]) -> float:
    """Euclidean distance between the centroids of two non-empty masks of the same shape, mm."""
    a, b = _checked_mask("mask_a", mask_a), _checked_mask("mask_b", mask_b)
    if a.shape != b.shape:
        raise InputError(f"mask_a, mask_b: shapes differ, {a.shape} and {b.shape}")
    return float(np.linalg.norm(centroid_mm(a, pixel_size_mm) - centroid_mm(b, pixel_size_mm)))


def area_mm2(mask: np.ndarray, pixel_size_mm: Sequence[float]) -> float:
    """Area of a non-empty mask, mm^2 (pixel count times the area of one pixel)."""
    size = _checked_pixel_size(pixel_size_mm)
    return float(np.count_nonzero(_checked_mask("mask", mask)) * size[0] * size[1])
