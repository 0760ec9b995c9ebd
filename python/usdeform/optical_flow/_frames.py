"""Frames as the trackers take them: 8-bit images in increasing force."""

from __future__ import annotations

import numpy as np

from ..errors import InputError


def as_uint8_frames(frames: np.ndarray) -> np.ndarray:
    """Check ``frames`` and return them as C-contiguous uint8 (n, rows, cols).

    float32 frames are scaled linearly from the stack's [min, max] to [0, 255].
    """
    frames = np.asarray(frames)
    if frames.dtype not in (np.uint8, np.float32):
        raise InputError(f"frames: expected dtype uint8 or float32, got {frames.dtype}")
    if frames.ndim != 3:
        raise InputError(f"frames: expected shape (n, rows, cols), got {frames.shape}")
    if frames.shape[0] < 2:
        raise InputError(f"frames: need at least 2 frames to track, got {frames.shape[0]}")
    if frames.dtype == np.uint8:
        return np.ascontiguousarray(frames)
    if not np.all(np.isfinite(frames)):
        raise InputError(
            f"frames: non-finite value at frame {int(np.flatnonzero(~np.isfinite(frames).all(axis=(1, 2)))[0])}"
        )
    low, high = float(frames.min()), float(frames.max())
    scale = 255.0 / (high - low) if high > low else 0.0
    return np.ascontiguousarray(np.rint((frames - low) * scale), dtype=np.uint8)


def force_order(force: np.ndarray | None, n: int) -> np.ndarray:
    """(n,) indices of the frames in increasing force (stable), or 0..n-1 without a force."""
    if force is None:
        return np.arange(n)
    force = np.asarray(force, dtype=np.float64)
    if force.shape != (n,):
        raise InputError(f"force: expected one value per frame, shape {(n,)}, got {force.shape}")
    if not np.all(np.isfinite(force)):
        raise InputError(f"force: non-finite value at frame {int(np.flatnonzero(~np.isfinite(force))[0])}")
    return np.argsort(force, kind="stable")
