"""Checks of physical inputs, shared by the file readers, the API and the command line.

Each check raises an :class:`~usdeform.errors.InputError` (or the ``error`` class the caller passes,
e.g. :class:`~usdeform.errors.FileFormatError` from a reader) whose message names the argument, file
field or frame at fault and the value found, so that a wrong input never turns into a wrong result:

* rigid transforms (probe poses): finite, last row ``0 0 0 1``, orthonormal rotation with det +1;
* calibrations (``image_to_probe``): finite, last row ``0 0 0 1``, pixel axes of a plausible size
  (:data:`MM_PER_PIXEL_RANGE`) that are neither parallel nor skewed;
* timestamps: finite and non-decreasing;
* forces: finite and inside the range the model was fitted on (or clamped into it, with a warning);
* sizes: computed with Python integers (no wrap-around) and bounded by what the machine can hold;
* data files: regular files (not ``/dev/zero`` or a pipe, which never end).

>>> check_rigid_transforms(np.eye(4), "probe_to_base")
>>> check_rigid_transforms(np.diag([1.5, 1.5, 1.5, 1.0]), "pose")
Traceback (most recent call last):
...
usdeform.errors.InputError: pose: the rotation is not orthonormal (largest error of R^T R - I: 1.25, tolerance 0.001)
"""

from __future__ import annotations

import math
import os
import stat
import warnings
from collections.abc import Iterable
from pathlib import Path

import numpy as np

from . import _core
from .errors import FileFormatError, InputError, MemoryLimitError

__all__ = [
    "FORCE_RANGE_MARGIN",
    "MAX_AXIS_SIZE",
    "MAX_INTERVALS",
    "MM_PER_PIXEL_RANGE",
    "ROTATION_TOLERANCE",
    "ForceClampWarning",
    "available_cores",
    "bounded_integer",
    "byte_limit",
    "check_calibration",
    "check_finite_per_frame",
    "check_rigid_transforms",
    "check_timestamps",
    "checked_byte_count",
    "forces_in_range",
    "grid_byte_limit",
    "memory_bytes",
    "regular_file",
    "threads_argument",
]

#: Largest entry of ``|R^T R - I|`` accepted in a rotation (tracker round-off is ~1e-6).
ROTATION_TOLERANCE = 1e-3
#: Pixel sizes (mm per pixel) a calibration can have: 0.1 um to 100 mm (real B-mode: 0.01 to 1 mm).
MM_PER_PIXEL_RANGE = (1e-4, 100.0)
#: Largest cosine between the two pixel axes of a calibration (about 3 degrees of skew).
MAX_AXIS_COSINE = 0.05
#: Forces may fall below 0 by this fraction of the fitted F_max (sensor noise around contact).
FORCE_RANGE_MARGIN = 0.05
#: Forces may exceed the fitted F_max by this fraction: the model's polynomial in force stays close
#: to its data just past them; far past them (1e6 N on a 20 N fit) it warps frames to nothing.
FORCE_EXTRAPOLATION = 0.25
#: Largest n_intervals of a model (as the compiled core checks; the force integrals do not depend on it).
MAX_INTERVALS = 1_000_000
#: Worker threads a kernel accepts (as the compiled core checks).
MAX_THREADS = 1024
#: Largest size along one axis of an image or volume a file may declare.
MAX_AXIS_SIZE = 2**31 - 1

_LAST_ROW = np.array([0.0, 0.0, 0.0, 1.0])


class ForceClampWarning(UserWarning):
    """Forces outside the model's fitted range were clamped into it (``clamp_force=True``)."""


def memory_bytes() -> int:
    """The machine's physical memory, bytes (no array can be larger); 2**63 where unknown."""
    try:
        return int(os.sysconf("SC_PHYS_PAGES")) * int(os.sysconf("SC_PAGE_SIZE"))
    except (ValueError, OSError, AttributeError):
        return 2**63


def _frame_label(frames: np.ndarray | None, index: int) -> str:
    return "" if frames is None else f"frame {int(frames[index])}: "


