"""A vessel's lumen found in a frame: its centre and radius as a :class:`~usdeform.regression.VesselAnchor`.

:func:`find_lumen` finds the lumen of a frame after a warp (the dark region at or nearest to a seed,
:func:`usdeform.metrics.segment_vessel`), searched in a window around where it is expected
(:func:`search_window`); :func:`same_lumen` tells whether a region found is the lumen followed. The
correction with a vessel-anchored model (:func:`usdeform.vessel_correction.correct_vessel_anchored`)
places the model's vessel part on the lumens found this way.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence

import cv2
import numpy as np

from .errors import InputError
from .metrics import segment_vessel
from .regression import VesselAnchor

__all__ = [
    "SEARCH_WINDOW_RADII",
    "Window",
    "find_lumen",
    "same_lumen",
    "search_window",
    "searchable_frame",
]


#: Half-width, in the expected lumen's radii, of the square a lumen is searched in when it is expected
#: somewhere (the previous frame's lumen, the previous correction's): the segmentation and its warp then
#: cover a part of the frame; a lumen reaching the square's edge, or none in it, is searched again in the
#: whole frame.
SEARCH_WINDOW_RADII = 2.5

Window = tuple[slice, slice]  # rows, columns of a frame


def search_window(expected: VesselAnchor, shape: tuple[int, int]) -> Window:
    """The square of :data:`SEARCH_WINDOW_RADII` radii around ``expected``, cut at the frame's edges
    (the whole frame where the square lies outside it)."""
    half = SEARCH_WINDOW_RADII * expected.radius_px
    (x, y), (rows, cols) = expected.centre_px, shape
    row_slice = slice(max(int(np.floor(y - half)), 0), min(int(np.ceil(y + half)) + 1, rows))
    column_slice = slice(max(int(np.floor(x - half)), 0), min(int(np.ceil(x + half)) + 1, cols))
    if row_slice.start >= row_slice.stop or column_slice.start >= column_slice.stop:
        return slice(0, rows), slice(0, cols)
    return row_slice, column_slice


def find_lumen(
    frame: np.ndarray,
    displacement_on: Callable[[Window], np.ndarray],
    seed_px: Sequence[float],
    window: Window | None = None,
) -> VesselAnchor | None:
    """The lumen of ``frame`` backward-mapped by the displacement ``displacement_on(window)`` gives
    (2, window rows, window columns): the dark region at or nearest to ``seed_px``, searched in
    ``window`` (None: the whole frame), None where there is none. The warp here only has to show the
    lumen to the segmentation: OpenCV's (bilinear to 1/32 px) of the window serves. Sources outside the
    frame take the nearest edge pixel, so that no dark strip of fill at the edge passes for a lumen."""
    rows, cols = frame.shape
    whole = (slice(0, rows), slice(0, cols))
    row_slice, column_slice = window or whole
    top, left = row_slice.start, column_slice.start
    x = np.arange(column_slice.start, column_slice.stop, dtype=np.float32)
    y = np.arange(row_slice.start, row_slice.stop, dtype=np.float32)[:, np.newaxis]
    field = displacement_on((row_slice, column_slice))
    source_x, source_y = field[0].astype(np.float32) + x, field[1].astype(np.float32) + y
    warped = cv2.remap(frame, source_x, source_y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
    height, width = warped.shape
    seed = (
        min(max(float(seed_px[0]) - left, 0.0), width - 1.0),
        min(max(float(seed_px[1]) - top, 0.0), height - 1.0),
    )
    try:
        mask: np.ndarray | None = segment_vessel(warped, seed).mask
    except InputError:  # the frame is checked: no anechoic region, or none that fits
        mask = None
    if window is not None and (
        mask is None
        or (top > 0 and mask[0].any())
        or (row_slice.stop < rows and mask[-1].any())
        or (left > 0 and mask[:, 0].any())
        or (column_slice.stop < cols and mask[:, -1].any())
    ):  # the window holds none of the lumen, or only a part of it: search the whole frame
        return find_lumen(frame, displacement_on, seed_px)
    if mask is None:
        return None
    found = VesselAnchor.of_mask(mask)
    return VesselAnchor((found.centre_px[0] + left, found.centre_px[1] + top), found.radius_px)


def same_lumen(found: VesselAnchor | None, expected: VesselAnchor) -> VesselAnchor | None:
    """``found`` if it overlaps ``expected`` (centres closer than the sum of the radii), else None: a
    dark region elsewhere (a shadow, the lumen pressed shut) is not the lumen followed."""
    if found is None:
        return None
    distance = float(np.hypot(*np.subtract(found.centre_px, expected.centre_px)))
    return found if distance < found.radius_px + expected.radius_px else None


def searchable_frame(frame: np.ndarray, shape: tuple[int, int], name: str) -> np.ndarray:
    """``frame`` checked as a deformed B-mode frame of ``shape``: uint8, or finite non-negative float32."""
    image = np.asarray(frame)
    if image.dtype not in (np.uint8, np.float32) or image.shape != shape:
        raise InputError(
            f"{name}: expected a {shape[0]} x {shape[1]} uint8 or float32 frame, got {image.dtype} {image.shape}"
        )
    if image.dtype == np.float32 and not (np.all(np.isfinite(image)) and image.min() >= 0):
        raise InputError(f"{name}: B-mode intensities must be finite and non-negative")
    return image
