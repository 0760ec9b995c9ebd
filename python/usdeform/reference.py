"""Plain NumPy twins of the Rust kernels, written for clarity rather than speed.

Each function computes what one kernel of ``usdeform._core`` computes, straight from the paper's
formulas, so that the tests can hold the two to the same answers and the benchmarks can time them
against each other. Conventions are those of the kernels: pixel ``(x, y)`` = ``(column, row)``,
displacements ``(lateral, axial)`` in pixels, volumes ``(z, y, x)``.
"""

from __future__ import annotations

import itertools
import math
import warnings
from collections.abc import Sequence

import numpy as np
import scipy.sparse
import scipy.sparse.linalg

from .errors import InputError
from .hole_filling import HoleFillingElement
from .options import Integration
from .regression import DisplacementModel, Normalization
from .stiffness import StiffnessProfile
from .volume import VoxelGrid

__all__ = [
    "SymmetricSolver",
    "compound_frames",
    "field_for_terms",
    "fill_holes",
    "force_integrals",
    "integrated_displacement",
    "regression_rate",
    "stiffness_integral",
    "warp_frame",
    "warp_frames",
]


def _pixel_grid(shape: tuple[int, int], normalization: Normalization) -> tuple[np.ndarray, np.ndarray]:
    rows, cols = shape
    y, x = np.mgrid[0:rows, 0:cols].astype(np.float64)
    return x / normalization.x_scale, y / normalization.y_scale


def field_for_terms(
    model: DisplacementModel, shape: tuple[int, int], h_terms: tuple[float, float, float]
) -> np.ndarray:
    """The model's field on a ``(rows, cols)`` pixel grid for the force terms ``h_terms`` (the
    normalised integrals of ``1``, ``h``, ``h^2``, or ``(1, h_n, h_n^2)`` for the rate), (2, rows, cols)
    pixels. The field is linear in the terms."""
    normalization = model.normalization
    x_n, y_n = _pixel_grid(shape, normalization)
    field = np.einsum("ct,t...->c...", model.coefficients.reshape(2, -1), model.spatial_vector(x_n, y_n, h_terms))
    field[0] *= normalization.lateral_scale
    field[1] *= normalization.axial_scale
    return field


def regression_rate(model: DisplacementModel, h_mm: float, shape: tuple[int, int]) -> np.ndarray:
    """``d(x, y, h) = K M(x, y, h)`` on a pixel grid, (2, rows, cols), either basis."""
    h_n = h_mm / model.normalization.h_scale
    return field_for_terms(model, shape, (1.0, h_n, h_n**2))


#: Gauss-Legendre nodes and weights on [-1, 1] of the force-integral twin.
_NODES, _WEIGHTS = np.polynomial.legendre.leggauss(64)


def _gauss(integrand, lower: float, upper: float) -> float:
    """``int_lower^upper integrand`` by 64-point Gauss-Legendre quadrature."""
    half = 0.5 * (upper - lower)
    return float(half * np.sum(_WEIGHTS * integrand(lower + half * (_NODES + 1.0))))


def stiffness_integral(profile: StiffnessProfile, force_n: float, p: int, q: int) -> float:
    """``int_0^F f^p / k(f)^q df`` by quadrature, ``k = sqrt(c2^2 + 4 c1 (f - c3))`` from the
    palpation start ``c3`` on and ``c2`` below it. Below the start the integrand is a polynomial
    (integrated exactly); above it the integral is taken over ``s = ln(k / c2)``, where it is smooth
    (``f = c3 + c2 lambda + c1 lambda^2``, ``lambda = c2 expm1(s) / (2 c1)``, ``df = k dlambda``,
    ``dlambda = k ds / (2 c1)``)."""
    c1, c2, c3 = profile.as_tuple()
    lower, upper, sign = (0.0, force_n, 1.0) if force_n >= 0 else (force_n, 0.0, -1.0)
    total = 0.0
    if lower < c3 or upper > c3:
        if c2 <= 0 or (upper > c3 and c2**2 + 4 * c1 * (upper - c3) <= 0):
            raise InputError(f"profiles: the stiffness of {profile.as_tuple()} is not positive on [{lower}, {upper}] N")
    if lower < c3:
        total += _gauss(lambda f: f**p / c2**q, lower, min(upper, c3))
    if upper > c3:
        start = max(lower, c3)
        if abs(4 * c1 * (upper - c3)) <= 1e-3 * c2**2:
            # Nearly linear (k changes by under 0.05 %): smooth in f itself, and 1 / c1 in the
            # substitution below would overflow for a subnormal c1.
            total += _gauss(lambda f: f**p / np.sqrt(c2**2 + 4 * c1 * (f - c3)) ** q, start, upper)
        else:

            def integrand(s: np.ndarray) -> np.ndarray:
                stiffness = c2 * np.exp(s)
                displacement = c2 * np.expm1(s) / (2 * c1)
                force = c3 + c2 * displacement + c1 * displacement**2
                return force**p * stiffness ** (2 - q) / (2 * c1)

            log_stiffness = [0.5 * np.log1p(4 * c1 * (f - c3) / c2**2) for f in (start, upper)]
            total += _gauss(integrand, *log_stiffness)
    return sign * total