def check_rigid_transforms(
    transforms: np.ndarray,
    name: str,
    *,
    valid: np.ndarray | None = None,
    error: type[InputError] = InputError,
    tolerance: float = ROTATION_TOLERANCE,
) -> None:
    """Raise ``error`` unless every transform is rigid.

    Parameters
    ----------
    transforms : ndarray
        ``(4, 4)`` or ``(n_frames, 4, 4)`` float64 transforms (mm).
    name : str
        What to call them in the message (an argument or a file field).
    valid : ndarray of bool, optional
        ``(n_frames,)``: only these frames are checked (the others are unusable poses).
    error : type
        The exception class raised.
    tolerance : float
        Largest entry of ``|R^T R - I|`` accepted.
    """
    matrices = np.asarray(transforms, dtype=np.float64)
    frames: np.ndarray | None = None
    if matrices.ndim == 3:
        frames = np.arange(matrices.shape[0]) if valid is None else np.flatnonzero(valid)
        matrices = matrices[frames]
    else:
        matrices = matrices[np.newaxis]
    bad = ~np.all(np.isfinite(matrices), axis=(1, 2))
    if bad.any():
        i = int(np.flatnonzero(bad)[0])
        where = "" if frames is None else f" at frame {int(frames[i])}"
        raise error(f"{name}: non-finite value{where}")
    bad = ~np.all(matrices[:, 3] == _LAST_ROW, axis=1)
    if bad.any():
        i = int(np.flatnonzero(bad)[0])
        raise error(f"{name}: {_frame_label(frames, i)}last row must be [0, 0, 0, 1], got {matrices[i, 3].tolist()}")
    rotations = matrices[:, :3, :3]
    deviation = np.abs(np.swapaxes(rotations, 1, 2) @ rotations - np.eye(3)).max(axis=(1, 2), initial=0.0)
    bad = deviation > tolerance
    if bad.any():
        i = int(np.flatnonzero(bad)[0])
        raise error(
            f"{name}: {_frame_label(frames, i)}the rotation is not orthonormal (largest error of R^T R - I: "
            f"{deviation[i]:.3g}, tolerance {tolerance:g})"
        )
    bad = np.linalg.det(rotations) < 0 if len(rotations) else np.zeros(0, dtype=bool)
    if bad.any():
        i = int(np.flatnonzero(bad)[0])
        raise error(f"{name}: {_frame_label(frames, i)}the rotation is a reflection (determinant -1, expected +1)")


def check_calibration(image_to_probe: np.ndarray, name: str, *, error: type[InputError] = InputError) -> None:
    """Raise ``error`` unless ``image_to_probe`` is a plausible image -> probe calibration.

    The matrix must be finite with a last row ``0 0 0 1``; its first two columns (the mm per pixel
    along the image columns and rows) must have lengths within :data:`MM_PER_PIXEL_RANGE` and be
    close to perpendicular (cosine at most :data:`MAX_AXIS_COSINE`).
    """
    matrix = np.asarray(image_to_probe, dtype=np.float64)
    if matrix.shape != (4, 4):
        raise error(f"{name}: expected a 4 x 4 matrix, got shape {matrix.shape}")
    if not np.all(np.isfinite(matrix)):
        raise error(f"{name}: non-finite value in {matrix.tolist()}")
    if not np.array_equal(matrix[3], _LAST_ROW):
        raise error(f"{name}: last row must be [0, 0, 0, 1], got {matrix[3].tolist()}")
    low, high = MM_PER_PIXEL_RANGE
    axes = matrix[:3, :2]
    lengths = np.linalg.norm(axes, axis=0)
    for axis, length in zip(("columns (x)", "rows (y)"), lengths, strict=True):
        if not low <= length <= high:
            raise error(
                f"{name}: pixel size along the image {axis} is {length:.3g} mm, expected {low:g} to {high:g} mm"
            )
    cosine = abs(float(axes[:, 0] @ axes[:, 1])) / float(lengths[0] * lengths[1])
    if cosine > MAX_AXIS_COSINE:
        raise error(
            f"{name}: the image's column and row axes are not perpendicular "
            f"({math.degrees(math.acos(min(cosine, 1.0))):.1f} degrees apart)"
        )


def check_finite_per_frame(values: np.ndarray, name: str, *, error: type[InputError] = InputError) -> None:
    """Raise ``error`` naming the first frame whose value in ``(n_frames,)`` ``values`` is not finite."""
    array = np.asarray(values, dtype=np.float64)
    bad = ~np.isfinite(array)
    if bad.any():
        i = int(np.flatnonzero(bad)[0])
        raise error(f"{name}: non-finite value at frame {i} ({array[i]})")


def check_timestamps(timestamps: np.ndarray, name: str = "timestamps", *, error: type[InputError] = InputError) -> None:
    """Raise ``error`` unless the ``(n_frames,)`` timestamps (s) are finite and non-decreasing."""
    values = np.asarray(timestamps, dtype=np.float64)
    check_finite_per_frame(values, name, error=error)
    decreasing = np.diff(values) < 0
    if decreasing.any():
        i = int(np.flatnonzero(decreasing)[0]) + 1
        raise error(
            f"{name}: must be non-decreasing, frame {i} ({values[i]} s) is earlier than "
            f"frame {i - 1} ({values[i - 1]} s)"
        )


