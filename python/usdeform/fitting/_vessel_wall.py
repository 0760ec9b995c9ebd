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

The lumen also anchors a model: :func:`usdeform.correction._vessel.correct_vessel_anchored` places a
:class:`~usdeform.regression.VesselAnchoredModel`'s vessel part on each frame's own lumen
(:func:`usdeform.correction.sweep_lumens` finds it).
"""

from __future__ import annotations

from collections.abc import Sequence

import cv2
import numpy as np
from scipy.ndimage import map_coordinates, median_filter
from scipy.spatial import cKDTree

from ..errors import InputError
from ..metrics import segment_vessel
from ..optical_flow import TrackedDisplacements, as_uint8_frames, force_order

__all__ = ["track_vessel_wall"]

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
    distances, nearest = cKDTree(points).query(wall_points, k=_NEAREST_TRACKS)  # (K, n), nearest first
    weights = 1.0 / np.maximum(distances, 1.0) ** 2  # (K, n)
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
    images = as_uint8_frames(frames)
    n, rows, cols = images.shape
    order = force_order(force, n)
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
