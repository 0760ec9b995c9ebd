"""Pixel displacement during a palpation: Lucas-Kanade tracking on a grid that is right or rejects (paper Sec. III-A).

:func:`track_palpation` measures where the tissue at each point of a regular grid in the lowest-force
(reference) frame has moved in every other frame. The points are tracked between consecutive frames in
increasing force and the motion is chained. Each step starts from an estimate that survives large motion
and decorrelated speckle: normalised-correlation block matching of ~50-pixel patches at half resolution
on a coarse grid, outliers replaced by their neighbours' median (a single step of 40 px, a dropped frame
or a fast press; pyramidal Lucas-Kanade alone locks onto a wrong speckle there and, on real data, kept
tracks of the wrong sign). Lucas-Kanade refines it from the previous frame, then from the latest key
frame, which keeps Lucas-Kanade's small per-step bias from adding up (on simulated palpations it halves
the error at the highest force). Every new key frame passes on the error of the track in its own frame,
so a new one is taken only once the speckle no longer correlates with the key frame's (the median
correlation of the surviving tracks' patches with their key-frame patches falls below
``key_frame_correlation``), or after ``key_frame_interval`` frames: a fixed interval of 5 frames let the
error grow with the frame rate (on simulated palpations against their true motion, the mean axial error
at the highest force in the worst of 12 depth and lateral bands was 0.86 px over 250 frames and 0.67 px
at 0.23 mm rows; key frames on decorrelation brought these to 0.14 and 0.23 px). Where the speckle
decorrelated during the step (the patches around the track correlate less than ``decorrelated_below``),
the random error of a 21-pixel window is large (at the real data's decorrelation, 0.4 px median even for
Lucas-Kanade started at the true position: the second frame's speckle is partly new), and it falls with
the area the estimate draws on. There a wide window refines the track from the key frame, and after the
checks the track's step is replaced by the median step of its 3 x 3 grid neighbourhood. A wide window
spans a strained motion (under 5 % axial strain, 2.5 px across 51 px), which a translation-only window
turns into a random error of its own: the wide window's last refinement therefore lets it stretch and
shear with the tissue (Lucas-Kanade with an affine warp, its correlation that of the warped window), and
so does the small window's wherever the motion since the key frame varies across it by more than
``max_translation_spread_px`` (estimated from the block matching). A track is dropped, for this and all
later frames, when any of these checks fails on a step (:data:`REJECTION_REASONS`, in this order; the
first that fails is counted in ``TrackedDisplacements.rejected``):

* ``left_frame``: the point has left the frame;
* ``texture``: the point has too little texture to track at the start of the step: the square
  root of the smaller eigenvalue of the structure tensor averaged over ``texture_window_px`` (an
  RMS intensity gradient, gray levels per pixel) is below ``min_texture_ratio`` times its median
  over the frame. The anechoic lumen of a vessel has no speckle and fails this;
* ``lucas_kanade_status``: OpenCV's status flag (of any of the step's calls) is 0;
* ``block_matching``: the refined step departs from the block-matching estimate it started from by
  more than that estimate's uncertainty (2 px plus how much the block-matching flow varies across
  one of its patches) and ``block_matching_margin_px``, where refining it again from the estimate
  does not confirm it (Lucas-Kanade left its own evidence for another speckle: on a real compression
  pair of 5 % strain, pyramid levels above the remaining motion moved deep tracks about 20 px away,
  to the wrong sign); or the estimate is itself less certain than ``max_block_matching_uncertainty_px``
  (the blocks there matched noise, and tracks started from them followed it, coherently);
* ``forward_backward``: tracking the new position back to the earlier frame misses the start by
  more than ``max_forward_backward_px``;
* ``lucas_kanade_error``: the Lucas-Kanade error of that backward call (mean absolute
  difference of the two windows, gray levels) exceeds ``max_lk_error``;
* ``correlation``: the normalised correlation of the ``window_px`` patches around the point
  before and after the step (where an affine warp refined the track: of the key frame's window,
  ``wide_window_px`` for decorrelated tracks, and its warped match) is below ``min_correlation``;
* ``neighbours``: the step disagrees with the steps of the surviving tracks within two grid
  spacings: its distance from their median exceeds ``max_neighbour_deviation_px``, or
  ``max_neighbour_residual`` times their own scatter about it (the normalised median test of
  particle image velocimetry, Westerweel & Scarano 2005, with a 0.1 px noise level).

:func:`boundary_constraints` gives the paper's eq. 10 displacements of the top and bottom image rows
in the same :class:`TrackedDisplacements` structure, so that the two can be joined
(:meth:`TrackedDisplacements.with_boundary`, :func:`concatenate`) into the measured displacements
D^m of the regression (paper eq. 11).

Coordinates: points are (x, y) = (column, row) in pixels, origin at the top-left pixel's centre, y
pointing down into the tissue; displacements are (lateral, axial) = (dx, dy) in pixels.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from types import MappingProxyType

import cv2
import numpy as np

from .. import _core
from .._arrays import readonly as _readonly
from ..errors import InputError

__all__ = ["REJECTION_REASONS", "TrackedDisplacements", "boundary_constraints", "concatenate", "track_palpation"]

REJECTION_REASONS = (
    "left_frame",
    "texture",
    "lucas_kanade_status",
    "block_matching",
    "forward_backward",
    "lucas_kanade_error",
    "correlation",
    "neighbours",
)
"""Why a track is dropped, in the order the checks are applied (see the module docstring)."""

_LK_CRITERIA = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 30, 0.01)
_COARSE_PATCH = 25  # side of the block-matching patches at half resolution, pixels
_COARSE_SPACING = 12  # spacing of the block-matching grid at half resolution, pixels
_MIN_SEARCH_PX = 8.0  # smallest block-matching search range, full-resolution pixels
_ESCALATE_EDGE_FRACTION = 0.1  # search the whole range again when more peaks than this lie on the edge
_COARSE_MIN_PEAK = 0.2  # weaker correlation peaks are no match (unrelated 25 x 25 patches reach about 0.2)
_COARSE_UNCERTAINTY_PX = 2.0  # error bound of a matched block's motion: one half-resolution pixel either way


@dataclass(frozen=True, eq=False)
class TrackedDisplacements:
    """Displacements of N points from the reference frame to M other frames, validated on construction.

    Attributes:
        points_px: (N, 2) float64 positions (x, y) of the points in the reference frame, pixels.
        displacements_px: (M, N, 2) float64 displacement (lateral dx, axial dy) of each point from
            the reference frame to frame m, pixels; NaN where not valid.
        valid: (M, N) bool, True where the displacement was measured reliably.
        frame_indices: (M,) int64 index, in the input frames, of the frame each row belongs to.
        reference_index: index, in the input frames, of the reference (lowest-force) frame.
        frame_shape: (rows, cols) of the frames, pixels.
        rejected: reason (one of :data:`REJECTION_REASONS`) -> (M,) int64 number of tracks dropped
            at frame m for that reason (the first failed check counts); empty for points that were
            not tracked (such as the boundary rows).
        dropped_reason: (N,) int64 index into :data:`REJECTION_REASONS` of the check that dropped
            each point, -1 where the point was kept to the last frame (default: all -1).
        dropped_at: (N,) int64 row m of the frame at which each point was dropped, -1 where it was
            kept (default: all -1).

    The arrays are stored as read-only copies.
    """

    points_px: np.ndarray
    displacements_px: np.ndarray
    valid: np.ndarray
    frame_indices: np.ndarray
    reference_index: int
    frame_shape: tuple[int, int]
    rejected: Mapping[str, np.ndarray] = field(default_factory=dict)
    dropped_reason: np.ndarray | None = None
    dropped_at: np.ndarray | None = None

    def __post_init__(self) -> None:
        points = np.array(self.points_px, dtype=np.float64)
        if points.ndim != 2 or points.shape[1] != 2:
            raise InputError(f"points_px: expected shape (N, 2), got {points.shape}")
        frame_indices = np.array(self.frame_indices, dtype=np.int64)
        if frame_indices.ndim != 1:
            raise InputError(f"frame_indices: expected shape (M,), got {frame_indices.shape}")
        m, n = len(frame_indices), len(points)
        displacements = np.array(self.displacements_px, dtype=np.float64)
        if displacements.shape != (m, n, 2):
            raise InputError(f"displacements_px: expected shape {(m, n, 2)}, got {displacements.shape}")
        valid = np.array(self.valid)
        if valid.dtype != np.bool_ or valid.shape != (m, n):
            raise InputError(f"valid: expected a bool array of shape {(m, n)}, got {valid.dtype} {valid.shape}")
        if not np.all(np.isfinite(points)):
            raise InputError("points_px: contains non-finite values")
        if not np.all(np.isfinite(displacements[valid])):
            raise InputError("displacements_px: non-finite value where valid is True")
        if len(self.frame_shape) != 2 or min(self.frame_shape) < 1:
            raise InputError(f"frame_shape: expected (rows, cols), got {self.frame_shape!r}")
        displacements[~valid] = np.nan
        rejected = {}
        for reason, counts in self.rejected.items():
            if reason not in REJECTION_REASONS:
                raise InputError(f"rejected: unknown reason {reason!r}; expected one of {REJECTION_REASONS}")
            counts = np.array(counts, dtype=np.int64)
            if counts.shape != (m,) or np.any(counts < 0):
                raise InputError(f"rejected[{reason!r}]: expected ({m},) non-negative counts, got shape {counts.shape}")
            rejected[reason] = _readonly(counts)
        object.__setattr__(self, "rejected", MappingProxyType(rejected))
        per_point = {}
        for name, upper in (("dropped_reason", len(REJECTION_REASONS)), ("dropped_at", m)):
            given = getattr(self, name)
            values = np.full(n, -1, dtype=np.int64) if given is None else np.array(given, dtype=np.int64)
            if values.shape != (n,) or np.any(values < -1) or np.any(values >= upper):
                raise InputError(f"{name}: expected ({n},) integers in [-1, {upper}), got shape {values.shape}")
            per_point[name] = values
        if np.any((per_point["dropped_reason"] < 0) != (per_point["dropped_at"] < 0)):
            raise InputError("dropped_reason, dropped_at: a point has one but not the other")
        if m and np.any(valid[-1, per_point["dropped_at"] >= 0]):
            raise InputError("dropped_at: a dropped point is valid in the last frame")
        for name, values in per_point.items():
            object.__setattr__(self, name, _readonly(values))
        object.__setattr__(self, "points_px", _readonly(points))
        object.__setattr__(self, "displacements_px", _readonly(displacements))
        object.__setattr__(self, "valid", _readonly(valid))
        object.__setattr__(self, "frame_indices", _readonly(frame_indices))
        object.__setattr__(self, "reference_index", int(self.reference_index))
        object.__setattr__(self, "frame_shape", (int(self.frame_shape[0]), int(self.frame_shape[1])))

    @property
    def kept_per_frame(self) -> np.ndarray:
        """(M,) int: number of valid points in each frame."""
        return self.valid.sum(axis=1)

    @property
    def kept_fraction(self) -> float:
        """Fraction of the N points valid in every one of the M frames (kept to the highest force)."""
        return float(self.valid.all(axis=0).mean()) if self.valid.size else 0.0

    def rejection_summary(self) -> dict[str, int]:
        """Reason -> number of tracks dropped for it over all frames (the reasons that dropped any)."""
        return {reason: int(counts.sum()) for reason, counts in self.rejected.items() if counts.sum() > 0}

    def with_boundary(
        self, probe_displacement_mm: np.ndarray, flexible_layer_mm: float, n_points: int
    ) -> TrackedDisplacements:
        """These points followed by the eq. 10 boundary points (see :func:`boundary_constraints`).

        ``probe_displacement_mm``: (n,) lambda_z of every input frame, mm (for example
        ``recording.probe_displacement``); the boundary uses each frame's lambda_z minus the
        reference frame's.
        """
        lambdas = np.asarray(probe_displacement_mm, dtype=np.float64)
        needed = max(int(self.frame_indices.max(initial=-1)), self.reference_index) + 1
        if lambdas.ndim != 1 or len(lambdas) < needed:
            raise InputError(
                f"probe_displacement_mm: expected one value per input frame (at least {needed}), "
                f"got shape {lambdas.shape}"
            )
        rows, cols = self.frame_shape
        boundary = boundary_constraints(
            rows,
            cols,
            lambdas[self.frame_indices] - lambdas[self.reference_index],
            flexible_layer_mm,
            n_points,
            frame_indices=self.frame_indices,
            reference_index=self.reference_index,
        )
        return concatenate([self, boundary])


def concatenate(parts: Sequence[TrackedDisplacements]) -> TrackedDisplacements:
    """Join point sets measured on the same frames (same frame_indices, reference_index, frame_shape)."""
    if len(parts) == 0:
        raise InputError("parts: expected at least one TrackedDisplacements")
    first = parts[0]
    for position, part in enumerate(parts):
        if not isinstance(part, TrackedDisplacements):
            raise InputError(f"parts[{position}]: expected a TrackedDisplacements, got {type(part).__name__}")
        if (
            not np.array_equal(part.frame_indices, first.frame_indices)
            or part.reference_index != first.reference_index
            or part.frame_shape != first.frame_shape
        ):
            raise InputError(
                f"parts[{position}]: frame_indices, reference_index and frame_shape must match those of parts[0]"
            )
    return TrackedDisplacements(
        points_px=np.concatenate([part.points_px for part in parts]),
        displacements_px=np.concatenate([part.displacements_px for part in parts], axis=1),
        valid=np.concatenate([part.valid for part in parts], axis=1),
        frame_indices=first.frame_indices,
        reference_index=first.reference_index,
        frame_shape=first.frame_shape,
        rejected={
            reason: np.sum([part.rejected[reason] for part in parts if reason in part.rejected], axis=0)
            for reason in REJECTION_REASONS
            if any(reason in part.rejected for part in parts)
        },
        dropped_reason=np.concatenate([np.asarray(part.dropped_reason) for part in parts]),
        dropped_at=np.concatenate([np.asarray(part.dropped_at) for part in parts]),
    )


def boundary_constraints(
    rows: int,
    cols: int,
    probe_displacement_mm: np.ndarray,
    flexible_layer_mm: float,
    n_points: int,
    *,
    frame_indices: np.ndarray | None = None,
    reference_index: int = 0,
) -> TrackedDisplacements:
    """The boundary displacements of paper eq. 10 on ``n_points`` columns evenly spaced over the image.

    Top row (y = 0, under the probe face): displacement [0, 0]. Bottom row (y = rows - 1):
    [0, -(lambda_z / L_T) * (rows - 1)] pixels: the tissue at image depth y moves towards the probe
    by lambda_z * y / L_T. The paper writes +lambda_z / L_T * L_I with its axial displacement positive
    towards the probe; our y axis points down into the tissue, so the same motion is negative.

    Args:
        rows, cols: frame size, pixels.
        probe_displacement_mm: (M,) lambda_z of each frame minus that of the reference frame, mm.
        flexible_layer_mm: thickness L_T of the flexible layer, mm.
        n_points: number of points on each of the two rows (2 * n_points points in all).
        frame_indices: (M,) input-frame index of each frame; default ``1..M`` (frame 0 the reference).
        reference_index: input-frame index of the reference frame.
    """
    if int(rows) != rows or int(cols) != cols or rows < 2 or cols < 1:
        raise InputError(f"rows, cols: expected integers with rows >= 2 and cols >= 1, got {rows}, {cols}")
    if int(n_points) != n_points or n_points < 1:
        raise InputError(f"n_points: expected a positive integer, got {n_points!r}")
    if not (np.isfinite(flexible_layer_mm) and flexible_layer_mm > 0):
        raise InputError(f"flexible_layer_mm: expected a positive thickness in mm, got {flexible_layer_mm!r}")
    lambdas = np.asarray(probe_displacement_mm, dtype=np.float64)
    if lambdas.ndim != 1 or not np.all(np.isfinite(lambdas)):
        raise InputError(f"probe_displacement_mm: expected a finite (M,) array in mm, got shape {lambdas.shape}")
    m = len(lambdas)
    frame_indices = np.arange(1, m + 1) if frame_indices is None else np.asarray(frame_indices)
    if frame_indices.shape != (m,):
        raise InputError(f"frame_indices: expected shape {(m,)} like probe_displacement_mm, got {frame_indices.shape}")
    rows, cols, n_points = int(rows), int(cols), int(n_points)
    xs = np.linspace(0.0, cols - 1.0, n_points)
    top = np.column_stack([xs, np.zeros(n_points)])
    bottom = np.column_stack([xs, np.full(n_points, rows - 1.0)])
    points = np.concatenate([top, bottom])
    displacements = np.zeros((m, 2 * n_points, 2))
    displacements[:, n_points:, 1] = -(lambdas / flexible_layer_mm * (rows - 1))[:, None]
    return TrackedDisplacements(
        points_px=points,
        displacements_px=displacements,
        valid=np.ones((m, 2 * n_points), dtype=bool),
        frame_indices=frame_indices,
        reference_index=reference_index,
        frame_shape=(rows, cols),
    )


def _as_uint8_frames(frames: np.ndarray) -> np.ndarray:
    """Check ``frames`` and return them as C-contiguous uint8 (n, rows, cols).

    float32 frames are scaled linearly from the stack's [min, max] to [0, 255].
    """
    frames = np.asarray(frames)
    if frames.dtype not in (np.uint8, np.float32):
        raise InputError(f"frames: expected dtype uint8 or float32, got {frames.dtype}")
    if frames.ndim != 3:
        raise InputError(f"frames: expected shape (n, rows, cols), got {frames.shape}")
    if frames.shape[0] < 2:
        raise InputError(f"frames: need at least 2 frames to track, got {frames.shape[0]}")
    if frames.dtype == np.uint8:
        return np.ascontiguousarray(frames)
    if not np.all(np.isfinite(frames)):
        raise InputError(
            f"frames: non-finite value at frame {int(np.flatnonzero(~np.isfinite(frames).all(axis=(1, 2)))[0])}"
        )
    low, high = float(frames.min()), float(frames.max())
    scale = 255.0 / (high - low) if high > low else 0.0
    return np.ascontiguousarray(np.rint((frames - low) * scale), dtype=np.uint8)


def _texture_map(frame: np.ndarray, window_px: int) -> np.ndarray:
    """(rows, cols) float32 sqrt of the smaller eigenvalue of the structure tensor averaged over a
    ``window_px`` square: the RMS intensity gradient along the least-textured direction, gray levels / px."""
    image = frame.astype(np.float32)
    gx = np.asarray(cv2.Sobel(image, cv2.CV_32F, 1, 0, ksize=3), dtype=np.float32) / np.float32(8.0)
    gy = np.asarray(cv2.Sobel(image, cv2.CV_32F, 0, 1, ksize=3), dtype=np.float32) / np.float32(8.0)
    size = (window_px, window_px)
    jxx = cv2.boxFilter(np.multiply(gx, gx), -1, size)
    jyy = cv2.boxFilter(np.multiply(gy, gy), -1, size)
    jxy = cv2.boxFilter(np.multiply(gx, gy), -1, size)
    smaller = 0.5 * (jxx + jyy) - np.sqrt(0.25 * (jxx - jyy) ** 2 + jxy**2)
    return np.sqrt(np.maximum(smaller, 0.0))


def _lucas_kanade(
    before: np.ndarray,
    after: np.ndarray,
    points: np.ndarray,
    initial: np.ndarray | None,
    window_px: tuple[int, int],
    pyramid_levels: int,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Pyramidal Lucas-Kanade from ``before`` to ``after`` of (N, 1, 2) float32 (x, y) points, starting
    at ``initial`` (N, 1, 2) if given, with a (width, height) window. Returns the tracked points
    (N, 1, 2), status (N,) and error (N,; infinite where a point was lost)."""
    tracked, status, error = cv2.calcOpticalFlowPyrLK(
        before,
        after,
        points,
        (points if initial is None else initial).copy(),
        winSize=window_px,
        maxLevel=pyramid_levels,
        criteria=_LK_CRITERIA,
        flags=0 if initial is None else cv2.OPTFLOW_USE_INITIAL_FLOW,
    )
    found = np.asarray(status).ravel() == 1
    # OpenCV leaves the error of a lost point uninitialised (at times a NaN, which numpy warns about when the
    # array is copied): infinite instead
    return np.asarray(tracked), found, np.where(found, np.asarray(error).ravel(), np.inf)


