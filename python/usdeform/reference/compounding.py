"""NumPy twins of the compounding kernels: splatting frames into voxels, a region of the volume, hole filling."""

from __future__ import annotations

import itertools
import math
from collections.abc import Sequence

import numpy as np

from ..errors import InputError
from ..volume import HoleFillingElement, VoxelGrid

MAXIMUM_MIN_WEIGHT = 0.125


def _splats(
    frames: np.ndarray,
    image_to_world: np.ndarray,
    grid: VoxelGrid,
    interpolation: str,
    valid: np.ndarray | None,
    min_weight: float = 0.0,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Every (voxel flat index, weight, value) a valid pixel contributes, in frame, row, column order;
    trilinear corners of weight below ``min_weight`` (or zero) are left out."""
    nz, ny, nx = grid.shape
    _n_frames, rows, cols = frames.shape
    world_to_index = np.linalg.inv(grid.index_to_world)
    row, col = np.mgrid[0:rows, 0:cols]
    pixels = np.stack([col.ravel(), row.ravel(), np.zeros(rows * cols), np.ones(rows * cols)]).astype(np.float64)
    positions = np.concatenate([(world_to_index @ pose @ pixels)[:3].T for pose in image_to_world])
    values = frames.reshape(-1).astype(np.float32)
    if interpolation == "nearest":
        corners = [(np.floor(positions + 0.5).astype(np.int64), np.ones(len(values)))]
    else:
        base = np.floor(positions)
        frac = positions - base
        corners = []
        for offset in np.ndindex(2, 2, 2):
            delta = np.array(offset[::-1])  # (di, dj, dk)
            weight = np.prod(np.where(delta == 1, frac, 1 - frac), axis=1)
            corners.append((base.astype(np.int64) + delta, weight))
    voxel, weight, value, order = [], [], [], []
    for index, w in corners:
        i, j, k = index.T
        keep = (i >= 0) & (i < nx) & (j >= 0) & (j < ny) & (k >= 0) & (k < nz) & (w > 0) & (w >= min_weight)
        if valid is not None:
            keep &= valid.reshape(-1)
        voxel.append((k * ny + j) * nx + i)
        weight.append(w)
        value.append(values)
        order.append(np.where(keep, np.arange(len(values)), -1))
    voxels, weights, values_, orders = (np.concatenate(a) for a in (voxel, weight, value, order))
    keep = orders >= 0
    by_pixel = np.argsort(orders[keep], kind="stable")
    return voxels[keep][by_pixel], weights[keep][by_pixel], values_[keep][by_pixel]


def compound_frames(
    frames: np.ndarray,
    image_to_world: np.ndarray,
    grid: VoxelGrid,
    interpolation: str = "nearest",
    compounding: str = "mean",
    *,
    valid: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Splat frames at their ``image_to_world`` poses into ``grid``: (image, weight), float32 (z, y, x);
    pixels whose ``valid`` flag (bool, the frames' shape) is False are left out. Linear maximum
    updates only the corners of weight >= :data:`MAXIMUM_MIN_WEIGHT`."""
    min_weight = MAXIMUM_MIN_WEIGHT if compounding == "max" and interpolation == "linear" else 0.0
    voxel, weight, value = _splats(frames, image_to_world, grid, interpolation, valid, min_weight)
    n_voxels = int(np.prod(grid.shape))
    weight_sum = np.bincount(voxel, weights=weight, minlength=n_voxels)
    image = np.zeros(n_voxels)
    if compounding == "mean":
        sums = np.bincount(voxel, weights=weight * value, minlength=n_voxels)
        np.divide(sums, weight_sum, out=image, where=weight_sum > 0)
    elif compounding == "max":
        image[:] = -np.inf
        np.maximum.at(image, voxel, value)
        image[weight_sum == 0] = 0.0
    elif compounding == "latest":
        last = len(voxel) - 1 - np.unique(voxel[::-1], return_index=True)[1]
        image[voxel[last]] = value[last]
    else:
        raise InputError(f"compounding: expected 'mean', 'max' or 'latest', got {compounding!r}")
    return image.reshape(grid.shape).astype(np.float32), weight_sum.reshape(grid.shape).astype(np.float32)


def volume_region(
    frames: np.ndarray,
    image_to_world: np.ndarray,
    grid: VoxelGrid,
    lo: tuple[int, int, int],
    hi: tuple[int, int, int],
    interpolation: str = "nearest",
    compounding: str = "mean",
    *,
    valid: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """(image, weight) of :func:`compound_frames` in the voxel box from ``lo`` (first voxel, z, y, x)
    to ``hi`` (one past the last), float32 of shape ``hi - lo``; InputError naming the bound unless
    ``0 <= lo < hi <= grid.shape`` on every axis."""
    for name, n, low, high in zip("zyx", grid.shape, lo, hi, strict=True):
        if not 0 <= low < n:
            raise InputError(f"lo: the {name} bound {low} is outside the grid's voxels 0..{n} along {name}")
        if not low < high <= n:
            raise InputError(
                f"hi: the {name} bound {high} must be above lo's {low} and at most the grid's {n} voxels along {name}"
            )
    image, weight = compound_frames(frames, image_to_world, grid, interpolation, compounding, valid=valid)
    box = tuple(slice(low, high) for low, high in zip(lo, hi, strict=True))
    return image[box], weight[box]


# The 13 stick directions (dx, dy, dz) of the hole filling, in the kernel's order and sign (PLUS's).
_STICK_DIRECTIONS = [
    (1, 0, 0), (0, 1, 0), (0, 0, 1), (1, 1, 0), (1, 0, 1), (0, 1, 1), (1, -1, 0),
    (1, 0, -1), (0, 1, -1), (1, 1, 1), (-1, 1, 1), (1, -1, 1), (-1, -1, 1),
]  # fmt: skip


def _shifted(array: np.ndarray, offset: tuple[int, int, int], outside: float | bool) -> np.ndarray:
    """``out[z, y, x] = array[z + dz, y + dy, x + dx]`` for ``offset`` (dz, dy, dx); ``outside`` beyond the volume."""
    out = np.full_like(array, outside)
    target, source = [], []
    for delta, n in zip(offset, array.shape, strict=True):
        target.append(slice(max(0, -delta), max(0, min(n, n - delta))))
        source.append(slice(max(0, delta), max(0, min(n, n + delta))))
    out[tuple(target)] = array[tuple(source)]
    return out


def _fill_from_cube(
    values: np.ndarray, weight: np.ndarray, known: np.ndarray, element: HoleFillingElement
) -> tuple[np.ndarray, np.ndarray]:
    half = element.size // 2
    value_sum, weight_sum = np.zeros(values.shape), np.zeros(values.shape)
    count = np.zeros(values.shape, dtype=np.int64)
    nearest = np.full(values.shape, np.inf)
    for dz, dy, dx in itertools.product(range(-half, half + 1), repeat=3):
        offset = (dz, dy, dx)
        if offset == (0, 0, 0):
            continue
        squared = float(sum(d * d for d in offset))
        here = _shifted(known, offset, False)
        value = np.where(here, _shifted(values, offset, 0.0), 0.0)
        count += here
        if element.kind == "nearest_neighbor":
            closer = here & (squared < nearest)
            tie = here & (squared == nearest)
            value_sum = np.where(closer, value, np.where(tie, value_sum + value, value_sum))
            weight_sum = np.where(closer, 1.0, np.where(tie, weight_sum + 1.0, weight_sum))
            nearest = np.where(closer, squared, nearest)
            continue
        if element.kind == "distance_weight_inverse":
            kernel = 1.0 / math.sqrt(squared)
        else:
            kernel = math.exp(-squared / (2.0 * element.stdev * element.stdev))
        kernel_here = np.where(here, kernel, 0.0)
        if element.kind == "gaussian_accumulation":
            kernel_here = kernel_here * _shifted(weight, offset, 0.0)
        value_sum = value_sum + kernel_here * value
        weight_sum = weight_sum + kernel_here
    enough = count >= element.min_known_ratio * float(element.size**3)
    filled = (count > 0) & enough & (weight_sum > 0)
    return np.where(filled, value_sum / np.where(filled, weight_sum, 1.0), 0.0), filled


def _stick_ends(
    values: np.ndarray, known: np.ndarray, direction: tuple[int, int, int], sign: int, limit: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Steps to the nearest known voxel along ``sign * direction`` (0: none within ``limit``), and its value."""
    steps, end_value = np.zeros(values.shape, dtype=np.int64), np.zeros(values.shape)
    for step in range(1, int(limit.max(initial=0)) + 1):
        offset = (sign * step * direction[2], sign * step * direction[1], sign * step * direction[0])
        first = _shifted(known, offset, False) & (steps == 0) & (step <= limit)
        steps[first] = step
        end_value[first] = _shifted(values, offset, 0.0)[first]
    return steps, end_value


def _fill_from_sticks(
    values: np.ndarray, known: np.ndarray, element: HoleFillingElement, integer: bool
) -> tuple[np.ndarray, np.ndarray]:
    """PLUS's sticks: ends ``f`` (forward) and ``b`` steps away with ``f + b <= limit - 1``, value
    ``(f * backward + (b + 1) * forward) / (f + b + 1)`` (truncated when ``integer``), score
    ``1 / ((f + b + 1) * |direction|)``; the best-scoring sticks, ties together, until enough are used."""
    scores, stick_values = [], []
    side_limit = np.full(values.shape, element.stick_length_limit - 1)
    for direction in _STICK_DIRECTIONS:
        forward, forward_value = _stick_ends(values, known, direction, 1, side_limit)
        backward, backward_value = _stick_ends(
            values, known, direction, -1, np.where(forward > 0, side_limit - forward, 0)
        )
        both = (forward > 0) & (backward > 0)
        span = (forward + backward + 1).astype(np.float64)
        forward_weight = (backward + 1) / span
        value = (1.0 - forward_weight) * backward_value + forward_weight * forward_value
        stick_values.append(np.floor(value) if integer else value)
        scores.append(np.where(both, 1.0 / (span * math.sqrt(sum(d * d for d in direction))), 0.0))
    score, stick_value = np.stack(scores), np.stack(stick_values)
    value_sum, score_sum = np.zeros(values.shape), np.zeros(values.shape)
    used = np.zeros(values.shape, dtype=np.int64)
    for _ in range(len(_STICK_DIRECTIONS)):
        best = score.max(axis=0)
        take = (score == best) & (best > 0) & (used < element.sticks_to_use)
        value_sum += (take * score * stick_value).sum(axis=0)
        score_sum += (take * score).sum(axis=0)
        used += take.sum(axis=0)
        score[take] = 0.0
    filled = score_sum > 0
    return np.where(filled, value_sum / np.where(filled, score_sum, 1.0), 0.0), filled


def fill_holes(
    image: np.ndarray, weight: np.ndarray, elements: Sequence[HoleFillingElement], min_known_weight: float
) -> np.ndarray:
    """Fill the holes of ``image`` (z, y, x; uint8 or float32) where ``weight`` is 0 or below
    ``min_known_weight``, each with the first of ``elements`` that succeeds (as ``_core.fill_holes``)."""
    known = (weight > 0) & (weight >= min_known_weight)
    values = image.astype(np.float64)
    out = values.copy()
    remaining = ~known
    for element in elements:
        if element.kind == "stick":
            filled_values, filled = _fill_from_sticks(values, known, element, image.dtype == np.uint8)
        else:
            filled_values, filled = _fill_from_cube(values, weight.astype(np.float64), known, element)
        take = remaining & filled
        out[take] = filled_values[take]
        remaining &= ~filled
    out[remaining] = 0.0
    if image.dtype == np.uint8:
        return np.where(known, image, np.clip(out, 0, 255).astype(np.uint8))  # truncation, as the kernel
    return out.astype(image.dtype)
