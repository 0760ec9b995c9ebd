"""The vessel wall as an observation: where the lumen boundary moved in each palpation frame.

A vessel's lumen is anechoic: it holds no speckle, so no optical-flow track says how far its walls
moved, and a displacement model fitted to the tissue tracks alone only bridges it (a compliant
vessel then stays flattened after correction). :func:`track_vessel_wall` measures the wall itself:

1. The lumen is segmented in the lowest-force (reference) frame with
   :func:`usdeform.metrics.segment_vessel` (thresholds from the frame's own gray levels, an
   opening, the dark component at ``seed_px`` or else the largest one off the frame's border).
   Its outer contour is resampled every ``spacing_px`` along its length, smoothed, and each point
   is moved along its outward normal onto the half level of the lightly blurred mask (sub-pixel).
2. Each other frame's lumen is segmented near where the reference lumen is predicted to be: the
   reference boundary moved by the tissue tracks around it (a locally linear fit to the
   nearest valid tracks), or by the lumen's previous centroid shift without tracks. A frame whose
   lumen is not found, or is found farther from the prediction than the reference lumen's radius,
   gives no wall observation.
3. Correspondence along normals: each reference point moved by its predicted displacement is
   moved on along the reference outward normal to the nearest point where the frame's blurred
   lumen mask crosses half level going outward, within ``search_fraction`` of the lumen's radius.
   The tracks (or the centroid shift) thus fix the motion along the wall, the image fixes the motion
   across it, which is what the lumen shows.
4. The normal corrections of neighbouring points along the contour must agree: a point whose
   correction differs from its neighbours' median by more than ``max(1 px, 3 x`` their robust
   scatter) is dropped (the median test tracks pass, applied along the contour).

The result is a :class:`~usdeform.optical_flow.TrackedDisplacements` of the reference boundary
points, on the same frames as :func:`usdeform.optical_flow.track_palpation`'s, so that the
regression takes it as observations of their own weight (:func:`usdeform.regression.fit_regression`,
``wall_observations`` and ``wall_weight``). Every threshold is relative to the image's own levels
or the lumen's own size.

The lumen also anchors a model: :func:`correct_vessel_anchored` corrects frames with a
:class:`~usdeform.regression.VesselAnchoredModel`, whose vessel part it places on each frame's own
lumen (found in the corrected frame itself, see :func:`frame_vessel_anchor`).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence

import cv2
import numpy as np
from scipy.ndimage import map_coordinates, median_filter

from . import _core
from ._arrays import frames_array
from .errors import InputError
from .metrics import segment_vessel
from .optical_flow import TrackedDisplacements, _as_uint8_frames, _checked_order
from .regression import VesselAnchor, VesselAnchoredModel
from .stiffness import StiffnessProfile, profiles_array
from .validation import correction_forces

__all__ = ["correct_vessel_anchored", "frame_vessel_anchor", "track_vessel_wall"]

_MASK_BLUR_PX = 1.0  # the mask is blurred by this much so that its half level gives sub-pixel edges
_RAY_STEP_PX = 0.25  # sampling step along a normal ray, pixels
_NEIGHBOURS_ALONG_CONTOUR = 3  # points on each side in the median test along the contour
_NEAREST_TRACKS = 12  # tracks fitted to a wall point's predicted displacement
_GRADIENT_RIDGE = 1e-2  # ridge on the local fit's gradient, relative to the tracks' weighted spread


def _resampled_contour(mask: np.ndarray, spacing_px: float) -> tuple[np.ndarray, np.ndarray]:
    """Points (K, 2) every ``spacing_px`` along the outer contour of ``mask`` (x, y, smoothed) and
    their unit outward normals (K, 2)."""
    contours, _ = cv2.findContours(mask.astype(np.uint8), cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)
    contour = max(contours, key=len)[:, 0].astype(np.float64)
    closed = np.vstack([contour, contour[:1]])
    arc = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(closed, axis=0), axis=1))])
    count = max(16, round(arc[-1] / spacing_px))
    samples = np.linspace(0.0, arc[-1], count, endpoint=False)
    points = np.column_stack([np.interp(samples, arc, closed[:, 0]), np.interp(samples, arc, closed[:, 1])])
    # Pixel-staircase contours have noisy normals: smooth the points over about two samples, circularly.
    kernel = np.array([1.0, 4.0, 6.0, 4.0, 1.0]) / 16.0
    padded = np.vstack([points[-2:], points, points[:2]])
    points = np.column_stack([np.convolve(padded[:, c], kernel, mode="valid") for c in (0, 1)])
    tangent = np.roll(points, -1, axis=0) - np.roll(points, 1, axis=0)
    normal = np.column_stack([tangent[:, 1], -tangent[:, 0]])
    normal /= np.maximum(np.linalg.norm(normal, axis=1, keepdims=True), 1e-12)
    if np.mean(np.sum((points - points.mean(axis=0)) * normal, axis=1)) < 0:
        normal = -normal
    return points, normal


def _outward_crossings(soft_mask: np.ndarray, starts: np.ndarray, normals: np.ndarray, search_px: float) -> np.ndarray:
    """Distance t (pixels) along each normal from each start to the nearest point where
    ``soft_mask`` falls through 0.5 going outward (inside -> outside), within +-``search_px``; NaN
    where there is none."""
    steps = np.arange(-search_px, search_px + _RAY_STEP_PX / 2, _RAY_STEP_PX)
    rays = starts[:, None, :] + steps[None, :, None] * normals[:, None, :]  # (K, S, 2) x, y
    values = map_coordinates(soft_mask, [rays[..., 1], rays[..., 0]], order=1, mode="constant", cval=0.0) - 0.5
    falls = (values[:, :-1] >= 0) & (values[:, 1:] < 0)
    fraction = values[:, :-1] / np.where(falls, values[:, :-1] - values[:, 1:], 1.0)
    crossing = np.where(falls, steps[:-1] + fraction * _RAY_STEP_PX, np.nan)
    nearest = np.argmin(np.where(falls, np.abs(crossing), np.inf), axis=1)
    return crossing[np.arange(len(starts)), nearest]


def _soft_mask(mask: np.ndarray) -> np.ndarray:
    return cv2.GaussianBlur(mask.astype(np.float32), (0, 0), _MASK_BLUR_PX)


def _predicted_displacements(tracked: TrackedDisplacements, step: int, wall_points: np.ndarray) -> np.ndarray | None:
    """Displacement at each wall point at row ``step`` of ``tracked``, from a locally linear fit
    (inverse-distance-squared weighted, slightly ridged gradients) to the nearest valid tracks; None
    without enough valid tracks.

    A linear fit, not a weighted mean: the lumen holds no tracks, so a wall point's nearest tracks
    all lie on its outer side, and their mean displacement is the displacement there, biased by the
    strain times that offset (a pixel and more where the vessel collapses)."""
    keep = tracked.valid[step]
    if np.count_nonzero(keep) < _NEAREST_TRACKS:
        return None
    points, displacements = tracked.points_px[keep], tracked.displacements_px[step, keep]
    distances = np.linalg.norm(wall_points[:, None, :] - points[None, :, :], axis=2)
    nearest = np.argsort(distances, axis=1)[:, :_NEAREST_TRACKS]
    weights = 1.0 / np.maximum(np.take_along_axis(distances, nearest, axis=1), 1.0) ** 2  # (K, n)
    offsets = points[nearest] - wall_points[:, None, :]  # (K, n, 2)
    terms = np.concatenate([np.ones((*offsets.shape[:2], 1)), offsets], axis=2)  # (K, n, 3): 1, dx, dy
    normal = np.einsum("kn,kni,knj->kij", weights, terms, terms)
    ridge = _GRADIENT_RIDGE * np.einsum("kn,kn->k", weights, np.sum(offsets**2, axis=2)) / 2
    normal[:, 1, 1] += ridge
    normal[:, 2, 2] += ridge
    moment = np.einsum("kn,kni,knc->kic", weights, terms, displacements[nearest])
    return np.linalg.solve(normal, moment)[:, 0, :]


def _contour_outliers(corrections: np.ndarray) -> np.ndarray:
    """True where a point's normal correction disagrees with its neighbours' along the (closed) contour."""
    size = 2 * _NEIGHBOURS_ALONG_CONTOUR + 1
    filled = np.where(np.isfinite(corrections), corrections, np.nanmedian(corrections))
    median = median_filter(filled, size=size, mode="wrap")
    scatter = 1.4826 * median_filter(np.abs(filled - median), size=size, mode="wrap")
    return ~(np.abs(corrections - median) <= np.maximum(1.0, 3.0 * scatter))


def track_vessel_wall(
    frames: np.ndarray,
    force: np.ndarray | None = None,
    *,
    tracked: TrackedDisplacements | None = None,
    seed_px: Sequence[float] | None = None,
    spacing_px: float = 2.0,
    search_fraction: float = 0.5,
) -> TrackedDisplacements:
    """Displacements of the lumen boundary from the lowest-force frame to every other frame.

    Parameters
    ----------
    frames : ndarray
        (n, rows, cols) uint8 or float32 B-mode frames of one palpation, n >= 2.
    force : ndarray, optional
        (n,) contact force per frame, N; frames are taken in increasing force from the lowest.
        None: in the order given.
    tracked : TrackedDisplacements, optional
        The tissue tracks of the same frames (:func:`usdeform.optical_flow.track_palpation`); they
        predict the wall's motion along itself. None: the lumen's centroid shift does.
    seed_px : sequence of float, optional
        (x, y) of the lumen in the lowest-force frame, pixels; None: the largest dark region off
        the frame's border.
    spacing_px : float
        Spacing of the wall points along the reference boundary, pixels.
    search_fraction : float
        How far, as a fraction of the reference lumen's equivalent radius, the wall is searched for
        along each normal from its predicted position.

    Returns
    -------
    TrackedDisplacements
        The reference boundary points and their displacements, valid where measured; the frames,
        reference and frame shape as :func:`usdeform.optical_flow.track_palpation` gives them.

    Raises
    ------
    InputError
        Bad arguments, tracks of other frames, or no lumen in the lowest-force frame.
    """
    images = _as_uint8_frames(frames)
    n, rows, cols = images.shape
    order = _checked_order(force, n)
    if not (np.isfinite(spacing_px) and spacing_px > 0):
        raise InputError(f"spacing_px: expected a positive number of pixels, got {spacing_px!r}")
    if not (np.isfinite(search_fraction) and search_fraction > 0):
        raise InputError(f"search_fraction: expected a positive fraction of the lumen radius, got {search_fraction!r}")
    if tracked is not None and (
        not np.array_equal(tracked.frame_indices, order[1:]) or tracked.frame_shape != (rows, cols)
    ):
        raise InputError(
            "tracked: expected the tracks of these frames (the same frame order and frame shape as track_palpation "
            "gives for them)"
        )
    reference = int(order[0])
    try:
        lumen = segment_vessel(images[reference], seed_px).mask
    except InputError as error:
        raise InputError(f"frames[{reference}] (the lowest-force frame): {error}") from None
    points, normals = _resampled_contour(lumen, float(spacing_px))
    radius = float(np.sqrt(lumen.sum() / np.pi))
    search = max(float(search_fraction) * radius, 3.0)
    points = points + np.nan_to_num(_outward_crossings(_soft_mask(lumen), points, normals, 2.0))[:, None] * normals
    points = np.clip(points, 0.0, [cols - 1.0, rows - 1.0])
    centroid = points.mean(axis=0)

    displacements = np.full((n - 1, len(points), 2), np.nan)
    valid = np.zeros((n - 1, len(points)), dtype=bool)
    shift = np.zeros(2)  # the lumen centroid's displacement at the previous frame
    for step in range(n - 1):
        predicted = None if tracked is None else _predicted_displacements(tracked, step, points)
        if predicted is None:
            predicted = np.broadcast_to(shift, points.shape)
        expected_centre = centroid + predicted.mean(axis=0)
        if not (0 <= expected_centre[0] <= cols - 1 and 0 <= expected_centre[1] <= rows - 1):
            continue
        try:
            found = segment_vessel(images[order[step + 1]], expected_centre).mask
        except InputError:
            continue
        found_centre = np.argwhere(found).mean(axis=0)[::-1]
        if np.linalg.norm(found_centre - expected_centre) > radius:
            continue
        corrections = _outward_crossings(_soft_mask(found), points + predicted, normals, search)
        measured = ~_contour_outliers(corrections) & np.isfinite(corrections)
        displacements[step, measured] = predicted[measured] + corrections[measured, None] * normals[measured]
        valid[step] = measured
        shift = found_centre - centroid
    return TrackedDisplacements(
        points_px=points,
        displacements_px=displacements,
        valid=valid,
        frame_indices=order[1:],
        reference_index=reference,
        frame_shape=(rows, cols),
    )


#: Largest change of the lumen's centre and radius, pixels, at which :func:`frame_vessel_anchor` stops.
ANCHOR_TOLERANCE_PX = 0.25
#: Most corrections :func:`frame_vessel_anchor` tries per frame.
ANCHOR_MAX_ITERATIONS = 8


#: Half-width, in the expected lumen's radii, of the square a lumen is searched in when it is expected
#: somewhere (the previous frame's lumen, the previous correction's): the segmentation and its warp then
#: cover a part of the frame; a lumen reaching the square's edge, or none in it, is searched again in the
#: whole frame.
SEARCH_WINDOW_RADII = 2.5

Window = tuple[slice, slice]  # rows, columns of a frame


def _search_window(expected: VesselAnchor, shape: tuple[int, int]) -> Window:
    """The square of :data:`SEARCH_WINDOW_RADII` radii around ``expected``, cut at the frame's edges
    (the whole frame where the square lies outside it)."""
    half = SEARCH_WINDOW_RADII * expected.radius_px
    (x, y), (rows, cols) = expected.centre_px, shape
    row_slice = slice(max(int(np.floor(y - half)), 0), min(int(np.ceil(y + half)) + 1, rows))
    column_slice = slice(max(int(np.floor(x - half)), 0), min(int(np.ceil(x + half)) + 1, cols))
    if row_slice.start >= row_slice.stop or column_slice.start >= column_slice.stop:
        return slice(0, rows), slice(0, cols)
    return row_slice, column_slice


def _lumen(
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
    y, x = np.mgrid[row_slice, column_slice].astype(np.float32)
    field = displacement_on((row_slice, column_slice))
    source_x, source_y = x + field[0].astype(np.float32), y + field[1].astype(np.float32)
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
        return _lumen(frame, displacement_on, seed_px)
    if mask is None:
        return None
    found = VesselAnchor.of_mask(mask)
    return VesselAnchor((found.centre_px[0] + left, found.centre_px[1] + top), found.radius_px)


def _same_lumen(found: VesselAnchor | None, expected: VesselAnchor) -> VesselAnchor | None:
    """``found`` if it overlaps ``expected`` (centres closer than the sum of the radii), else None: a
    dark region elsewhere (a shadow, the lumen pressed shut) is not the lumen followed."""
    if found is None:
        return None
    distance = float(np.hypot(*np.subtract(found.centre_px, expected.centre_px)))
    return found if distance < found.radius_px + expected.radius_px else None


def _searchable_frame(frame: np.ndarray, shape: tuple[int, int], name: str) -> np.ndarray:
    """``frame`` checked as a deformed B-mode frame of ``shape``: uint8, or finite non-negative float32."""
    image = np.asarray(frame)
    if image.dtype not in (np.uint8, np.float32) or image.shape != shape:
        raise InputError(
            f"{name}: expected a {shape[0]} x {shape[1]} uint8 or float32 frame, got {image.dtype} {image.shape}"
        )
    if image.dtype == np.float32 and not (np.all(np.isfinite(image)) and image.min() >= 0):
        raise InputError(f"{name}: B-mode intensities must be finite and non-negative")
    return image


def frame_vessel_anchor(
    frame: np.ndarray,
    force_n: float,
    profile: StiffnessProfile,
    model: VesselAnchoredModel,
    *,
    near: VesselAnchor | None = None,
    clamp_force: bool = False,
) -> VesselAnchor | None:
    """The zero-force lumen of one deformed frame: where the vessel part of ``model`` belongs.

    The lumen is found in the frame corrected by the image part alone (the dark region at or nearest
    to ``near``'s centre, else to the model's reference lumen), then again in the frame corrected with
    the vessel part on the lumen found, until centre and radius change by less than
    :data:`ANCHOR_TOLERANCE_PX` (at most :data:`ANCHOR_MAX_ITERATIONS` corrections). The corrected
    lumen then is the lumen the vessel part was placed on: a fixed point. It converges because the
    vessel part moves the lumen's edge by a fraction of its radius (its collapse), so each step
    shrinks the change by that fraction. A region that does not overlap ``near`` (when given) or the
    previous step's lumen is not taken for the lumen. Each search after the first, and the first when
    ``near`` is given, looks within :data:`SEARCH_WINDOW_RADII` radii of the lumen expected.

    Parameters
    ----------
    frame : ndarray
        (rows, cols) uint8 or non-negative float32 deformed frame of the model's frame shape.
    force_n : float
        Its force, N; in the model's fitted range unless ``clamp_force``.
    profile : StiffnessProfile
        Its stiffness profile.
    model : VesselAnchoredModel
        The model.
    near : VesselAnchor, optional
        Where the lumen is expected (in a sweep: the previous frame's); None: search from the model's
        reference lumen, without the overlap test.
    clamp_force : bool
        Clamp a force outside the fitted range into it, with a warning (default: InputError).

    Returns
    -------
    VesselAnchor or None
        The lumen at zero force, or None where no lumen is found in the frame.
    """
    shape = model.frame_shape
    image = _searchable_frame(frame, shape, "frame")
    force = float(correction_forces(force_n, 1, model, clamp=clamp_force, name="force_n")[0])
    return _zero_force_lumen(image, force, profile, model, model.image_model.displacement(force, profile, shape), near)


def _zero_force_lumen(
    image: np.ndarray,
    force: float,
    profile: StiffnessProfile,
    model: VesselAnchoredModel,
    image_part: np.ndarray,
    near: VesselAnchor | None,
) -> VesselAnchor | None:
    """:func:`frame_vessel_anchor` on a checked frame and force, with the model's image part at that
    force, ``image_part`` (2, rows, cols), already evaluated (the correction warps with it too)."""
    shape = model.frame_shape

    def image_part_on(window: Window) -> np.ndarray:
        return image_part[:, window[0], window[1]]

    def placed_on(lumen: VesselAnchor) -> Callable[[Window], np.ndarray]:
        def field_on(window: Window) -> np.ndarray:
            return image_part_on(window) + model.vessel_displacement(force, profile, shape, lumen, window=window)

        return field_on

    if near is None:
        anchor = _lumen(image, image_part_on, model.reference.centre_px)
    else:
        anchor = _same_lumen(_lumen(image, image_part_on, near.centre_px, _search_window(near, shape)), near)
    for _ in range(ANCHOR_MAX_ITERATIONS):
        if anchor is None:
            return None
        found = _lumen(image, placed_on(anchor), anchor.centre_px, _search_window(anchor, shape))
        found = _same_lumen(found, anchor)
        if found is None:
            return anchor
        change = max(*np.abs(np.subtract(found.centre_px, anchor.centre_px)), abs(found.radius_px - anchor.radius_px))
        anchor = found
        if change < ANCHOR_TOLERANCE_PX:
            break
    return anchor


def _anchors_argument(anchors: Sequence[VesselAnchor | None], n_frames: int) -> list[VesselAnchor | None]:
    """``anchors`` checked: one VesselAnchor or None per frame."""
    given = list(anchors)
    if len(given) != n_frames:
        raise InputError(f"anchors: expected one per frame ({n_frames}), got {len(given)}")
    for index, anchor in enumerate(given):
        if anchor is not None and not isinstance(anchor, VesselAnchor):
            raise InputError(f"anchors[{index}]: expected a VesselAnchor or None, got {type(anchor).__name__}")
    return given


def correct_vessel_anchored(
    frames: np.ndarray,
    forces: np.ndarray | Sequence[float] | float,
    profiles: StiffnessProfile | Sequence[StiffnessProfile] | np.ndarray,
    model: VesselAnchoredModel,
    *,
    fill: float = 0.0,
    clamp_force: bool = False,
    anchors: Sequence[VesselAnchor | None] | None = None,
) -> tuple[np.ndarray, np.ndarray, list[VesselAnchor | None]]:
    """Frames warped back to zero force with a vessel-anchored model, its vessel part on each frame's
    own lumen (:func:`frame_vessel_anchor`, searched where the previous frame's lumen was: the frames
    of a sweep follow the vessel). Where a frame's lumen is not found (a lumen pressed shut, or only
    a dark region that does not overlap the last lumen found), the vessel part stays where the last
    lumen was found, or on the model's reference lumen before any; the region the next lumen may lie
    in then grows by the last lumen's size per frame missed, so that a vessel that moved on while
    unseen is found again.

    Parameters
    ----------
    frames : ndarray
        ``(n_frames, rows, cols)`` or one ``(rows, cols)`` frame, uint8 or float32 (non-negative
        where the lumens are searched), of the model's frame shape.
    forces : float or array_like
        Each frame's force (N), or one for all; in the model's fitted range unless ``clamp_force``.
    profiles : StiffnessProfile, sequence of StiffnessProfile, or ndarray
        One profile for all frames, one per frame, or an ``(n_frames, 3)`` array of ``(c1, c2, c3)``.
    model : VesselAnchoredModel
        The fitted model.
    fill : float
        Value of pixels whose source lies outside the frame.
    clamp_force : bool
        Clamp forces outside the model's fitted range into it, with a warning (default: InputError).
    anchors : sequence of VesselAnchor or None, optional
        One per frame: the lumens to place the vessel part on instead of searching the frames (e.g.
        to warp masks or other images of the same frames as the frames were corrected; None
        entries as for a frame whose lumen is not found).

    Returns
    -------
    corrected : ndarray
        The corrected frames, same shape and dtype as ``frames``.
    valid : ndarray of bool
        True where a pixel's source lies inside its frame.
    anchors : list of VesselAnchor or None
        Each frame's zero-force lumen (None: not found there).
    """
    stack = frames_array(frames)
    n_frames, rows, cols = stack.shape
    if (rows, cols) != model.frame_shape:
        raise InputError(f"frames: {rows} x {cols} pixels, but the model was fitted on {model.frame_shape} frames")
    frame_forces = correction_forces(forces, n_frames, model, clamp=clamp_force)
    frame_profiles = profiles_array(profiles, n_frames)
    given = None if anchors is None else _anchors_argument(anchors, n_frames)
    corrected, valid = np.empty_like(stack), np.empty(stack.shape, dtype=bool)
    found: list[VesselAnchor | None] = []
    previous: VesselAnchor | None = None  # the last lumen found
    missed = 0  # frames since it was found
    for index, frame in enumerate(stack):
        profile = StiffnessProfile(*frame_profiles[index])
        force = float(frame_forces[index])
        image_part = model.image_model.displacement(force, profile, (rows, cols))
        if given is None:
            _searchable_frame(frame, (rows, cols), f"frames[{index}]")
            # The lumen may have moved on while it was not seen: the region it is expected in grows by
            # its size with every frame since.
            near = None if previous is None else VesselAnchor(previous.centre_px, previous.radius_px * (1 + missed))
            anchor = _zero_force_lumen(frame, force, profile, model, image_part, near)
        else:
            anchor = given[index]
        found.append(anchor)
        previous, missed = (anchor, 0) if anchor is not None else (previous, missed + 1)
        field = image_part + model.vessel_displacement(force, profile, (rows, cols), previous or model.reference)
        warped, inside = _core.warp_by_field(frame[None], field[None], fill=float(fill))
        corrected[index], valid[index] = warped[0], inside[0]
    if np.ndim(frames) == 2:
        return corrected[0], valid[0], found
    return corrected, valid, found
