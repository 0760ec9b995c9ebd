"""Compounding: tracked frames into a voxel volume, as PLUS's volume reconstructor does.

Each pixel ``(col, row)`` sits at image coordinates ``(col, row, 0, 1)`` and is placed in the world
by its frame's ``image_to_world = probe_to_base @ image_to_probe`` (mm, paper eq. 1). It is splatted
to the nearest voxel (``"nearest"``) or over the 8 surrounding voxels with trilinear weights
(``"linear"``), and the values landing in a voxel are combined by ``"mean"`` (weighted), ``"max"`` or
``"latest"``. The coverage volume holds the summed splat weights. Frames can be streamed in
batches; the volume is the same for any batching and any thread count.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from . import _core
from .correction import correction_arguments, frames_array
from .errors import InputError
from .regression import DisplacementModel
from .stiffness import StiffnessProfile
from .volume import Volume, VoxelGrid

__all__ = ["BYTES_PER_VOXEL", "DEFAULT_MAX_BYTES", "Compounder", "compound_frames", "grid_for_frames"]

#: Default memory limit of a compounder (accumulator plus returned volume), bytes.
DEFAULT_MAX_BYTES = 4 * 1024**3
#: Bytes a compounder needs per voxel (f32 value and weight, plus the returned image and weight).
BYTES_PER_VOXEL: int = _core.BYTES_PER_VOXEL

INTERPOLATIONS = ("nearest", "linear")
COMPOUNDINGS = ("mean", "max", "latest")


def _poses_array(image_to_world: np.ndarray, n_frames: int) -> np.ndarray:
    poses = np.asarray(image_to_world, dtype=np.float64)
    if poses.shape == (4, 4):
        poses = poses[np.newaxis]
    if poses.shape != (n_frames, 4, 4):
        raise InputError(f"image_to_world: expected shape ({n_frames}, 4, 4), one pose per frame, got {poses.shape}")
    return np.ascontiguousarray(poses)


class Compounder:
    """Accumulates frames into ``grid``; refuses, before allocating, a grid needing more than ``max_bytes``."""

    def __init__(
        self,
        grid: VoxelGrid,
        interpolation: str = "nearest",
        compounding: str = "mean",
        max_bytes: int = DEFAULT_MAX_BYTES,
    ) -> None:
        self.grid = grid
        self.interpolation = interpolation
        self.compounding = compounding
        self._accumulator = _core.Accumulator(
            grid.shape, grid.index_to_world, interpolation, compounding, int(max_bytes)
        )

    @property
    def frames_inserted(self) -> int:
        return self._accumulator.frames_inserted

    def add_frames(self, frames: np.ndarray, image_to_world: np.ndarray, threads: int | None = None) -> None:
        """Insert frames ``(n, rows, cols)`` (uint8 or float32) at poses ``image_to_world`` ``(n, 4, 4)``."""
        stack = frames_array(frames)
        self._accumulator.insert(stack, _poses_array(image_to_world, stack.shape[0]), threads)

    def add_corrected_frames(
        self,
        frames: np.ndarray,
        image_to_world: np.ndarray,
        forces: np.ndarray | Sequence[float] | float,
        profiles: StiffnessProfile | Sequence[StiffnessProfile] | np.ndarray,
        model: DisplacementModel,
        fill: float = 0.0,
        threads: int | None = None,
    ) -> None:
        """Correct frames to zero force (as :func:`usdeform.correction.correct_frames`) and insert them,
        fused: the corrected frames are never all held in memory."""
        stack = frames_array(frames)
        n_frames = stack.shape[0]
        self._accumulator.insert_corrected(
            stack,
            _poses_array(image_to_world, n_frames),
            *correction_arguments(forces, profiles, model, n_frames),
            float(fill),
            threads,
        )

    def volume(self) -> Volume:
        """The volume so far: float32 image (0 where nothing landed) and float32 coverage weight."""
        image, weight = self._accumulator.volume()
        return Volume(image=image, grid=self.grid, weight=weight)


def compound_frames(
    frames: np.ndarray,
    image_to_world: np.ndarray,
    grid: VoxelGrid,
    interpolation: str = "nearest",
    compounding: str = "mean",
    max_bytes: int = DEFAULT_MAX_BYTES,
    threads: int | None = None,
) -> Volume:
    """Compound one stack of frames into ``grid`` (see :class:`Compounder`)."""
    compounder = Compounder(grid, interpolation, compounding, max_bytes)
    compounder.add_frames(frames, image_to_world, threads)
    return compounder.volume()


def grid_for_frames(
    image_to_world: np.ndarray, frame_shape: tuple[int, int], spacing_mm: float | np.ndarray, margin_mm: float = 0.0
) -> VoxelGrid:
    """The axis-aligned grid of ``spacing_mm`` voxels (one value, or (x, y, z)) enclosing every frame's
    corners (plus a margin), as PLUS does when the configuration sets no output extent."""
    rows, cols = frame_shape
    poses = np.asarray(image_to_world, dtype=np.float64).reshape(-1, 4, 4)
    if len(poses) == 0:
        raise InputError("image_to_world: no frame poses to enclose")
    corners = np.array([[0, 0, 0, 1], [cols - 1, 0, 0, 1], [0, rows - 1, 0, 1], [cols - 1, rows - 1, 0, 1]], float).T
    points = np.concatenate([(pose @ corners)[:3].T for pose in poses])
    return VoxelGrid.from_bounds(points.min(axis=0) - margin_mm, points.max(axis=0) + margin_mm, spacing_mm)