def forces_in_range(forces: np.ndarray, max_force_n: float, *, clamp: bool = False, name: str = "forces") -> np.ndarray:
    """Per-frame forces (N) checked against a model's fitted range ``[0, max_force_n]``.

    Forces from ``-FORCE_RANGE_MARGIN * max_force_n`` to ``(1 + FORCE_EXTRAPOLATION) * max_force_n``
    pass unchanged. Others raise
    InputError naming the first frame and its value; with ``clamp`` they are clamped into the range
    with a :class:`ForceClampWarning` instead (a model extrapolated far past its data warps frames
    to nonsense). Non-finite forces always raise.

    Returns
    -------
    ndarray
        The forces, float64, clamped where ``clamp`` allowed it.
    """
    values = np.asarray(forces, dtype=np.float64)
    check_finite_per_frame(values, name)
    outside = (values < -FORCE_RANGE_MARGIN * max_force_n) | (values > (1.0 + FORCE_EXTRAPOLATION) * max_force_n)
    if not outside.any():
        return values
    i = int(np.flatnonzero(outside)[0])
    message = (
        f"{name}: frame {i}: force {values[i]:.6g} N is outside the model's fitted range 0 to {max_force_n:.6g} N "
        f"({int(outside.sum())} of {values.size} frames outside)"
    )
    if not clamp:
        raise InputError(message + "; refit on palpations covering it, or clamp (clamp_force=True, --clamp-force)")
    warnings.warn(message + "; clamped into the range", ForceClampWarning, stacklevel=2)
    return np.clip(values, 0.0, max_force_n)


def available_cores() -> int:
    """The cores this process may run on (its CPU affinity where the system has one), at least 1."""
    return len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count() or 1


def threads_argument(threads: object) -> int | None:
    """``threads`` checked: None (all cores) or 1 to :data:`MAX_THREADS`."""
    if threads is None:
        return None
    if isinstance(threads, bool) or not isinstance(threads, (int, np.integer)) or not 1 <= threads <= MAX_THREADS:
        raise InputError(f"threads: expected 1 to {MAX_THREADS} (or None for all cores), got {str(threads)[:40]}")
    return int(threads)


def byte_limit(max_bytes: object) -> int:
    """``max_bytes`` (a memory limit) as a non-negative int the compiled core takes (below 2**127);
    InputError otherwise."""
    if isinstance(max_bytes, (float, np.floating)) and float(max_bytes).is_integer():
        max_bytes = int(max_bytes)
    return bounded_integer(max_bytes, "max_bytes", 0, 2**127)


def grid_byte_limit(shape: Iterable[int], max_bytes: object) -> int:
    """``max_bytes`` checked as a memory limit for a voxel grid of ``shape`` (z, y, x).

    Raises InputError unless ``max_bytes`` is a non-negative integer, and MemoryLimitError when the
    grid fits the limit but not the machine's memory (allocating it would end the process).
    """
    limit = byte_limit(max_bytes)
    needed = math.prod(int(n) for n in shape) * _core.BYTES_PER_VOXEL
    if limit >= needed > memory_bytes():
        raise MemoryLimitError(
            f"the voxel grid {tuple(shape)} needs {needed} bytes, more than this machine's {memory_bytes()} bytes "
            "of memory; use a coarser grid"
        )
    return limit


def checked_byte_count(
    sizes: Iterable[int], itemsize: int, name: str, *, error: type[InputError] = FileFormatError
) -> int:
    """The bytes of an array of ``sizes`` elements of ``itemsize`` bytes, computed without overflow.

    Raises ``error`` naming ``name`` for a negative size, a size above :data:`MAX_AXIS_SIZE` or an
    array larger than the machine's memory.
    """
    counts = [int(size) for size in sizes]
    if any(size < 0 for size in counts):
        raise error(f"{name}: negative size in {counts}")
    if any(size > MAX_AXIS_SIZE for size in counts):
        raise error(f"{name}: size above {MAX_AXIS_SIZE} along an axis in {counts}")
    total = math.prod(counts) * int(itemsize)
    if total > memory_bytes():
        raise error(f"{name}: {counts} needs {total} bytes, more than this machine's {memory_bytes()} bytes of memory")
    return total


def bounded_integer(
    value: object, name: str, minimum: int, maximum: int, *, error: type[InputError] = InputError
) -> int:
    """``value`` as an int in ``[minimum, maximum]``; ``error`` names ``name`` otherwise."""
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)):
        raise error(f"{name}: expected an integer, got {value!r}"[:200])
    if not minimum <= int(value) <= maximum:
        raise error(f"{name}: expected an integer from {minimum} to {maximum}, got {str(value)[:40]}")
    return int(value)


def regular_file(path: Path, name: str, *, error: type[InputError] = FileFormatError) -> Path:
    """``path`` if it is a regular file; ``error`` names ``name`` for a device, pipe or folder
    (which may never end, like ``/dev/zero``) and for a missing file."""
    try:
        mode = os.stat(path).st_mode
    except FileNotFoundError:
        raise error(f"{name}: {path} does not exist") from None
    except OSError as exc:
        raise error(f"{name}: cannot read {path} ({exc.strerror})") from None
    if not stat.S_ISREG(mode):
        raise error(f"{name}: {path} is not a regular file")
    return Path(path)
