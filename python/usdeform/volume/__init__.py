"""Volumes: tracked frames compounded into a voxel grid and its holes filled, as PLUS's
vtkPlusVolumeReconstructor does.

The reconstructor's flow, one call each (:class:`VolumeReconstructor`): configure (the grid from
:func:`output_grid`, or a PLUS configuration's :class:`ReconstructionSettings`), add frames (batch after
batch), update (hole filling and the voxel type) and get the volume. :func:`compound_recording` runs the
four on a :class:`~usdeform.recording.Recording`; :class:`Compounder` is the splat alone. Volumes are
``(z, y, x)`` with a 4x4 index-to-world affine, mm.

Behind the door: :mod:`._grid` (grids and volumes), :mod:`._compounder` (the splat), :mod:`._holes`
(PLUS's hole filling), :mod:`._settings` (PLUS's reconstruction settings) and :mod:`._recording` (a
recording into a volume).
"""

from __future__ import annotations

from ._compounder import (
    BYTES_PER_VOXEL,
    COMPOUNDINGS,
    DEFAULT_MAX_BYTES,
    INTERPOLATIONS,
    Compounder,
    compound_frames,
    corner_points,
    grid_for_frames,
    plus_grid_for_frames,
)
from ._grid import Volume, VoxelGrid
from ._holes import PLUS_MIN_KNOWN_WEIGHT, HoleFillingElement, HoleFillingKind, VoxelType, fill_holes, voxel_values
from ._recording import (
    DEFAULT_SPACING_MM,
    VolumeReconstructor,
    clip_frames,
    compound_recording,
    finish_volume,
    output_grid,
)
from ._settings import ReconstructionSettings

__all__ = [
    "BYTES_PER_VOXEL",
    "COMPOUNDINGS",
    "DEFAULT_MAX_BYTES",
    "DEFAULT_SPACING_MM",
    "INTERPOLATIONS",
    "PLUS_MIN_KNOWN_WEIGHT",
    "Compounder",
    "HoleFillingElement",
    "HoleFillingKind",
    "ReconstructionSettings",
    "Volume",
    "VolumeReconstructor",
    "VoxelGrid",
    "VoxelType",
    "clip_frames",
    "compound_frames",
    "compound_recording",
    "corner_points",
    "fill_holes",
    "finish_volume",
    "grid_for_frames",
    "output_grid",
    "plus_grid_for_frames",
    "voxel_values",
]
