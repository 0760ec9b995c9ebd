"""Compounding: tracked frames into a voxel volume, as PLUS's volume reconstructor does.

Each pixel ``(col, row)`` sits at image coordinates ``(col, row, 0, 1)`` and is placed in the world
by its frame's ``image_to_world = probe_to_base @ image_to_probe`` (mm, paper eq. 1). It is splatted
to the nearest voxel (``"nearest"``) or over the 8 surrounding voxels with trilinear weights
(``"linear"``), and the values landing in a voxel are combined by ``"mean"`` (weighted), ``"max"`` or
``"latest"``. The coverage volume holds the summed splat weights. Frames can be streamed in
batches; the volume is the same for any batching and any thread count.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from .. import _core
from .._arrays import frames_array, poses_array
from ..errors import InputError
from ..options import COMPOUNDINGS, INTERPOLATIONS, Compounding, Interpolation
from ..regression import (
    DeformationModel,
    DisplacementModel,
    LumenTrack,
    VesselAnchoredModel,
    correction_forces,
    profiles_array,
)
from ..validation import grid_byte_limit, threads_argument
from ._grid import Volume, VoxelGrid

if TYPE_CHECKING:
    from ..correction import Forces, Profiles

__all__ = [
    "BYTES_PER_VOXEL",
    "COMPOUNDINGS",
    "DEFAULT_MAX_BYTES",
    "INTERPOLATIONS",
    "Compounder",
    "compound_frames",
    "corner_points",
    "grid_for_frames",
    "plus_grid_for_frames",
]

#: Default memory limit of a compounder (accumulator plus returned volume), bytes.
DEFAULT_MAX_BYTES = 4 * 1024**3
#: Bytes a compounder needs per voxel (f32 value and weight, plus the returned image and weight).
BYTES_PER_VOXEL: int = _core.BYTES_PER_VOXEL


class Compounder:
    """Accumulates frames into a voxel grid, batch after batch.

    Parameters
    ----------
    grid : VoxelGrid
        The output grid.
    interpolation : {"nearest", "linear"}
        How a pixel is splatted.
    compounding : {"mean", "max", "latest"}
        How the values landing in a voxel are combined.
    max_bytes : int
        Memory limit; a grid needing more is refused before anything is allocated
        (:class:`~usdeform.errors.MemoryLimitError`).

    Notes
    -----
    Long inserts check for Ctrl-C every 64 frames (``KeyboardInterrupt``; the frames inserted
    until then stay in, see :attr:`frames_inserted`). A compounder may be shared between threads:
    a call made while another thread's call is running fails with
    :class:`~usdeform.errors.UsdeformError` rather than waiting.
    """

    def __init__(
        self,
        grid: VoxelGrid,
        interpolation: Interpolation = "nearest",
        compounding: Compounding = "mean",
        *,
        max_bytes: int = DEFAULT_MAX_BYTES,
    ) -> None:
        self.grid = grid
        self.interpolation = interpolation
        self.compounding = compounding
        self._accumulator = _core.Accumulator(
            grid.shape, grid.index_to_world, interpolation, compounding, grid_byte_limit(grid.shape, max_bytes)
        )
        #: Where the lumen search of :meth:`add_corrected_frames` stands (vessel-anchored models); set
        #: ``LumenTrack()`` to start a further sweep at the palpated lumen.
        self.lumen_track = LumenTrack()

    @property
    def frames_inserted(self) -> int:
        """Frames inserted so far."""
        return self._accumulator.frames_inserted

    def add_frames(
        self,
        frames: np.ndarray,
        image_to_world: np.ndarray,
        *,
        valid: np.ndarray | None = None,
        threads: int | None = None,
    ) -> None:
        """Insert frames at their poses.

        Parameters
        ----------
        frames : ndarray
            ``(n, rows, cols)`` (or one frame), uint8 or float32.
        image_to_world : ndarray
            ``(n, 4, 4)`` poses, mm.
        valid : ndarray of bool, optional
            Validity mask of the frames' shape (as :func:`~usdeform.correction.correct_frames`
            returns it): pixels marked False are left out of the image and of the coverage.
        threads : int, optional
            Worker threads (None: all cores).
        """
        stack = frames_array(frames)
        mask = None if valid is None else np.ascontiguousarray(valid[np.newaxis] if np.ndim(valid) == 2 else valid)
        self._accumulator.insert(
            stack, poses_array(image_to_world, stack.shape[0]), valid=mask, threads=threads_argument(threads)
        )

    def add_corrected_frames(
        self,
        frames: np.ndarray,
        image_to_world: np.ndarray,
        forces: Forces,
        profiles: Profiles,
        model: DeformationModel,
        *,
        fill: float = 0.0,
        exclude_invalid: bool = True,
        threads: int | None = None,
        clamp_force: bool = False,
    ) -> None:
        """Correct frames to zero force (as :func:`usdeform.correction.correct_frames`) and insert
        them, fused: the corrected frames are never all held in memory. A vessel-anchored model's
        lumens are searched frame after frame (as :func:`usdeform.correction.sweep_lumens`);
        with more than one thread, on one of them while the frames whose lumens are found are
        warped, with the vessel part on each lumen, and inserted on the others. The search goes on
        from where the compounder's earlier calls left it (:attr:`lumen_track`; a new compounder
        starts at the palpated lumen): a sweep added in batches of any sizes gives the volume of one
        call. A model with further vessels corrects the frames first
        (:func:`~usdeform.correction._vessel.correct_vessel_anchored`), each call starting its search
        at the palpated lumen.

        Parameters
        ----------
        frames : ndarray
            ``(n, rows, cols)`` (or one frame), uint8 or float32, of the model's ``frame_shape``.
        image_to_world : ndarray
            ``(n, 4, 4)`` poses, mm.
        forces, profiles, model, fill, threads, clamp_force
            As for :func:`~usdeform.correction.correct_frames`.
        exclude_invalid : bool
            Leave pixels sampled from outside their frame out of the image and the coverage (they
            hold no data); False inserts them with the value ``fill``.
        """
        if isinstance(model, VesselAnchoredModel) and model.other_vessels:  # corrected first, then inserted
            from ..correction._vessel import correct_vessel_anchored  # loads OpenCV (metrics)

            corrected, valid, _ = correct_vessel_anchored(
                frames, forces, profiles, model, fill=fill, clamp_force=clamp_force, threads=threads
            )
            self.add_frames(corrected, image_to_world, valid=valid if exclude_invalid else None, threads=threads)
            return
        if isinstance(model, VesselAnchoredModel):
            from ..correction import checked_sweep, lumen_search, searchable_frames  # loads OpenCV (metrics)
            from ..correction._vessel import track_state, update_track

            stack, frame_forces, frame_profiles = checked_sweep(frames, forces, profiles, model, clamp_force)
            last_found, frames_missed = track_state(self.lumen_track)
            stands = self._accumulator.insert_anchored(
                searchable_frames(stack, model.frame_shape, "frames"),
                poses_array(image_to_world, len(stack)),
                frame_forces,
                frame_profiles,
                model.image_model.kernel,
                model.vessel_kernel,
                lumen_search(model),
                last_found=last_found,
                frames_missed=frames_missed,
                fill=float(fill),
                exclude_invalid=exclude_invalid,
                threads=threads_argument(threads),
            )
            update_track(self.lumen_track, *stands)
            return
        if not isinstance(model, DisplacementModel):
            raise InputError(f"model: expected a DisplacementModel or VesselAnchoredModel, got {type(model).__name__}")
        stack = frames_array(frames)
        self._accumulator.insert_corrected(
            stack,
            poses_array(image_to_world, len(stack)),
            correction_forces(forces, len(stack), model, clamp=clamp_force),
            profiles_array(profiles, len(stack)),
            model.kernel,
            fill=float(fill),
            exclude_invalid=exclude_invalid,
            threads=threads_argument(threads),
        )

    def volume(self) -> Volume:
        """The volume so far: float32 image (0 where nothing landed) and float32 coverage weight."""
        image, weight = self._accumulator.volume()
        return Volume(image=image, grid=self.grid, weight=weight)

    def volume_region(self, lo: tuple[int, int, int], hi: tuple[int, int, int]) -> Volume:
        """The volume so far in the voxel box from ``lo`` (its first voxel) to ``hi`` (one past its last), (z, y, x)
        indices, on that box's grid: only the box is normalised, and it equals the same box of :meth:`volume`.
        Raises InputError naming a bound outside the grid or not above ``lo``."""
        image, weight = self._accumulator.volume_region(lo, hi)
        index_to_world = self.grid.index_to_world.copy()
        first_voxel = self.grid.index_to_world @ np.array([lo[2], lo[1], lo[0], 1.0])  # (x, y, z, 1) of index lo
        index_to_world[:3, 3] = first_voxel[:3]
        box = (hi[0] - lo[0], hi[1] - lo[1], hi[2] - lo[2])
        return Volume(image=image, grid=VoxelGrid(box, index_to_world), weight=weight)


def compound_frames(
    frames: np.ndarray,
    image_to_world: np.ndarray,
    grid: VoxelGrid,
    interpolation: Interpolation = "nearest",
    compounding: Compounding = "mean",
    *,
    max_bytes: int = DEFAULT_MAX_BYTES,
    valid: np.ndarray | None = None,
    threads: int | None = None,
) -> Volume:
    """Compound one stack of frames into ``grid`` (see :class:`Compounder`; ``valid`` as for
    :meth:`Compounder.add_frames`)."""
    compounder = Compounder(grid, interpolation, compounding, max_bytes=max_bytes)
    compounder.add_frames(frames, image_to_world, valid=valid, threads=threads)
    return compounder.volume()


def grid_for_frames(
    image_to_world: np.ndarray,
    frame_shape: tuple[int, int],
    spacing_mm: float | np.ndarray,
    *,
    margin_mm: float = 0.0,
) -> VoxelGrid:
    """The axis-aligned grid enclosing every frame's corners (plus a margin), as PLUS does when the
    configuration sets no output extent.

    Parameters
    ----------
    image_to_world : ndarray
        ``(n, 4, 4)`` frame poses, mm.
    frame_shape : tuple of int
        ``(rows, cols)`` of the frames.
    spacing_mm : float or ndarray
        Voxel spacing, one value or ``(x, y, z)``, mm.
    margin_mm : float
        Margin around the frames, mm.

    Returns
    -------
    VoxelGrid
    """
    rows, cols = frame_shape
    points = corner_points(image_to_world, (0, cols - 1), (0, rows - 1))
    return VoxelGrid.from_bounds(points.min(axis=0) - margin_mm, points.max(axis=0) + margin_mm, spacing_mm)


def plus_grid_for_frames(
    image_to_world: np.ndarray,
    frame_shape: tuple[int, int],
    spacing_mm: float | np.ndarray,
    *,
    clip_rectangle: tuple[tuple[int, int], tuple[int, int]] | None = None,
) -> VoxelGrid:
    """The grid PLUS fits to the frames: that of its ``VolumeReconstructor``, which always calls
    ``vtkIGSIOVolumeReconstructor::SetOutputExtentFromFrameList`` (IGSIO, under PLUS's
    ``vtkPlusVolumeReconstructor``).

    PLUS takes four corners per frame, pixel columns ``max(0, col0)`` and ``min(cols - 1, col0 + ncols)``
    by rows ``max(0, row0)`` and ``min(rows - 1, row0 + nrows)`` of the clip rectangle (its far corner one
    pixel beyond the rectangle, capped at the frame's last pixel; the whole frame without a clip
    rectangle), and puts voxel (0, 0, 0) on their minimum in the world and the last plane of each axis
    nearest to their maximum (``std::round``): ``VoxelGrid.from_bounds(..., last_plane="nearest")``.

    Parameters
    ----------
    image_to_world : ndarray
        ``(n, 4, 4)`` poses of the whole (unclipped) frames, mm.
    frame_shape : tuple of int
        ``(rows, cols)`` of the whole frames.
    spacing_mm : float or ndarray
        Voxel spacing, one value or ``(x, y, z)``, mm.
    clip_rectangle : tuple, optional
        ``((col0, row0), (ncols, nrows))``: PLUS's ``ClipRectangleOrigin`` and ``ClipRectangleSize``.

    Returns
    -------
    VoxelGrid

    Examples
    --------
    >>> plus_grid_for_frames(np.eye(4)[np.newaxis], (10, 20), 2.0, clip_rectangle=((4, 2), (9, 5))).shape
    (1, 4, 6)
    """
    rows, cols = frame_shape
    columns, lines = (0, cols - 1), (0, rows - 1)
    if clip_rectangle is not None:
        (col0, row0), (n_cols, n_rows) = clip_rectangle
        columns = (max(0, col0), min(cols - 1, col0 + n_cols))
        lines = (max(0, row0), min(rows - 1, row0 + n_rows))
    points = corner_points(image_to_world, columns, lines)
    return VoxelGrid.from_bounds(points.min(axis=0), points.max(axis=0), spacing_mm, last_plane="nearest")


def corner_points(image_to_world: np.ndarray, columns: tuple[int, int], rows: tuple[int, int]) -> np.ndarray:
    """``(4 n, 3)`` world positions (mm) of the pixels ``(col, row)``, each of two columns by each of two
    rows, in every pose."""
    poses = np.asarray(image_to_world, dtype=np.float64).reshape(-1, 4, 4)
    if len(poses) == 0:
        raise InputError("image_to_world: no frame poses to enclose")
    corners = np.array([[col, row, 0.0, 1.0] for col in columns for row in rows]).T
    return np.concatenate([(pose @ corners)[:3].T for pose in poses])
