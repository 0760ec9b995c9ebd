"""Tracked displacements of points from a reference frame, and the eq. 10 boundary constraints.

:class:`TrackedDisplacements` holds what :func:`~usdeform.optical_flow.track_palpation` measured;
:func:`boundary_constraints` gives the paper's eq. 10 displacements of the top and bottom image rows in
the same structure, so that the two can be joined (:meth:`TrackedDisplacements.with_boundary`,
:func:`concatenate`) into the measured displacements D^m of the regression (paper eq. 11).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from types import MappingProxyType

import numpy as np

from .._arrays import readonly as _readonly
from ..errors import InputError

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
"""Why a track is dropped, in the order the checks are applied (see :mod:`usdeform.optical_flow`)."""


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
