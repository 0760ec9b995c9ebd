"""Hole filling: giving values to the voxels of a compounded volume that no pixel reached, as PLUS does.

PLUS's volume reconstructor fills holes after compounding when its configuration says
``FillHoles="ON"`` (vtkPlusFillHolesInVolume), with the ``<HoleFillingElement>`` steps of the
``<HoleFilling>`` element applied in order: each hole takes the value of the first step that succeeds.
A voxel is a hole when its coverage weight is 0 or below :data:`PLUS_MIN_KNOWN_WEIGHT`. Steps read
only voxels that hold data, never values filled in the same pass, so the result is the same for any
thread count. The kinds (sizes and distances in voxels):

- ``"gaussian"``: Gaussian-weighted mean (``stdev``) of the known voxels in the ``size``^3 cube;
- ``"gaussian_accumulation"``: the same with each voxel's weight times its coverage weight;
- ``"distance_weight_inverse"``: mean weighted by 1 / distance over the cube;
- ``"nearest_neighbor"``: mean of the known voxels nearest to the hole in the cube;
- the four above fill a hole only when at least ``min_known_ratio`` of the cube's ``size``^3 voxels
  are known;
- ``"stick"``: along each of the 13 lines through the hole, the nearest known voxels forward and
  backward, ``f`` and ``b`` steps away with ``f + b <= stick_length_limit - 1``, give a stick of value
  ``(f * backward + (b + 1) * forward) / (f + b + 1)`` and score ``1 / ((f + b + 1) * |direction|)``;
  the best-scoring sticks, all of a tie together, are taken until ``sticks_to_use`` are used, and
  their score-weighted mean fills the hole.

The cube kinds are a reconstruction from PLUS's documented behaviour. The stick follows PLUS's
source (IGSIO's vtkIGSIOFillHolesInVolume), each stick's value truncated in uint8 as PLUS's cast
does; it is checked against PLUS's reference volumes (tests/test_plus_reconstruction.py).
usdeform_core::holes (rust/core/src/holes.rs) states each assumption. A PLUS configuration's hole
filling is applied by :func:`usdeform.volume.finish_volume`.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Literal, get_args

import numpy as np

from .. import _core
from ..errors import InputError
from ..validation import byte_limit, threads_argument
from ._compounder import DEFAULT_MAX_BYTES
from ._grid import Volume

__all__ = [
    "PLUS_MIN_KNOWN_WEIGHT",
    "HoleFillingElement",
    "HoleFillingKind",
    "VoxelType",
    "fill_holes",
    "voxel_values",
]

HoleFillingKind = Literal["gaussian", "gaussian_accumulation", "distance_weight_inverse", "nearest_neighbor", "stick"]
VoxelType = Literal["float32", "uint8"]

#: Smallest coverage weight of a voxel that holds data. PLUS accumulates splat weights in a uint16
#: buffer in steps of 1/256 (its ACCUMULATION_MULTIPLIER), so a voxel that only trilinear weights
#: below 1/256 reached stays empty there; run: on the SpinePhantomFreehand LINEAR volume this rule
#: raises the correlation with PLUS over all voxels from 0.9933 to 0.9975.
PLUS_MIN_KNOWN_WEIGHT = 1.0 / 256.0


@dataclass(frozen=True)
class HoleFillingElement:
    """One hole-filling step (PLUS ``<HoleFillingElement>``); each kind reads the fields it needs.

    Attributes:
        kind: the rule (PLUS Type, lower case).
        size: width of the cube around the hole, voxels, odd (PLUS Size).
        stdev: standard deviation of the Gaussian kinds, voxels (PLUS Stdev).
        min_known_ratio: fraction of the cube's voxels that must be known (PLUS MinimumKnownVoxelsRatio).
        stick_length_limit: one more than the most steps from one known end to the other (PLUS StickLengthLimit).
        sticks_to_use: best-scoring sticks averaged, 1 to 13 (PLUS NumberOfSticksToUse).
    """

    kind: HoleFillingKind
    size: int = 3
    stdev: float = 1.0
    min_known_ratio: float = 0.5
    stick_length_limit: int = 9
    sticks_to_use: int = 1

    def __post_init__(self) -> None:
        if self.kind not in get_args(HoleFillingKind):
            raise InputError(f"kind: expected one of {list(get_args(HoleFillingKind))}, got {self.kind!r}")
        cube = self.kind != "stick"
        if cube and not (isinstance(self.size, int) and self.size >= 1 and self.size % 2 == 1):
            raise InputError(f"size: expected an odd number of voxels >= 1, got {self.size!r}")
        if cube and not 0.0 <= self.min_known_ratio <= 1.0:
            raise InputError(f"min_known_ratio: expected a fraction in [0, 1], got {self.min_known_ratio!r}")
        if self.kind.startswith("gaussian") and not (np.isfinite(self.stdev) and self.stdev > 0):
            raise InputError(f"stdev: expected a positive number of voxels, got {self.stdev!r}")
        if not cube and self.stick_length_limit < 1:
            raise InputError(f"stick_length_limit: expected at least 1 voxel, got {self.stick_length_limit!r}")
        if not cube and not 1 <= self.sticks_to_use <= 13:
            raise InputError(f"sticks_to_use: expected 1 to 13 sticks, got {self.sticks_to_use!r}")

    def as_tuple(self) -> tuple[str, int, float, float, int, int]:
        """The fields in the order the compiled kernel takes them."""
        return (
            self.kind,
            int(self.size),
            float(self.stdev),
            float(self.min_known_ratio),
            int(self.stick_length_limit),
            int(self.sticks_to_use),
        )


def voxel_values(image: np.ndarray, voxel_type: VoxelType) -> np.ndarray:
    """``image`` as ``voxel_type``: float32, or uint8 rounded to nearest and clipped to [0, 255]."""
    if voxel_type == "float32":
        return np.ascontiguousarray(image, dtype=np.float32)
    if voxel_type == "uint8":
        return np.clip(np.floor(np.asarray(image, dtype=np.float64) + 0.5), 0, 255).astype(np.uint8)
    raise InputError(f"voxel_type: expected one of {list(get_args(VoxelType))}, got {voxel_type!r}")


def fill_holes(
    volume: Volume,
    elements: Sequence[HoleFillingElement],
    *,
    voxel_type: VoxelType = "float32",
    min_known_weight: float = PLUS_MIN_KNOWN_WEIGHT,
    max_bytes: int = DEFAULT_MAX_BYTES,
    threads: int | None = None,
) -> Volume:
    """The volume with its holes filled by ``elements`` in order (see the module docstring).

    Parameters
    ----------
    volume
        A compounded volume with its coverage ``weight`` (the holes are where it is below
        ``min_known_weight`` or 0).
    elements
        The steps, tried in order for each hole.
    voxel_type
        ``"float32"``, or ``"uint8"`` as PLUS writes: the known voxels rounded to nearest and the
        filled values truncated (PLUS's cast of its float result).
    min_known_weight
        Smallest coverage weight of a voxel holding data.
    max_bytes
        Refuse, before allocating, an output larger than this, bytes.
    threads
        Threads to use (None: all cores); the result does not depend on it.

    Returns
    -------
    Volume
        The filled image as ``voxel_type`` on the same grid, with the input's coverage weight
        (0 at the filled voxels; holes no step filled are 0 in the image).
    """
    if volume.weight is None:
        raise InputError("volume: has no coverage weight, so its holes are unknown; compound it with a Compounder")
    if not (np.isfinite(min_known_weight) and min_known_weight >= 0):
        raise InputError(f"min_known_weight: expected a non-negative weight, got {min_known_weight!r}")
    if not elements:
        raise InputError("elements: expected at least one hole-filling element")
    weight = np.ascontiguousarray(volume.weight, dtype=np.float32)
    image = _core.fill_holes(
        voxel_values(volume.image, voxel_type),
        weight,
        [element.as_tuple() for element in elements],
        float(min_known_weight),
        byte_limit(max_bytes),
        threads_argument(threads),
    )
    return Volume(image=image, grid=volume.grid, weight=volume.weight)
