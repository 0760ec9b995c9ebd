"""A recording's tracked frames into a volume, as PLUS's volume reconstructor does: the clip rectangle, the
output grid (from a PLUS configuration or enclosing the frames), compounding and hole filling.

Pixels without data (a corrected recording's ``pixel_valid`` False: sampled from outside their frame) are
left out of the image and the coverage.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence

import numpy as np

from ..errors import InputError
from ..options import COMPOUNDINGS, INTERPOLATIONS, Compounding, Interpolation, checked_option
from ..recording import Recording
from ._compounder import DEFAULT_MAX_BYTES, Compounder, grid_for_frames, plus_grid_for_frames
from ._grid import Volume, VoxelGrid
from ._holes import HoleFillingElement, VoxelType, fill_holes, voxel_values
from ._settings import ReconstructionSettings

__all__ = [
    "DEFAULT_SPACING_MM",
    "VolumeReconstructor",
    "clip_frames",
    "compound_recording",
    "finish_volume",
    "output_grid",
]

#: Voxel size when neither the caller nor a PLUS configuration gives one, mm.
DEFAULT_SPACING_MM = 0.5


def clip_frames(
    frames: np.ndarray, image_to_world: np.ndarray, origin: tuple[int, int], size: tuple[int, int]
) -> tuple[np.ndarray, np.ndarray]:
    """The PLUS clip rectangle of every frame, with the poses of the clipped images.

    Parameters
    ----------
    frames : ndarray
        ``(n, rows, cols)`` frames.
    image_to_world : ndarray
        ``(n, 4, 4)`` poses, mm.
    origin : tuple of int
        ``(col, row)`` of the first pixel kept.
    size : tuple of int
        ``(cols, rows)`` of the kept rectangle.

    Returns
    -------
    frames, image_to_world : ndarray
        The clipped frames and their poses (their pixel (0, 0) is the original pixel ``origin``).

    Examples
    --------
    >>> frames = np.zeros((1, 6, 8), np.uint8)
    >>> clipped, poses = clip_frames(frames, np.eye(4)[np.newaxis], origin=(3, 2), size=(4, 3))
    >>> clipped.shape, poses[0, :2, 3].tolist()
    ((1, 3, 4), [3.0, 2.0])
    """
    (col, row), (cols, rows) = origin, size
    if col < 0 or row < 0 or row + rows > frames.shape[1] or col + cols > frames.shape[2]:
        raise InputError(
            f"ClipRectangle: origin {origin} and size {size} (col, row) exceed the "
            f"{frames.shape[1]} x {frames.shape[2]} frames"
        )
    clipped_to_image = np.eye(4)
    clipped_to_image[:2, 3] = (col, row)
    return frames[:, row : row + rows, col : col + cols], image_to_world @ clipped_to_image


def finish_volume(
    volume: Volume,
    settings: ReconstructionSettings | None = None,
    *,
    hole_filling: Sequence[HoleFillingElement] | None = None,
    voxel_type: VoxelType = "float32",
    max_bytes: int = DEFAULT_MAX_BYTES,
) -> Volume:
    """A compounded volume after hole filling, with voxels of ``voxel_type``: PLUS's step after compounding.

    Parameters
    ----------
    volume : Volume
        The compounded volume with its coverage weight.
    settings : ReconstructionSettings, optional
        A PLUS configuration's settings: with ``FillHoles="ON"`` its ``<HoleFillingElement>`` steps are
        the default of ``hole_filling``.
    hole_filling : sequence of HoleFillingElement, optional
        The steps (see :mod:`usdeform.volume`); empty: no hole filling. Default: the
        configuration's, else none.
    voxel_type : {"float32", "uint8"}
        Voxel type of the result (uint8 as PLUS writes).
    max_bytes : int
        Memory limit of the filled volume, bytes.

    Returns
    -------
    Volume
        Same grid and coverage weight.
    """
    if hole_filling is None:
        hole_filling = settings.hole_filling if settings is not None and settings.fill_holes else ()
    if not hole_filling:
        return dataclasses.replace(volume, image=voxel_values(volume.image, voxel_type))
    return fill_holes(volume, hole_filling, voxel_type=voxel_type, max_bytes=max_bytes)


def output_grid(
    image_to_base: np.ndarray,
    frame_shape: tuple[int, int],
    settings: ReconstructionSettings | None = None,
    spacing_mm: float | None = None,
) -> VoxelGrid:
    """The grid :func:`compound_recording` compounds into.

    With a PLUS configuration: its ``OutputOrigin`` and ``OutputExtent`` when it has them and
    ``spacing_mm`` is None, else the grid PLUS's VolumeReconstructor fits to the frames (the clip
    rectangle's corners, origin on their minimum, last planes rounded to the nearest:
    :func:`~usdeform.volume.plus_grid_for_frames`) at ``spacing_mm`` or the configuration's
    ``OutputSpacing``. Without one: the grid enclosing the whole frames
    (:func:`~usdeform.volume.grid_for_frames`) at ``spacing_mm`` or :data:`DEFAULT_SPACING_MM`.

    Parameters
    ----------
    image_to_base : ndarray
        ``(n, 4, 4)`` poses of the frames (unclipped), mm.
    frame_shape : tuple of int
        ``(rows, cols)`` of the frames.
    settings : ReconstructionSettings, optional
        A PLUS configuration's settings.
    spacing_mm : float, optional
        Voxel size, mm.

    Returns
    -------
    VoxelGrid
    """
    if settings is None:
        return grid_for_frames(image_to_base, frame_shape, spacing_mm or DEFAULT_SPACING_MM)
    if settings.output_extent is not None and spacing_mm is None:
        return settings.voxel_grid()
    clip = None
    if settings.clip_rectangle_origin is not None and settings.clip_rectangle_size is not None:
        clip = (settings.clip_rectangle_origin, settings.clip_rectangle_size)
    spacing = settings.output_spacing_mm if spacing_mm is None else spacing_mm
    return plus_grid_for_frames(image_to_base, frame_shape, spacing, clip_rectangle=clip)


class VolumeReconstructor:
    """PLUS's vtkPlusVolumeReconstructor in four calls: configure (the constructor), add frames
    (:meth:`add_frames`, batch after batch), update (:meth:`update`: hole filling and the voxel type) and get
    (:meth:`volume`). :func:`compound_recording` runs it on a recording.

    Parameters
    ----------
    grid : VoxelGrid
        The output grid (:func:`output_grid`).
    interpolation, compounding, max_bytes
        As for :class:`Compounder`.
    hole_filling, voxel_type
        As for :func:`finish_volume` (default: no hole filling, float32 voxels).
    """

    def __init__(
        self,
        grid: VoxelGrid,
        interpolation: Interpolation = "nearest",
        compounding: Compounding = "mean",
        *,
        hole_filling: Sequence[HoleFillingElement] = (),
        voxel_type: VoxelType = "float32",
        max_bytes: int = DEFAULT_MAX_BYTES,
    ) -> None:
        self._compounder = Compounder(grid, interpolation, compounding, max_bytes=max_bytes)
        self._hole_filling, self._voxel_type, self._max_bytes = tuple(hole_filling), voxel_type, max_bytes
        self._volume: Volume | None = None

    def add_frames(self, frames: np.ndarray, image_to_base: np.ndarray, *, valid: np.ndarray | None = None) -> None:
        """Insert frames at their poses (``image_to_base``, mm); pixels ``valid`` marks False are left out."""
        self._compounder.add_frames(frames, image_to_base, valid=valid)
        self._volume = None

    def update(self) -> Volume:
        """The frames added so far compounded, their holes filled and their voxels converted."""
        self._volume = finish_volume(
            self._compounder.volume(),
            hole_filling=self._hole_filling,
            voxel_type=self._voxel_type,
            max_bytes=self._max_bytes,
        )
        return self._volume

    def volume(self) -> Volume:
        """The volume of the last :meth:`update` (updated first when frames were added since)."""
        return self.update() if self._volume is None else self._volume


def compound_recording(
    recording: Recording,
    *,
    settings: ReconstructionSettings | None = None,
    spacing_mm: float | None = None,
    interpolation: Interpolation | None = None,
    compounding: Compounding | None = None,
    hole_filling: Sequence[HoleFillingElement] | None = None,
    voxel_type: VoxelType = "float32",
    max_bytes: int = DEFAULT_MAX_BYTES,
    name: str = "recording",
) -> tuple[Volume, int]:
    """Compound a recording's tracked frames into a volume and fill its holes, as PLUS's volume
    reconstructor does.

    Parameters
    ----------
    recording : Recording
        Frames and poses; frames without a valid pose, and pixels its ``pixel_valid`` marks False
        (a corrected recording's pixels without data), are left out.
    settings : ReconstructionSettings, optional
        A PLUS configuration's settings: clip rectangle and fan (the pixels pasted), grid, hole
        filling, and the defaults of the options below.
    spacing_mm : float, optional
        Voxel size, mm; given, the grid is fitted to the frames even when ``settings`` has an extent
        (:func:`output_grid`). Default: the configuration's, else :data:`DEFAULT_SPACING_MM`.
    interpolation : {"nearest", "linear"}, optional
        Default: the configuration's, else nearest.
    compounding : {"mean", "max", "latest"}, optional
        Default: the configuration's, else mean.
    hole_filling, voxel_type
        As for :func:`finish_volume` (default: the configuration's hole filling, float32 voxels).
    max_bytes : int
        Memory limit of the volume.
    name : str
        What to call the recording in errors (e.g. its file).

    Returns
    -------
    volume : Volume
        The image and its coverage weight (0 at the voxels hole filling gave a value).
    n_frames : int
        How many frames were compounded.
    """
    posed = recording.posed_indices(name)
    frames, image_to_base = recording.frames[posed], recording.image_to_base[posed]
    valid = None if recording.pixel_valid is None else recording.pixel_valid[posed]
    grid = output_grid(image_to_base, recording.shape, settings, spacing_mm)
    if settings is not None and settings.fan_angles_deg is not None:  # PLUS pastes only the fan's pixels
        fan = settings.pixel_mask(frames.shape[1], frames.shape[2])
        valid = np.broadcast_to(fan, frames.shape) if valid is None else valid & fan
    if settings is not None and settings.clip_rectangle_origin is not None and settings.clip_rectangle_size:
        origin, size = settings.clip_rectangle_origin, settings.clip_rectangle_size
        if valid is not None:
            valid = clip_frames(valid, image_to_base, origin, size)[0]
        frames, image_to_base = clip_frames(frames, image_to_base, origin, size)
    interpolation = interpolation or checked_option(
        "interpolation", settings.interpolation if settings is not None else "nearest", INTERPOLATIONS
    )
    compounding = compounding or checked_option(
        "compounding", settings.compounding if settings is not None else "mean", COMPOUNDINGS
    )
    if hole_filling is None:  # the configuration's hole filling, as finish_volume takes it
        hole_filling = settings.hole_filling if settings is not None and settings.fill_holes else ()
    reconstructor = VolumeReconstructor(
        grid, interpolation, compounding, hole_filling=hole_filling, voxel_type=voxel_type, max_bytes=max_bytes
    )
    reconstructor.add_frames(frames, image_to_base, valid=None if valid is None else np.ascontiguousarray(valid))
    return reconstructor.volume(), len(posed)