def force_integrals(
    force_n: float,
    profile: StiffnessProfile,
    normalization: Normalization,
    integration: Integration = "force",
) -> tuple[float, float, float]:
    """Normalised integrals of ``1``, ``h`` and ``h^2`` (``h = f / k(f)``) from 0 to ``force_n``
    (paper eq. 8): over force, or over probe displacement (``dlambda = df / k``, normalised by
    ``h_scale``); by quadrature (:func:`stiffness_integral`), where the kernel has a closed form."""
    extra = 1 if integration == "displacement" else 0
    integral_1, integral_h, integral_h2 = (stiffness_integral(profile, force_n, p, p + extra) for p in range(3))
    n = normalization
    scale = n.h_scale if integration == "displacement" else n.force_scale
    return (integral_1 / scale, integral_h / (n.h_scale * scale), integral_h2 / (n.h_scale**2 * scale))


def integrated_displacement(
    model: DisplacementModel, force_n: float, profile: StiffnessProfile, shape: tuple[int, int]
) -> np.ndarray:
    """``D(x, y, F) = int_0^F K M(x, y, F'/k) dF'`` on a pixel grid, (2, rows, cols) pixels (either
    basis); force coupling replaces ``profile`` by 1 N/mm."""
    coupled = profile if model.coupling == "stiffness" else StiffnessProfile.UNIT
    terms = force_integrals(force_n, coupled, model.normalization, model.integration)
    return field_for_terms(model, shape, terms)


