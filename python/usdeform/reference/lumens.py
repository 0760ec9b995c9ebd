"""NumPy and OpenCV twin of the compiled lumen search (``usdeform._core.sweep_lumens``): each frame's
zero-force lumen for a vessel-anchored model, searched where the previous frame's was.

A search warps a window of the frame back with the model's field (:func:`warp_window`: bilinear in
float32, the edge replicated, uint8 rounded to nearest) and segments its dark region with
:func:`usdeform.metrics.segment_vessel` (OpenCV's blur, opening and connected components); the
compiled search does the same steps in one pass.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from functools import partial

import numpy as np

from ..correction import ANCHOR_MAX_ITERATIONS, ANCHOR_TOLERANCE_PX, SEARCH_WINDOW_RADII
from ..errors import InputError
from ..metrics import segment_vessel
from ..regression import LumenTrack, StiffnessProfile, VesselAnchor, VesselAnchoredModel

Window = tuple[slice, slice]  # rows, columns of a frame
#: ``D(x, y, F)`` of a model at one frame's force on a window, its vessel part on a lumen (None: the
#: image part alone): (2, window rows, window columns), pixels.
FieldOn = Callable[[VesselAnchor | None, Window], np.ndarray]
#: A model's :data:`FieldOn` at a force (N) and profile.
Displacement = Callable[[float, StiffnessProfile, VesselAnchor | None, Window], np.ndarray]


def search_window(expected: VesselAnchor, shape: tuple[int, int]) -> Window:
    """The square of ``SEARCH_WINDOW_RADII`` radii around ``expected``, cut at the frame's edges
    (the whole frame where the square lies outside it)."""
    half = SEARCH_WINDOW_RADII * expected.radius_px
    (x, y), (rows, cols) = expected.centre_px, shape
    row_slice = slice(max(int(np.floor(y - half)), 0), min(int(np.ceil(y + half)) + 1, rows))
    column_slice = slice(max(int(np.floor(x - half)), 0), min(int(np.ceil(x + half)) + 1, cols))
    if row_slice.start >= row_slice.stop or column_slice.start >= column_slice.stop:
        return slice(0, rows), slice(0, cols)
    return row_slice, column_slice


def warp_window(frame: np.ndarray, source_x: np.ndarray, source_y: np.ndarray) -> np.ndarray:
    """``frame`` sampled bilinearly at ``(source_x, source_y)`` (float32 pixel positions), the four
    pixels around each clamped to the frame (its edge replicated outside it), in float32; a uint8
    frame's samples rounded to nearest (``floor(v + 0.5)``) and returned as uint8."""
    rows, cols = frame.shape
    x0, y0 = np.floor(source_x), np.floor(source_y)
    fx, fy = source_x - x0, source_y - y0
    x0 = np.clip(x0, -1, cols - 1).astype(np.int64)
    y0 = np.clip(y0, -1, rows - 1).astype(np.int64)

    def at(y: np.ndarray, x: np.ndarray) -> np.ndarray:
        return frame[np.clip(y, 0, rows - 1), np.clip(x, 0, cols - 1)].astype(np.float32)

    one = np.float32(1.0)
    sample = (one - fy) * ((one - fx) * at(y0, x0) + fx * at(y0, x0 + 1)) + fy * (
        (one - fx) * at(y0 + 1, x0) + fx * at(y0 + 1, x0 + 1)
    )
    if frame.dtype == np.uint8:
        return np.clip(np.floor(sample + np.float32(0.5)), 0, 255).astype(np.uint8)
    return sample.astype(np.float32)


