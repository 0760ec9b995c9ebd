"""Voxel grids and reconstructed volumes.

Arrays are indexed ``(z, y, x)``. The ``index_to_world`` affine (4x4, float64, mm) maps the
homogeneous continuous index ``[i, j, k, 1]`` to world coordinates, where ``i`` runs along the last
array axis (x), ``j`` along the middle one (y) and ``k`` along the first one (z), the convention of
ITK, PLUS and 3D Slicer: ``image[k, j, i]`` is the voxel whose centre is ``index_to_world @ [i, j, k, 1]``.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import numpy as np

from ..errors import InputError
from ..validation import MAX_AXIS_SIZE

__all__ = ["Volume", "VoxelGrid"]


def _check_affine(index_to_world: np.ndarray) -> np.ndarray:
    affine = np.asarray(index_to_world, dtype=np.float64)
    if affine.shape != (4, 4):
        raise InputError(f"index_to_world: expected a 4x4 matrix, got shape {affine.shape}")
    if not np.all(np.isfinite(affine)):
        raise InputError("index_to_world: contains non-finite values")
    if not np.array_equal(affine[3], [0.0, 0.0, 0.0, 1.0]):
        raise InputError(f"index_to_world: last row must be [0, 0, 0, 1], got {affine[3].tolist()}")
    volume = abs(np.linalg.det(affine[:3, :3]))
    if volume < 1e-12:
        raise InputError(
            f"index_to_world: the 3x3 part is singular (a voxel of {volume:.3g} mm^3; spacing below 0.1 um?)"
        )
    return affine


@dataclass(frozen=True, eq=False)
class VoxelGrid:
    """A voxel grid: ``shape`` as ``(z, y, x)`` voxel counts and its ``index_to_world`` affine (mm)."""

    shape: tuple[int, int, int]
    index_to_world: np.ndarray

    def __post_init__(self) -> None:
        shape = tuple(int(n) for n in self.shape)
        if len(shape) != 3 or min(shape) < 1:
            raise InputError(f"shape: expected three positive voxel counts (z, y, x), got {self.shape}")
        object.__setattr__(self, "shape", shape)
        object.__setattr__(self, "index_to_world", _check_affine(self.index_to_world))

    @classmethod
    def from_bounds(
        cls,
        lower_mm: np.ndarray,
        upper_mm: np.ndarray,
        spacing_mm: float | np.ndarray,
        *,
        last_plane: Literal["inside", "nearest"] = "inside",
    ) -> VoxelGrid:
        """Axis-aligned grid from ``lower_mm`` towards ``upper_mm`` (x, y, z order, mm): voxel (0, 0, 0)
        is centred on ``lower_mm`` and the last plane along each axis is the last one at or below
        ``upper_mm`` (``"inside"``) or the one nearest to it, halves rounded up (``"nearest"``, as
        PLUS's ``SetOutputExtentFromFrameList`` rounds with ``std::round``).

        Examples
        --------
        >>> VoxelGrid.from_bounds(np.zeros(3), np.array([1.2, 1.25, 1.4]), 0.5).shape  # (z, y, x)
        (3, 3, 3)
        >>> VoxelGrid.from_bounds(np.zeros(3), np.array([1.2, 1.25, 1.4]), 0.5, last_plane="nearest").shape
        (4, 4, 3)
        """
        lower = np.asarray(lower_mm, dtype=np.float64)
        upper = np.asarray(upper_mm, dtype=np.float64)
        spacing = np.broadcast_to(np.asarray(spacing_mm, dtype=np.float64), (3,))
        if lower.shape != (3,) or upper.shape != (3,):
            raise InputError("lower_mm, upper_mm: expected 3 coordinates (x, y, z) each")
        if not (np.all(np.isfinite(lower)) and np.all(np.isfinite(upper))):
            raise InputError("lower_mm, upper_mm: contain non-finite values")
        if np.any(spacing <= 0) or not np.all(np.isfinite(spacing)):
            raise InputError(f"spacing_mm: expected positive finite spacing, got {spacing.tolist()}")
        if np.any(upper < lower):
            raise InputError("upper_mm: must be >= lower_mm on every axis")
        steps = (upper - lower) / spacing
        extent = np.floor(steps + 1e-9) if last_plane == "inside" else np.floor(steps + 0.5)
        if not np.all(extent < MAX_AXIS_SIZE):
            axis = "xyz"[int(np.argmax(extent))]
            raise InputError(
                f"spacing_mm: {spacing.tolist()} mm over {(upper - lower).tolist()} mm gives {np.max(extent) + 1:.3g} "
                f"voxels along {axis}, more than {MAX_AXIS_SIZE}; use a coarser spacing"
            )
        counts = extent.astype(np.int64) + 1
        affine = np.eye(4)
        affine[:3, :3] = np.diag(spacing)
        affine[:3, 3] = lower
        return cls((int(counts[2]), int(counts[1]), int(counts[0])), affine)

    @property
    def spacing(self) -> np.ndarray:
        """Voxel size along i, j, k (x, y, z), mm."""
        return np.linalg.norm(self.index_to_world[:3, :3], axis=0)

    @property
    def origin(self) -> np.ndarray:
        """World position of the centre of voxel (0, 0, 0), mm."""
        return self.index_to_world[:3, 3].copy()

    @property
    def direction(self) -> np.ndarray:
        """Unit direction cosines of the i, j, k axes, as the columns of a 3x3 matrix."""
        return self.index_to_world[:3, :3] / self.spacing


@dataclass(frozen=True, eq=False)
class Volume:
    """A reconstructed volume: ``image`` ``(z, y, x)`` on ``grid``, with its coverage ``weight``.

    ``weight`` is the summed splat weight per voxel (0 where no pixel landed), or None when unknown.
    """

    image: np.ndarray
    grid: VoxelGrid
    weight: np.ndarray | None = None

    def __post_init__(self) -> None:
        if self.image.shape != self.grid.shape:
            raise InputError(f"image: shape {self.image.shape} does not match the grid {self.grid.shape}")
        if self.weight is not None and self.weight.shape != self.grid.shape:
            raise InputError(f"weight: shape {self.weight.shape} does not match the grid {self.grid.shape}")

    @property
    def index_to_world(self) -> np.ndarray:
        """The grid's (4, 4) voxel index -> world affine, mm."""
        return self.grid.index_to_world
