"""Array adapters shared by the stages: inputs checked and converted to what the kernels take.

Every function names the argument at fault in its :class:`~usdeform.errors.InputError`.

>>> frames_array(np.zeros((4, 5), np.uint8)).shape
(1, 4, 5)
>>> forces_array(2.5, 3)
array([2.5, 2.5, 2.5])
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from .errors import InputError

__all__ = ["finite_or_none", "forces_array", "frames_array", "interpolate_in_time", "poses_array", "readonly"]


def readonly(array: np.ndarray) -> np.ndarray:
    """A read-only view of ``array`` (the array itself stays writeable)."""
    view = array.view()
    view.flags.writeable = False
    return view


def frames_array(frames: np.ndarray, name: str = "frames") -> np.ndarray:
    """``frames`` as a C-contiguous ``(n_frames, rows, cols)`` uint8 or float32 array.

    Parameters
    ----------
    frames : ndarray
        ``(n_frames, rows, cols)`` or one ``(rows, cols)`` frame, uint8 or float32.
    name : str
        The argument's name in errors.

    Returns
    -------
    ndarray
        ``(n_frames, rows, cols)``, C-contiguous, same dtype.
    """
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


def poses_array(image_to_world: np.ndarray, n_frames: int) -> np.ndarray:
    """One 4x4 ``image_to_world`` pose per frame (mm) as a float64 ``(n_frames, 4, 4)`` array; one
    ``(4, 4)`` pose is accepted for one frame."""
    poses = np.asarray(image_to_world, dtype=np.float64)
    if poses.shape == (4, 4):
        poses = poses[np.newaxis]
    if poses.shape != (n_frames, 4, 4):
        raise InputError(f"image_to_world: expected shape ({n_frames}, 4, 4), one pose per frame, got {poses.shape}")
    return np.ascontiguousarray(poses)


def finite_or_none(value: float | None) -> float | None:
    """``value`` as a float, or None where it is missing or not finite (for JSON, which has no NaN)."""
    return float(value) if value is not None and np.isfinite(value) else None


def interpolate_in_time(times_s: np.ndarray, known_times_s: np.ndarray, values: np.ndarray) -> np.ndarray:
    """``values`` ``(k, d)`` known at ``known_times_s`` ``(k,)``, linearly interpolated at ``times_s``
    ``(n,)`` (held constant beyond the ends): ``(n, d)``.

    Examples
    --------
    >>> interpolate_in_time(np.array([0.0, 0.5, 2.0]), np.array([0.0, 1.0]), np.array([[0.0], [10.0]])).ravel().tolist()
    [0.0, 5.0, 10.0]
    """
    return np.stack([np.interp(times_s, known_times_s, column) for column in np.asarray(values).T], axis=1)