def find_lumen(
    frame: np.ndarray,
    displacement_on: Callable[[Window], np.ndarray],
    seed_px: Sequence[float],
    window: Window | None = None,
) -> VesselAnchor | None:
    """The lumen of ``frame`` backward-mapped by the displacement ``displacement_on(window)`` gives
    (2, window rows, window columns): the dark region at or nearest to ``seed_px``, searched in
    ``window`` (None: the whole frame), None where there is none; searched again in the whole frame
    where the window holds none of it or only a part."""
    rows, cols = frame.shape
    whole = (slice(0, rows), slice(0, cols))
    row_slice, column_slice = window or whole
    top, left = row_slice.start, column_slice.start
    x = np.arange(column_slice.start, column_slice.stop, dtype=np.float32)
    y = np.arange(row_slice.start, row_slice.stop, dtype=np.float32)[:, np.newaxis]
    field = displacement_on((row_slice, column_slice))
    warped = warp_window(frame, field[0].astype(np.float32) + x, field[1].astype(np.float32) + y)
    height, width = warped.shape
    seed = (
        min(max(float(seed_px[0]) - left, 0.0), width - 1.0),
        min(max(float(seed_px[1]) - top, 0.0), height - 1.0),
    )
    try:
        mask: np.ndarray | None = segment_vessel(warped, seed).mask
    except InputError:  # no anechoic region, or none that fits
        mask = None
    if window is not None and (
        mask is None
        or (top > 0 and mask[0].any())
        or (row_slice.stop < rows and mask[-1].any())
        or (left > 0 and mask[:, 0].any())
        or (column_slice.stop < cols and mask[:, -1].any())
    ):
        return find_lumen(frame, displacement_on, seed_px)
    if mask is None:
        return None
    found = VesselAnchor.of_mask(mask)
    return VesselAnchor((found.centre_px[0] + left, found.centre_px[1] + top), found.radius_px)


def same_lumen(found: VesselAnchor | None, expected: VesselAnchor) -> VesselAnchor | None:
    """``found`` if it overlaps ``expected`` (centres closer than the sum of the radii), else None."""
    if found is None:
        return None
    distance = float(np.hypot(*np.subtract(found.centre_px, expected.centre_px)))
    return found if distance < found.radius_px + expected.radius_px else None


def zero_force_lumen(
    frame: np.ndarray, model: VesselAnchoredModel, near: VesselAnchor | None, field_on: FieldOn
) -> VesselAnchor | None:
    """One frame's zero-force lumen (:func:`usdeform.correction.frame_vessel_anchor`), with the
    model's field at the frame's force given by ``field_on``."""
    shape = model.frame_shape
    if near is None:
        anchor = find_lumen(frame, partial(field_on, None), model.reference.centre_px)
    else:
        anchor = same_lumen(
            find_lumen(frame, partial(field_on, None), near.centre_px, search_window(near, shape)), near
        )
    for _ in range(ANCHOR_MAX_ITERATIONS):
        if anchor is None:
            return None
        found = find_lumen(frame, partial(field_on, anchor), anchor.centre_px, search_window(anchor, shape))
        found = same_lumen(found, anchor)
        if found is None:
            return anchor
        change = max(*np.abs(np.subtract(found.centre_px, anchor.centre_px)), abs(found.radius_px - anchor.radius_px))
        anchor = found
        if change < ANCHOR_TOLERANCE_PX:
            break
    return anchor


def sweep_lumens(
    frames: np.ndarray,
    forces: np.ndarray,
    profiles: np.ndarray,
    model: VesselAnchoredModel,
    displacement: Displacement | None = None,
    track: LumenTrack | None = None,
) -> list[VesselAnchor | None]:
    """:func:`usdeform.correction.sweep_lumens` frame by frame in Python, the field from
    ``displacement(force, profile, lumen, window)`` (None: the compiled
    :meth:`~usdeform.regression.VesselAnchoredModel.displacement_on`)."""
    field = displacement or model.displacement_on
    found: list[VesselAnchor | None] = []
    state = track if track is not None else LumenTrack()
    previous, missed = state.last_found, state.frames_missed
    for index, frame in enumerate(frames):
        near = None if previous is None else VesselAnchor(previous.centre_px, previous.radius_px * (1 + missed))
        profile = StiffnessProfile(*profiles[index])
        anchor = zero_force_lumen(frame, model, near, partial(field, float(forces[index]), profile))
        found.append(anchor)
        previous, missed = (anchor, 0) if anchor is not None else (previous, missed + 1)
    state.last_found, state.frames_missed = previous, missed
    return found