def _inside(x: np.ndarray, y: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    """Whether ``(x, y)`` lies in ``[0, cols-1] x [0, rows-1]``."""
    rows, cols = shape
    return (x >= 0) & (y >= 0) & (x <= cols - 1) & (y <= rows - 1)


def _bilinear(frame: np.ndarray, x: np.ndarray, y: np.ndarray, fill: float) -> np.ndarray:
    """Sample ``frame`` at ``(x, y)``; ``fill`` outside ``[0, cols-1] x [0, rows-1]``."""
    rows, cols = frame.shape
    inside = _inside(x, y, frame.shape)
    xs, ys = np.where(inside, x, 0.0), np.where(inside, y, 0.0)
    x0 = np.minimum(np.floor(xs).astype(np.int64), max(cols - 2, 0))
    y0 = np.minimum(np.floor(ys).astype(np.int64), max(rows - 2, 0))
    x1, y1 = np.minimum(x0 + 1, cols - 1), np.minimum(y0 + 1, rows - 1)
    fx, fy = xs - x0, ys - y0
    source = frame.astype(np.float64)
    top = source[y0, x0] * (1 - fx) + source[y0, x1] * fx
    bottom = source[y1, x0] * (1 - fx) + source[y1, x1] * fx
    return np.where(inside, top * (1 - fy) + bottom * fy, fill)


def warp_frames(
    frames: np.ndarray,
    forces: np.ndarray,
    profiles: np.ndarray,
    model: DisplacementModel,
    *,
    fill: float = 0.0,
    return_mask: bool = False,
) -> np.ndarray | tuple[np.ndarray, np.ndarray]:
    """Backward-map each frame to zero force: output (x, y) = frame at (x, y) + D(x, y, F_frame);
    with ``return_mask`` also the validity mask (True where the source lies inside the frame)."""
    out = np.empty_like(frames)
    valid = np.empty(frames.shape, dtype=bool)
    for index, frame in enumerate(frames):
        profile = StiffnessProfile(*profiles[index])
        field = integrated_displacement(model, float(forces[index]), profile, frame.shape)
        out[index], valid[index] = warp_frame(frame, field, fill)
    return (out, valid) if return_mask else out


def warp_frame(frame: np.ndarray, displacement: np.ndarray, fill: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """One ``frame`` backward-mapped by ``displacement`` (2, rows, cols; lateral, axial; pixels):
    bilinear, ``fill`` outside, uint8 rounded half up; and the validity mask (source inside the frame)."""
    rows, cols = frame.shape
    y, x = np.mgrid[0:rows, 0:cols].astype(np.float64)
    source_x, source_y = x + displacement[0], y + displacement[1]
    values = _bilinear(frame, source_x, source_y, fill)
    if frame.dtype == np.uint8:
        values = np.clip(np.floor(values + 0.5), 0, 255)
    return values.astype(frame.dtype), _inside(source_x, source_y, (rows, cols))


#: Smallest trilinear weight with which a pixel updates a voxel under linear maximum compounding, as
#: PLUS's trilinear maximum (core ``compound::MAXIMUM_MIN_WEIGHT``).
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


# The 13 stick directions (dx, dy, dz) of the hole filling, in the kernel's order.
_STICK_DIRECTIONS = [
    (1, 0, 0), (0, 1, 0), (0, 0, 1), (1, 1, 0), (1, 0, 1), (0, 1, 1), (1, -1, 0),
    (1, 0, -1), (0, 1, -1), (1, 1, 1), (1, 1, -1), (1, -1, 1), (-1, 1, 1),
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


def _fill_from_sticks(
    values: np.ndarray, known: np.ndarray, element: HoleFillingElement
) -> tuple[np.ndarray, np.ndarray]:
    lengths, stick_values = [], []
    for direction in _STICK_DIRECTIONS:
        ends = []
        for sign in (1, -1):
            steps = np.zeros(values.shape)
            end_value = np.zeros(values.shape)
            for step in range(1, element.stick_length_limit):  # the other side takes at least one step
                offset = (sign * step * direction[2], sign * step * direction[1], sign * step * direction[0])
                first = _shifted(known, offset, False) & (steps == 0)
                steps[first] = step
                end_value[first] = _shifted(values, offset, 0.0)[first]
            ends.append((steps, end_value))
        (forward, forward_value), (backward, backward_value) = ends
        both = (forward > 0) & (backward > 0) & (forward + backward <= element.stick_length_limit)
        total = np.where(both, forward + backward, 1.0)
        lengths.append(np.where(both, total * math.sqrt(sum(d * d for d in direction)), np.inf))
        stick_values.append(np.where(both, (forward_value * backward + backward_value * forward) / total, 0.0))
    order = np.argsort(np.stack(lengths), axis=0, kind="stable")[: element.sticks_to_use]
    chosen_lengths = np.take_along_axis(np.stack(lengths), order, axis=0)
    chosen = np.where(np.isfinite(chosen_lengths), np.take_along_axis(np.stack(stick_values), order, axis=0), 0.0)
    used = np.isfinite(chosen_lengths).sum(axis=0)
    return np.where(used > 0, chosen.sum(axis=0) / np.maximum(used, 1), 0.0), used > 0


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
            filled_values, filled = _fill_from_sticks(values, known, element)
        else:
            filled_values, filled = _fill_from_cube(values, weight.astype(np.float64), known, element)
        take = remaining & filled
        out[take] = filled_values[take]
        remaining &= ~filled
    out[remaining] = 0.0
    if image.dtype == np.uint8:
        return np.where(known, image, np.clip(out, 0, 255).astype(np.uint8))  # truncation, as the kernel
    return out.astype(image.dtype)


class SymmetricSolver:
    """Twin of ``_core.SymmetricSolver``: the symmetric matrix of a CSC pattern (``indptr``, ``indices``)
    whose lower triangle is read, solved by SciPy's SuperLU."""

    def __init__(self, indptr: np.ndarray, indices: np.ndarray):
        self.indptr, self.indices = np.asarray(indptr, dtype=np.int64), np.asarray(indices, dtype=np.int64)
        self.size = len(self.indptr) - 1

    def solve(self, values: np.ndarray, rhs: np.ndarray) -> np.ndarray:
        """x of A x = ``rhs``, A symmetric with the lower-triangle entries of ``values``; InputError if singular."""
        stored = scipy.sparse.csc_matrix((values, self.indices, self.indptr), shape=(self.size, self.size))
        lower = scipy.sparse.tril(stored)
        matrix = (lower + scipy.sparse.tril(stored, -1).T).tocsc()
        with np.errstate(all="ignore"), warnings.catch_warnings():
            warnings.simplefilter("ignore", scipy.sparse.linalg.MatrixRankWarning)
            solution = scipy.sparse.linalg.spsolve(matrix, rhs)
        if not np.all(np.isfinite(solution)):
            raise InputError("values: the matrix is singular")
        return np.asarray(solution)