def _half_resolution(frame: np.ndarray) -> np.ndarray:
    """The frame at half resolution (2 x 2 pixel means), float32: half-resolution pixel (u, v) covers
    full-resolution pixels 2u..2u+1, so its centre is at (2u + 0.5, 2v + 0.5)."""
    return np.asarray(
        cv2.resize(frame, (frame.shape[1] // 2, frame.shape[0] // 2), interpolation=cv2.INTER_AREA), dtype=np.float32
    )


def _parabola_peak(below: float, peak: float, above: float) -> float:
    """Subpixel offset (in (-0.5, 0.5)) of the maximum of a parabola through three equally spaced samples."""
    curvature = below - 2.0 * peak + above
    return 0.0 if curvature >= 0 else min(max(0.5 * float(below - above) / float(curvature), -0.5), 0.5)


@dataclass(frozen=True)
class _CoarseFlow:
    """Block-matching displacement on a regular grid of the half-resolution frame.

    ``origin`` and ``spacing``: full-resolution (x, y) of grid node (0, 0) and the node spacing,
    pixels; ``flow``: (grid rows, grid cols, 2) float32 (dx, dy) at the nodes, full-resolution pixels.
    """

    origin: tuple[float, float]
    spacing: float
    flow: np.ndarray
    at_search_edge: float = 0.0  # fraction of the matched nodes whose peak lies on the edge of the search range
    matched: bool = True  # False where no block matched (a frame smaller than a patch, or no texture)

    def _sample(self, values: np.ndarray, points: np.ndarray) -> np.ndarray:
        """(N, C) bilinear samples of the (grid rows, grid cols, C) node ``values`` at (N, 2)
        full-resolution (x, y) points, edge values beyond the grid."""
        # OpenCV maps have fewer than 32767 rows and columns: lay the points out in rows of 1024.
        padded = np.zeros((-(-len(points) // 1024) * 1024, 2), dtype=np.float32)
        padded[: len(points)] = (points - np.asarray(self.origin)) / self.spacing
        map_x, map_y = (padded[:, i].reshape(-1, 1024) for i in (0, 1))
        sampled = cv2.remap(values, map_x, map_y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
        return np.asarray(sampled, dtype=np.float32).reshape(len(padded), -1)[: len(points)]

    def at(self, points: np.ndarray) -> np.ndarray:
        """(N, 2) bilinearly interpolated flow at (N, 2) full-resolution (x, y) points; beyond the grid
        (the frame's margins, which no patch centre reaches) continued linearly with the edge's gradient,
        as a compression's displacement grows with depth."""
        flow = self._sample(self.flow, points)
        grid = (np.asarray(points, dtype=np.float64) - np.asarray(self.origin)) / self.spacing
        for axis, column in ((1, 0), (0, 1)):  # the node axis and the (x, y) column it runs along
            nodes = self.flow.shape[axis]
            beyond = grid[:, column] - np.clip(grid[:, column], 0.0, nodes - 1.0)
            if nodes > 1 and np.any(beyond):
                gradient = np.gradient(self.flow, axis=axis)  # per node spacing
                flow += (self._sample(gradient, points) * beyond[:, None]).astype(np.float32)
        return flow

    def spread_at(self, points: np.ndarray, window_px: tuple[int, int]) -> np.ndarray:
        """(N,) how much the flow varies across a (width, height) window at (N, 2) (x, y) points, pixels:
        the larger over (dx, dy) of |d/dx| (width - 1) + |d/dy| (height - 1), the derivatives by
        differences between grid nodes (the scale of the block-matching patches, so a structure much
        smaller than them does not count)."""
        spread = np.zeros(self.flow.shape, dtype=np.float32)
        for axis, side in ((1, window_px[0]), (0, window_px[1])):
            if self.flow.shape[axis] > 1:
                spread += np.abs(np.gradient(self.flow, self.spacing, axis=axis)) * np.float32(side - 1)
        return self._sample(spread, points).max(axis=1)

    def uncertainty_at(self, points: np.ndarray) -> np.ndarray:
        """(N,) error bound of the flow at (N, 2) (x, y) points, pixels: ``_COARSE_UNCERTAINTY_PX`` plus
        how much the flow varies across a block-matching patch there (a strained patch's peak lies
        anywhere within that differential motion); infinite where no block matched."""
        if not self.matched:
            return np.full(len(points), np.inf)
        patch = 2 * _COARSE_PATCH
        return _COARSE_UNCERTAINTY_PX + self.spread_at(points, (patch, patch)).astype(np.float64)


def _coarse_flow(before: np.ndarray, after: np.ndarray, search_px: float) -> _CoarseFlow:
    """Motion from ``before`` to ``after`` by normalised-correlation block matching at half resolution.

    Patches of ``_COARSE_PATCH`` half-resolution pixels (about 50 full-resolution pixels: large
    enough that decorrelated speckle still has one clear correlation peak) on a grid
    ``_COARSE_SPACING`` apart are searched over +-``search_px`` full-resolution pixels; the peak is
    refined to subpixel by a parabola. Nodes whose peak is weak (below ``_COARSE_MIN_PEAK``: no
    texture, such as a lumen) or that fail the normalised median test against their 3 x 3
    neighbours (Westerweel & Scarano 2005, Exp. Fluids 39:1096, threshold 2, noise level 0.1 px)
    take their neighbours' median. We write this ourselves rather than use OpenCV's dense flows:
    on simulated pairs with 40-pixel steps, DIS (medium preset) and Farneback (31 px, 5 levels)
    left 19-33 % and 27-36 % of the points more than 3 px wrong, this 0-0.9 %
    (benches/bench_tracking.py).
    """
    small_before, small_after = _half_resolution(before), _half_resolution(after)
    rows, cols = small_before.shape
    half = _COARSE_PATCH // 2
    search = int(np.ceil(search_px / 2.0))
    ys = np.arange(half, rows - half, _COARSE_SPACING)
    xs = np.arange(half, cols - half, _COARSE_SPACING)
    if len(ys) == 0 or len(xs) == 0:  # a frame smaller than one patch: no coarse motion, LK alone
        return _CoarseFlow((0.0, 0.0), 1.0, np.zeros((1, 1, 2), dtype=np.float32), matched=False)
    padded = cv2.copyMakeBorder(small_after, search, search, search, search, cv2.BORDER_REPLICATE)
    flow = np.zeros((len(ys), len(xs), 2), dtype=np.float32)
    peak = np.zeros((len(ys), len(xs)), dtype=np.float32)
    on_edge = np.zeros((len(ys), len(xs)), dtype=bool)
    for i, y in enumerate(ys):
        for j, x in enumerate(xs):
            patch = small_before[y - half : y + half + 1, x - half : x + half + 1]
            region = padded[y - half : y + half + 1 + 2 * search, x - half : x + half + 1 + 2 * search]
            score = cv2.matchTemplate(region, patch, cv2.TM_CCOEFF_NORMED)
            _, best, _, (col, row) = cv2.minMaxLoc(score)
            dx = col + (_parabola_peak(score[row, col - 1], best, score[row, col + 1]) if 0 < col < 2 * search else 0.0)
            dy = row + (_parabola_peak(score[row - 1, col], best, score[row + 1, col]) if 0 < row < 2 * search else 0.0)
            flow[i, j] = (2.0 * (dx - search), 2.0 * (dy - search))
            peak[i, j] = best
            on_edge[i, j] = min(col, row) == 0 or max(col, row) == 2 * search
    matched = peak >= _COARSE_MIN_PEAK
    flow[~matched] = np.nan
    for _ in range(2):
        median, residual = _normalised_median_test(flow, 1, 0.1)
        replace = ~(residual <= 2.0) & np.isfinite(median).all(axis=2)  # outliers and missing nodes
        flow[replace] = median[replace]
    flow[np.isnan(flow)] = 0.0
    edge_fraction = float(on_edge[matched].mean()) if matched.any() else 0.0
    origin = (2.0 * xs[0] + 0.5, 2.0 * ys[0] + 0.5)
    return _CoarseFlow(origin, 2.0 * _COARSE_SPACING, flow, edge_fraction, bool(matched.any()))


def _neighbourhoods(values: np.ndarray, radius: int) -> np.ndarray:
    """(rows, cols, 2, (2 radius + 1)^2) view of the vectors of a (rows, cols, 2) grid in each node's
    (2 radius + 1)^2 neighbourhood (the node itself in the middle), NaN beyond the grid."""
    size = 2 * radius + 1
    padded = np.pad(values, ((radius, radius), (radius, radius), (0, 0)), constant_values=np.nan)
    return np.lib.stride_tricks.sliding_window_view(padded, (size, size), axis=(0, 1)).reshape(
        (*values.shape, size * size)
    )


def _nanmedian(values: np.ndarray) -> np.ndarray:
    """Median over the last axis ignoring NaN (NaN where all are NaN): ``np.nanmedian`` without its
    masked-array path, which costs milliseconds per call on the short axes of a neighbourhood."""
    ordered = np.sort(values, axis=-1)  # NaN sorts last
    count = np.count_nonzero(~np.isnan(values), axis=-1)
    lower = np.take_along_axis(ordered, np.maximum((count - 1) // 2, 0)[..., None], axis=-1)[..., 0]
    upper = np.take_along_axis(ordered, (count // 2)[..., None], axis=-1)[..., 0]
    return np.where(count > 0, 0.5 * (lower + upper), np.nan)


def _normalised_median_test(values: np.ndarray, radius: int, noise_px: float) -> tuple[np.ndarray, np.ndarray]:
    """The normalised median test of particle image velocimetry (Westerweel & Scarano 2005, Exp. Fluids 39:1096).

    For a (rows, cols, 2) grid of vectors (NaN: missing), the median u_m over each node's
    (2 radius + 1)^2 neighbourhood without the node itself and the residual
    |u - u_m| / (median_i |u_i - u_m| + noise_px) of the node's vector u against its neighbours u_i:
    the distance from the neighbours' median in units of their own scatter. Returns the medians
    (rows, cols, 2) and residuals (rows, cols), NaN where the node or all its neighbours are missing.
    """
    size = 2 * radius + 1
    neighbours = np.delete(_neighbourhoods(values, radius), size * size // 2, axis=-1)
    median = _nanmedian(neighbours)
    scatter = _nanmedian(np.linalg.norm(neighbours - median[..., None], axis=2))
    return median, np.linalg.norm(values - median, axis=-1) / (scatter + noise_px)


def _sample_patches(image: np.ndarray, map_x: np.ndarray, map_y: np.ndarray) -> np.ndarray:
    """(N, M) float32 bilinear samples of ``image`` at the (N, M) subpixel points (``map_x``, ``map_y``),
    the edge replicated beyond the frame. One patch per map row, in chunks: OpenCV maps have fewer
    than 32767 rows and columns."""
    chunk = 16384
    parts = [
        cv2.remap(
            image,
            np.ascontiguousarray(map_x[first : first + chunk], dtype=np.float32),
            np.ascontiguousarray(map_y[first : first + chunk], dtype=np.float32),
            cv2.INTER_LINEAR,
            borderMode=cv2.BORDER_REPLICATE,
        ).reshape(-1, map_x.shape[1])
        for first in range(0, len(map_x), chunk)
    ]
    return np.concatenate(parts).astype(np.float32, copy=False) if parts else np.zeros(map_x.shape, np.float32)


def _window_offsets(window_px: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
    """(M,) float32 x and y offsets of the pixels of a (width, height) window from its centre, row by row."""
    width, height = window_px
    y_offsets, x_offsets = np.mgrid[-(height // 2) : height // 2 + 1, -(width // 2) : width // 2 + 1]
    return x_offsets.ravel().astype(np.float32), y_offsets.ravel().astype(np.float32)


def _patch_correlation(
    before: np.ndarray, after: np.ndarray, start: np.ndarray, end: np.ndarray, window_px: tuple[int, int]
) -> np.ndarray:
    """(N,) normalised correlation of the (width, height) ``window_px`` patches of ``before`` centred
    on the (N, 2) subpixel points ``start`` and of ``after`` centred on ``end`` (bilinear samples)."""
    x_offsets, y_offsets = _window_offsets(window_px)

    def patches(image: np.ndarray, centres: np.ndarray) -> np.ndarray:
        values = _sample_patches(image, centres[:, 0, None] + x_offsets, centres[:, 1, None] + y_offsets)
        return values - values.mean(axis=1, keepdims=True)

    first, second = patches(before, start), patches(after, end)
    products = np.einsum("ij,ij->i", first, second)
    norms = np.sqrt(np.einsum("ij,ij->i", first, first) * np.einsum("ij,ij->i", second, second))
    return np.where(norms > 0, products / np.maximum(norms, 1e-12), 0.0)


def _affine_lucas_kanade(
    before: np.ndarray,
    after: np.ndarray,
    start: np.ndarray,
    initial: np.ndarray,
    window_px: tuple[int, int],
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Lucas-Kanade with an affine warp of the window: where ``before``'s (width, height) window around
    each of the (N, 2) float32 points ``start`` lies in ``after``, starting at ``initial`` (N, 2).

    The window may stretch and shear (six parameters: the step and the local displacement gradient),
    as the tissue under it does: under 5-9 % axial strain a 51-pixel window spans 2.5-4.5 px of
    differential motion, which OpenCV's translation-only Lucas-Kanade turns into a random error
    (benches/bench_tracking.py). Inverse compositional Gauss-Newton (Baker & Matthews 2004, IJCV
    56:221) on zero-mean windows (blind to a change of brightness), until the step changes by less
    than ``_LK_CRITERIA``'s epsilon or after its iteration count. The window is cut where it leaves
    ``before`` or, warped, ``after`` (no replicated edge). We write it ourselves: OpenCV's
    Lucas-Kanade is translation-only and its ECC alignment (``cv2.findTransformECC``) aligns one
    window per call, too slow for a thousand windows per frame. The kernel is
    ``_core.affine_lucas_kanade`` (exact bilinear samples, windows in parallel; its NumPy twin is
    ``usdeform.reference.affine_lucas_kanade``); the gradients of ``before`` are OpenCV's Scharr.

    Returns the tracked points (N, 2) float32 (``initial`` where not ok), (N,) True where the
    window's texture determines all six parameters, the result is finite and moved less than half
    the window's smaller side from ``initial``, and the (N,) normalised correlation of the window
    and its warped match (0 where not ok).
    """
    image = before.astype(np.float32)
    gradient_x, gradient_y = (
        np.asarray(cv2.Scharr(image, cv2.CV_32F, dx, 1 - dx, scale=1.0 / 32.0), dtype=np.float32) for dx in (1, 0)
    )
    start, initial = (np.ascontiguousarray(points, dtype=np.float32) for points in (start, initial))
    tracked, ok, correlation = initial.copy(), np.zeros(len(initial), dtype=bool), np.zeros(len(initial))
    # The kernel refuses points that are not finite: their windows are not ok and stay where they are.
    finite = np.isfinite(start).all(axis=1) & np.isfinite(initial).all(axis=1)
    _, max_iterations, epsilon = _LK_CRITERIA
    tracked[finite], ok[finite], correlation[finite] = _core.affine_lucas_kanade(
        image,
        gradient_x,
        gradient_y,
        np.ascontiguousarray(after, dtype=np.float32),
        start[finite],
        initial[finite],
        (int(window_px[0]), int(window_px[1])),
        max_iterations=int(max_iterations),
        epsilon=float(epsilon),
    )
    return tracked, ok, correlation


def _pyramid_levels(remaining_px: float, window_px: tuple[int, int]) -> int:
    """Fewest pyramid levels for Lucas-Kanade to reach a motion of ``remaining_px`` pixels from its start:
    a window converges over about a quarter of its smaller side, and each level doubles that. A level
    more than the motion needs lets the coarse, smoothed image pull the track onto another speckle."""
    reach_px = min(window_px) / 4.0
    return max(0, int(np.ceil(np.log2(remaining_px / reach_px)))) if remaining_px > reach_px else 0


def _grid_points(rows: int, cols: int, spacing_px: float, border_px: float) -> tuple[np.ndarray, tuple[int, int]]:
    """(N, 2) float64 (x, y) points of a regular grid, at least ``border_px`` from the frame's edges,
    row by row, and the grid's (rows, cols)."""
    xs = np.arange(border_px, cols - 1 - border_px + 1e-9, spacing_px)
    ys = np.arange(border_px, rows - 1 - border_px + 1e-9, spacing_px)
    if len(xs) == 0 or len(ys) == 0:
        raise InputError(
            f"grid_spacing_px={spacing_px}, border_px={border_px}: no grid point fits in a {rows} x {cols} frame"
        )
    grid_y, grid_x = np.meshgrid(ys, xs, indexing="ij")
    return np.column_stack([grid_x.ravel(), grid_y.ravel()]), (len(ys), len(xs))


def _window_sides(window_px: int | tuple[int, int], name: str) -> tuple[int, int]:
    """(width, height) of a window given as one odd side or an odd (width, height) pair; InputError otherwise."""
    sides = (window_px, window_px) if isinstance(window_px, int | np.integer) else tuple(window_px)
    if len(sides) != 2 or not all(isinstance(side, int | np.integer) and side >= 3 and side % 2 == 1 for side in sides):
        raise InputError(f"{name}: expected an odd integer >= 3 or a (width, height) pair of them, got {window_px!r}")
    return int(sides[0]), int(sides[1])


def _checked_order(force: np.ndarray | None, n: int) -> np.ndarray:
    """(n,) indices of the frames in increasing force (stable), or 0..n-1 without a force."""
    if force is None:
        return np.arange(n)
    force = np.asarray(force, dtype=np.float64)
    if force.shape != (n,):
        raise InputError(f"force: expected one value per frame, shape {(n,)}, got {force.shape}")
    if not np.all(np.isfinite(force)):
        raise InputError(f"force: non-finite value at frame {int(np.flatnonzero(~np.isfinite(force))[0])}")
    return np.argsort(force, kind="stable")


def track_palpation(
    frames: np.ndarray,
    force: np.ndarray | None = None,
    *,
    grid_spacing_px: float = 8.0,
    border_px: float | None = None,
    window_px: int | tuple[int, int] = 21,
    wide_window_px: int | tuple[int, int] = 51,
    decorrelated_below: float = 0.7,
    max_translation_spread_px: float = 0.5,
    pyramid_levels: int | None = None,
    key_frame_interval: int = 25,
    key_frame_correlation: float = 0.7,
    max_step_px: float = 48.0,
    block_matching_margin_px: float = 1.0,
    max_block_matching_uncertainty_px: float = 16.0,
    max_forward_backward_px: float = 1.0,
    max_lk_error: float = 30.0,
    texture_window_px: int = 9,
    min_texture_ratio: float = 0.5,
    min_correlation: float = 0.2,
    max_neighbour_residual: float = 3.0,
    max_neighbour_deviation_px: float = 2.0,
) -> TrackedDisplacements:
    """Track a grid of points from the lowest-force frame through a palpation; drop what cannot be trusted.

    Each step from one frame to the next (in increasing force) starts from a block-matching
    estimate of the motion that survives large steps and decorrelated speckle (normalised
    correlation of ~50-pixel patches at half resolution over +-``max_step_px``, outliers replaced by
    their neighbours' median), refines it with Lucas-Kanade from the current frame, then refines
    that by tracking directly from the latest key frame with it as the initial flow. A new key
    frame is taken once the median correlation of the surviving tracks' patches with the key frame's
    falls below ``key_frame_correlation``, or after ``key_frame_interval`` frames. Refining against a key
    frame keeps the small per-step bias of Lucas-Kanade (it underestimates subpixel motion) from adding
    up over many steps, while the key frame stays close enough for the speckle to correlate;
    ``key_frame_interval=1`` is plain frame-to-frame chaining. Tracks whose patches correlate less
    than ``decorrelated_below`` after the step are refined with the wider ``wide_window_px`` (its
    last refinement with an affine warp) and take the median step of their neighbourhood; where the
    motion varies across the small window by more than ``max_translation_spread_px`` it is refined
    with an affine warp too (see the module docstring). The checks of the
    module docstring then drop the tracks that are not trustworthy (``TrackedDisplacements.rejected``
    counts them).

    Args:
        frames: (n, rows, cols) uint8 or float32 B-mode frames, n >= 2 (float32 is scaled linearly
            from the stack's [min, max] to 8 bits, since OpenCV's Lucas-Kanade works on 8-bit images).
        force: (n,) contact force per frame, N (any quantity increasing with compression, such as
            lambda_z, will do). Frames are tracked in increasing (stable-sorted) force from the
            lowest-force frame. None: the frames are taken to be in increasing force already.
        grid_spacing_px: spacing of the grid of tracked points, pixels.
        border_px: distance of the grid from the frame's edges, pixels; default half the window's
            smaller side.
        window_px: side (odd) of the Lucas-Kanade window and of the correlation check's patches, pixels,
            or their (width, height).
        wide_window_px: (width, height) (odd) of the window that refines the decorrelated tracks,
            pixels (one side for a square). On decorrelated speckle the random error falls with the
            window's area (benches/bench_tracking.py, at the real data's decorrelation: affine
            Lucas-Kanade started at the true position stops 0.45-0.59 px from it with a 21 x 21 window,
            0.16-0.20 px with 51 x 51, 0.14-0.16 px with 61 x 61); a window much larger than the
            structures in view (a vessel of 3 mm radius, 39 px at 0.077 mm) averages over motions
            no affine warp describes (there 61 x 61 kept 86 % of the tracks, 51 x 51 91 %).
        decorrelated_below: a track whose ``window_px`` patches correlate less than this after a
            step is decorrelated: the wide window refines it and its step becomes its
            neighbourhood's median (-1 turns both off). The default, 0.7 (about 1 / sqrt(2)), is
            where the factor sqrt(1 / rho^2 - 1) by which decorrelation scales the smallest
            possible speckle-tracking error (the Cramer-Rao bound of Walker & Trahey 1995, IEEE
            Trans. UFFC 42:301) reaches 1.
        max_translation_spread_px: where the motion since the key frame varies across the small window
            by more than this, pixels (the block matching's displacement gradient times the window's
            sides), the small window's Lucas-Kanade is refined with an affine warp. At 0.5 px the
            translation-only window misfits its own edges by a quarter pixel, the order of the error
            aimed at; ``inf`` turns it off.
        pyramid_levels: number of pyramid levels above the full-resolution image; None (the default)
            chooses, for each window and step, the fewest that reach the motion left after block
            matching (its uncertainty, or the whole search range where no block matched): 0 where
            block matching worked.
        key_frame_interval: most frames between two key frames (>= 1).
        key_frame_correlation: a new key frame is taken as soon as the median correlation of the surviving
            tracks' ``window_px`` patches with their key-frame patches falls below this; the default is
            ``decorrelated_below``'s, where the Cramer-Rao factor reaches 1. Measured on simulated palpations
            against their true motion (8-250 frames, 0.18 and 0.23 mm rows, out-of-plane motion): 0.6 kept
            15 % fewer tracks to the highest force on benches/bench_tracking.py's 10-frame palpation of large
            steps, 0.8 erred more on an 8-frame one; no new key frame at all kept 53 % of the tracks under
            out-of-plane motion.
        max_step_px: largest motion between two consecutive frames (in force) that is searched, pixels.
        block_matching_margin_px: how far a refined step may depart from the block-matching estimate
            it started from beyond that estimate's uncertainty (2 px plus the flow's variation across
            a block-matching patch), pixels (``inf`` turns the check off).
        max_block_matching_uncertainty_px: a track whose block-matching estimate is less certain than
            this, pixels, is dropped: a flow that varies by 14 px across one 50-pixel patch (28 % strain in
            one step) is not a tissue's, the blocks there matched noise (``inf`` turns the check off).
        max_forward_backward_px: largest forward-backward error of a step, pixels.
        max_lk_error: largest Lucas-Kanade error of a step (mean absolute window difference, gray levels).
        texture_window_px: side of the (odd) square over which the texture of a point is measured, pixels.
        min_texture_ratio: a point is trackable where its texture is at least this fraction of the
            median texture of the frame.
        min_correlation: smallest normalised correlation of a track's patches before and after a step.
        max_neighbour_residual: largest normalised median residual of a track's step against the
            steps of its neighbours on the grid (see the module docstring); ``inf`` turns the check off.
        max_neighbour_deviation_px: largest distance of a track's step from the median step of its
            neighbours on the grid, pixels; ``inf`` turns the check off.

    Returns:
        :class:`TrackedDisplacements` with M = n - 1 frames in increasing force (``frame_indices``
        says which input frame each is) and ``reference_index`` the lowest-force frame.
    """
    images = _as_uint8_frames(frames)
    n, rows, cols = images.shape
    order = _checked_order(force, n)
    window, wide_window = _window_sides(window_px, "window_px"), _window_sides(wide_window_px, "wide_window_px")
    if int(texture_window_px) != texture_window_px or texture_window_px < 3 or texture_window_px % 2 == 0:
        raise InputError(f"texture_window_px: expected an odd integer >= 3, got {texture_window_px!r}")
    if pyramid_levels is not None and (int(pyramid_levels) != pyramid_levels or pyramid_levels < 0):
        raise InputError(f"pyramid_levels: expected None or an integer >= 0, got {pyramid_levels!r}")
    if int(key_frame_interval) != key_frame_interval or key_frame_interval < 1:
        raise InputError(f"key_frame_interval: expected an integer >= 1, got {key_frame_interval!r}")
    for name, threshold in (
        ("grid_spacing_px", grid_spacing_px),
        ("max_step_px", max_step_px),
        ("block_matching_margin_px", block_matching_margin_px),
        ("max_block_matching_uncertainty_px", max_block_matching_uncertainty_px),
        ("max_forward_backward_px", max_forward_backward_px),
        ("max_lk_error", max_lk_error),
        ("max_neighbour_residual", max_neighbour_residual),
        ("max_neighbour_deviation_px", max_neighbour_deviation_px),
        ("max_translation_spread_px", max_translation_spread_px),
    ):
        if not (threshold > 0) or np.isnan(threshold) or (name == "max_step_px" and not np.isfinite(threshold)):
            raise InputError(f"{name}: expected a positive number, got {threshold!r}")
    if not (np.isfinite(min_texture_ratio) and min_texture_ratio >= 0):
        raise InputError(f"min_texture_ratio: expected a non-negative number, got {min_texture_ratio!r}")
    for name, bound in (
        ("min_correlation", min_correlation),
        ("decorrelated_below", decorrelated_below),
        ("key_frame_correlation", key_frame_correlation),
    ):
        if not (np.isfinite(bound) and -1.0 <= bound <= 1.0):
            raise InputError(f"{name}: expected a number in [-1, 1], got {bound!r}")
    border = float(min(window) // 2 if border_px is None else border_px)
    if not (np.isfinite(border) and border >= 0):
        raise InputError(f"border_px: expected a non-negative number of pixels, got {border_px!r}")

    points, grid_shape = _grid_points(rows, cols, float(grid_spacing_px), border)
    alive = np.ones(len(points), dtype=bool)
    current = points.astype(np.float32)[:, None, :]  # (N, 1, 2) subpixel positions in the latest frame
    key_step, key_positions = 0, current
    displacements = np.full((n - 1, len(points), 2), np.nan)
    valid = np.zeros((n - 1, len(points)), dtype=bool)
    rejected = {reason: np.zeros(n - 1, dtype=np.int64) for reason in REJECTION_REASONS}
    dropped_reason = np.full(len(points), -1, dtype=np.int64)
    dropped_at = np.full(len(points), -1, dtype=np.int64)
    search_px = float(max_step_px)
    for step in range(n - 1):
        before, after, key = images[order[step]], images[order[step + 1]], images[order[key_step]]
        texture = _texture_map(before, int(texture_window_px))
        start_cols = np.clip(np.rint(current[:, 0, 0]).astype(int), 0, cols - 1)
        start_rows = np.clip(np.rint(current[:, 0, 1]).astype(int), 0, rows - 1)
        textured = texture[start_rows, start_cols] >= min_texture_ratio * np.median(texture)

        coarse_flow = _coarse_flow(before, after, search_px)
        if search_px < max_step_px and coarse_flow.at_search_edge > _ESCALATE_EDGE_FRACTION:
            coarse_flow = _coarse_flow(before, after, float(max_step_px))
        # The next step is searched over twice this one's largest motion (a dropped frame doubles
        # it) plus a margin, and over the whole range when many peaks land on the edge of that.
        search_px = min(float(max_step_px), 2.0 * float(np.abs(coarse_flow.flow).max()) + _MIN_SEARCH_PX)
        coarse = coarse_flow.at(current[:, 0])
        initial = current + coarse[:, None, :]
        # Lucas-Kanade need only reach what block matching leaves uncertain (nearly all tracks' bound).
        uncertainty_px = coarse_flow.uncertainty_at(current[:, 0])
        # Where the blocks matched noise their flow varies wildly; no start there is evidence of anything.
        evidence = ~(uncertainty_px > max_block_matching_uncertainty_px) | (not coarse_flow.matched)
        starts = alive & evidence
        remaining_px = min(float(np.percentile(uncertainty_px[starts], 90)) if starts.any() else 0.0, search_px)
        levels, wide_levels = (
            (int(pyramid_levels),) * 2
            if pyramid_levels is not None
            else (_pyramid_levels(remaining_px, window), _pyramid_levels(remaining_px, wide_window))
        )
        predicted, predicted_ok, _ = _lucas_kanade(before, after, current, initial, window, levels)
        if key_step == step:
            tracked, tracked_ok = predicted.copy(), predicted_ok
        else:
            tracked, tracked_ok, _ = _lucas_kanade(key, after, key_positions, predicted, window, levels)
        correlation = _patch_correlation(before, after, current[:, 0], tracked[:, 0], window)
        # Where the speckle decorrelated, the small window's random error is large: refine those tracks with the
        # wide window (from the key frame, like the small one; OpenCV's translation-only window brings them within
        # reach of the affine one). Where the motion since the key frame varies by more than
        # ``max_translation_spread_px`` across the small window (estimated as this step's spread times the steps
        # since the key frame: a press goes one way), its translation-only model misfits: let it stretch.
        decorrelated = correlation < decorrelated_below
        strained = coarse_flow.spread_at(current[:, 0], window) * (step + 1 - key_step) > max_translation_spread_px
        wide, affine = np.flatnonzero(alive & decorrelated), np.flatnonzero(alive & strained & ~decorrelated)
        if len(wide):
            tracked[wide], wide_ok, _ = _lucas_kanade(
                key, after, key_positions[wide], tracked[wide], wide_window, wide_levels
            )
            tracked_ok[wide] &= wide_ok
        for group, group_window in ((wide, wide_window), (affine, window)):
            if len(group):
                tracked[group, 0], affine_ok, correlation[group] = _affine_lucas_kanade(
                    key, after, key_positions[group, 0], tracked[group, 0], group_window
                )
                tracked_ok[group] &= affine_ok
        # A step that left the block-matching estimate by more than the estimate's uncertainty is refined again
        # from the estimate, at full resolution with the wide window: kept where the two refinements agree (the
        # estimate was off), replaced where only the new one stays with the estimate (the first jumped to another
        # speckle), dropped where neither holds.
        tolerance_px = uncertainty_px + block_matching_margin_px
        departed = np.flatnonzero(alive & (np.linalg.norm(tracked - initial, axis=2).ravel() > tolerance_px))
        with_block_matching = np.ones(len(tracked), dtype=bool)
        if len(departed):
            again, again_ok, _ = _lucas_kanade(before, after, current[departed], initial[departed], wide_window, 0)
            stays = again_ok & (np.linalg.norm(again - initial[departed], axis=2).ravel() <= tolerance_px[departed])
            agrees = again_ok & (np.linalg.norm(again - tracked[departed], axis=2).ravel() <= max_forward_backward_px)
            replaced = departed[stays & ~agrees]
            tracked[replaced] = again[stays & ~agrees]
            correlation[replaced] = _patch_correlation(
                before, after, current[replaced, 0], tracked[replaced, 0], window
            )
            with_block_matching[departed[~stays & ~agrees]] = False
        uses_wide = np.zeros(len(tracked), dtype=bool)
        uses_wide[wide] = True
        back, back_ok, back_error = np.empty_like(tracked), np.empty(len(tracked), bool), np.empty(len(tracked))
        for group, group_window, group_levels in ((~uses_wide, window, levels), (uses_wide, wide_window, wide_levels)):
            if group.any():
                guess = tracked[group] - coarse[group, None, :]
                back[group], back_ok[group], back_error[group] = _lucas_kanade(
                    after, before, tracked[group], guess, group_window, group_levels
                )
        if len(wide):  # the way back like the way there (a small window's strain errs well within the check's 1 px)
            back[wide, 0], affine_ok, _ = _affine_lucas_kanade(
                after, before, tracked[wide, 0], back[wide, 0], wide_window
            )
            back_ok[wide] &= affine_ok
        x, y = tracked[:, 0, 0], tracked[:, 0, 1]
        inside = (x >= 0) & (x <= cols - 1) & (y >= 0) & (y <= rows - 1)
        forward_backward = np.linalg.norm(back - current, axis=2).ravel() <= max_forward_backward_px
        checks = {
            "left_frame": inside,
            "texture": textured,
            "lucas_kanade_status": predicted_ok & tracked_ok & back_ok,
            "block_matching": with_block_matching & evidence,
            "forward_backward": forward_backward,
            "lucas_kanade_error": back_error <= max_lk_error,
            "correlation": correlation >= min_correlation,
        }
        passed = alive.copy()
        for reason, ok in checks.items():
            failed = passed & ~ok
            rejected[reason][step] = np.count_nonzero(failed)
            dropped_reason[failed], dropped_at[failed] = REJECTION_REASONS.index(reason), step
            passed &= ok
        # Consistency: each surviving track's step against its surviving neighbours' steps.
        increments = np.where(passed[:, None], (tracked - current)[:, 0], np.nan).reshape((*grid_shape, 2))
        median, residual = _normalised_median_test(increments, 2, 0.1)
        deviation = np.linalg.norm(increments - median, axis=-1).ravel()
        # NaN (no neighbour at all: nothing to disagree with) passes.
        consistent = ~(residual.ravel() > max_neighbour_residual) & ~(deviation > max_neighbour_deviation_px)
        failed = passed & ~consistent
        rejected["neighbours"][step] = np.count_nonzero(failed)
        dropped_reason[failed], dropped_at[failed] = REJECTION_REASONS.index("neighbours"), step
        alive = passed & consistent
        # A decorrelated track's own step is noisy: take the median of the steps in its 3 x 3 neighbourhood
        # (itself included; per component: it keeps a linear motion and ignores a minority that moves
        # otherwise, such as tracks across a vessel wall).
        steps = np.where(alive[:, None], (tracked - current)[:, 0], np.nan).reshape((*grid_shape, 2))
        smoothed = alive & decorrelated
        if smoothed.any():
            neighbourhood_median = _nanmedian(_neighbourhoods(steps, 1)).reshape(-1, 2)  # NaN where none is alive
            tracked[smoothed, 0] = current[smoothed, 0] + neighbourhood_median[smoothed]
        current = np.where(alive[:, None, None], tracked, current)
        valid[step] = alive
        displacements[step, alive] = current[alive, 0].astype(np.float64) - points[alive]
        new_key = step + 1 - key_step >= key_frame_interval or not alive.any()
        if not new_key:  # the key frame's patches are compared only where the interval has not ended it already
            key_patches = _patch_correlation(key, after, key_positions[alive, 0], current[alive, 0], window)
            new_key = bool(np.median(key_patches) < key_frame_correlation)
        if new_key:
            key_step, key_positions = step + 1, current
    return TrackedDisplacements(
        points_px=points,
        displacements_px=displacements,
        valid=valid,
        frame_indices=order[1:],
        reference_index=int(order[0]),
        frame_shape=(rows, cols),
        rejected=rejected,
        dropped_reason=dropped_reason,
        dropped_at=dropped_at,
    )
