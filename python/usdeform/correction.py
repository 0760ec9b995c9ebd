"""Correction: warp frames back to zero force (paper Section III-B).

Backward mapping: the zero-force pixel at ``(x, y)`` is read, bilinearly, from the deformed frame
at ``(x, y) + D(x, y, F)``, with ``D`` the regression's displacement at the frame's force and
stiffness profile. Sources outside the frame give ``fill``.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from . import _core
from .errors import InputError
from .regression import DisplacementModel
from .stiffness import StiffnessProfile, profiles_array

__all__ = ["correct_frames", "correction_arguments", "forces_array", "frames_array"]


def frames_array(frames: np.ndarray, name: str = "frames") -> np.ndarray:
    """``frames`` as a C-contiguous ``(n_frames, rows, cols)`` uint8 or float32 array (a 2-D frame becomes one frame)."""
    array = np.asarray(frames)
    if array.ndim == 2:
        array = array[np.newaxis]
    if array.dtype not in (np.uint8, np.float32):
        raise InputError(f"{name}: expected uint8 or float32 pixels, got dtype {array.dtype}")
    if array.ndim != 3 or 0 in array.shape:
        raise InputError(f"{name}: expected a non-empty (n_frames, rows, cols) array, got shape {array.shape}")
    return np.ascontiguousarray(array)


def forces_array(forces: np.ndarray | Sequence[float] | float, n_frames: int) -> np.ndarray:
    """Per-frame forces (N) as a float64 ``(n_frames,)`` array; a scalar is repeated."""
    array = np.asarray(forces, dtype=np.float64)
    if array.ndim == 0:
        array = np.full(n_frames, float(array))
    if array.shape != (n_frames,):
        raise InputError(f"forces: expected {n_frames} values, one per frame, got shape {array.shape}")
    return np.ascontiguousarray(array)


def correction_arguments(
    forces: np.ndarray | Sequence[float] | float,
    profiles: StiffnessProfile | Sequence[StiffnessProfile] | np.ndarray,
    model: DisplacementModel,
    n_frames: int,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, int, str]:
    """The per-frame and model arguments of the correction kernels, converted and checked (a
    force-coupled model gets the unit profile for every frame)."""
    profiles = profiles_array(profiles, n_frames)
    if model.coupling == "force":
        profiles = profiles_array(StiffnessProfile.UNIT, n_frames)
    return (
        forces_array(forces, n_frames),
        profiles,
        model.coefficients,
        model.normalization.as_array(),
        model.n_intervals,
        model.integration,
    )


def correct_frames(
    frames: np.ndarray,
    forces: np.ndarray | Sequence[float] | float,
    profiles: StiffnessProfile | Sequence[StiffnessProfile] | np.ndarray,
    model: DisplacementModel,
    fill: float = 0.0,
    threads: int | None = None,
) -> np.ndarray:
    """Frames ``(n_frames, rows, cols)`` (uint8 or float32) warped back to zero force.

    ``forces`` (N) and ``profiles`` (one :class:`StiffnessProfile` for all frames, one per frame, or
    an ``(n_frames, 3)`` array of ``(c1, c2, c3)``) give each frame's deformation; ``threads`` caps
    the worker threads (None: all cores; the result does not depend on it).
    """
    stack = frames_array(frames)
    n_frames = stack.shape[0]
    corrected = _core.warp_frames(stack, *correction_arguments(forces, profiles, model, n_frames), float(fill), threads)
    return corrected if np.ndim(frames) == 3 else corrected[0]
