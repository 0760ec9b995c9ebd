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
from .optical_flow import window_offsets
from .options import Integration
from .regression import DisplacementModel, Normalization, VesselAnchor, VesselAnchoredModel
from .stiffness import StiffnessProfile
from .volume import VoxelGrid

__all__ = [
    "SymmetricSolver",
    "affine_lucas_kanade",
    "anchored_displacement",
    "compound_frames",
    "crc64",
    "field_for_terms",
    "fill_holes",
    "force_integrals",
    "integrated_displacement",
    "regression_rate",
    "stiffness_integral",
    "volume_region",
    "warp_anchored_frames",
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


def anchored_displacement(
    model: VesselAnchoredModel,
    force_n: float,
    profile: StiffnessProfile,
    lumen: VesselAnchor | None,
    window: tuple[slice, slice] | None = None,
) -> np.ndarray:
    """``D(x, y, F)`` of a vessel-anchored model on ``window`` (a row and a column slice; None: the
    frame), its vessel part on ``lumen`` (None: the image part alone): (2, window rows, window
    columns), pixels. The image part by :func:`integrated_displacement`, the vessel part by the
    model's own NumPy :meth:`~usdeform.regression.VesselAnchoredModel.vessel_displacement`."""
    shape = model.frame_shape
    rows, cols = window or (slice(0, shape[0]), slice(0, shape[1]))
    field = integrated_displacement(model.image_model, force_n, profile, shape)[:, rows, cols]
    if lumen is None:
        return field
    return field + model.vessel_displacement(force_n, profile, shape, lumen, window=(rows, cols))


def warp_anchored_frames(
    frames: np.ndarray,
    forces: np.ndarray,
    profiles: np.ndarray,
    model: VesselAnchoredModel,
    anchors: np.ndarray,
    *,
    fill: float = 0.0,
) -> tuple[np.ndarray, np.ndarray]:
    """Each frame backward-mapped by :func:`anchored_displacement` with the vessel part on its row of
    ``anchors`` ((n_frames, 3) of (x, y, radius), pixels): the frames and the validity mask."""
    out, valid = np.empty_like(frames), np.empty(frames.shape, dtype=bool)
    for index, frame in enumerate(frames):
        lumen = VesselAnchor(tuple(anchors[index, :2]), anchors[index, 2])
        field = anchored_displacement(model, float(forces[index]), StiffnessProfile(*profiles[index]), lumen)
        out[index], valid[index] = warp_frame(frame, field, fill)
    return out, valid


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


def _replicated_bilinear(image: np.ndarray, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Bilinear samples of ``image`` at ``(x, y)``, the edge replicated beyond the frame (OpenCV's
    ``BORDER_REPLICATE``: the position clamped into it); 0 at NaN."""
    rows, cols = image.shape
    return _bilinear(image, np.clip(x, 0, cols - 1), np.clip(y, 0, rows - 1), 0.0)


def affine_lucas_kanade(
    before: np.ndarray,
    gradient_x: np.ndarray,
    gradient_y: np.ndarray,
    after: np.ndarray,
    start: np.ndarray,
    initial: np.ndarray,
    window_px: tuple[int, int],
    max_iterations: int = 30,
    epsilon: float = 0.01,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Twin of ``_core.affine_lucas_kanade``: where the (width, height) ``window_px`` window of ``before``
    around each (N, 2) float32 point ``start`` lies in ``after``, from ``initial`` (N, 2), with an affine
    warp of the window (the step and the local displacement gradient).

    Inverse compositional Gauss-Newton (Baker & Matthews 2004, IJCV 56:221) on zero-mean windows, all
    windows at once. The template and the descent images are ``before``, ``gradient_x`` and
    ``gradient_y`` sampled at ``start`` plus the window's offsets, the match ``after`` sampled at the
    warped offsets, all by exact bilinear interpolation. A window is cut (weight 0) where it leaves
    ``before`` or, warped, ``after``, and its template and Hessian are prepared again after a cut. The
    iteration stops after ``max_iterations`` or once both components of the translation update are below
    ``epsilon``; an update that undoes the previous one (translation within ``epsilon``) is halved and
    ends it. Returns the tracked points (N, 2) float32 (``initial`` where not ok), ok (N,) (the Hessian's
    smallest eigenvalue above 1e-6 of its largest, a finite result moved less than half the window's
    smaller side from ``initial``) and the (N,) correlation of each template with its warped match (0
    where not ok).
    """
    x_offsets, y_offsets = (offsets.astype(np.float64) for offsets in window_offsets(window_px))
    rows, cols = before.shape
    initial = np.asarray(initial, dtype=np.float32)
    start_xy, initial_xy = np.asarray(start, dtype=np.float64), initial.astype(np.float64)
    n = len(start_xy)

    def in_frame(x: np.ndarray, y: np.ndarray) -> np.ndarray:
        return _inside(x, y, (rows, cols))

    map_x, map_y = start_xy[:, 0, None] + x_offsets, start_xy[:, 1, None] + y_offsets
    sampled, gx, gy = (_replicated_bilinear(image, map_x, map_y) for image in (before, gradient_x, gradient_y))
    # (N, M, 6) steepest-descent images: gx and gy times 1, x and y (parameters dx, d(dx)/dx, d(dx)/dy,
    # dy, d(dy)/dx, d(dy)/dy in this order).
    descent = np.stack([gx, gx * x_offsets, gx * y_offsets, gy, gy * x_offsets, gy * y_offsets], axis=-1)
    weight = (
        in_frame(map_x, map_y) & in_frame(initial_xy[:, 0, None] + x_offsets, initial_xy[:, 1, None] + y_offsets)
    ).astype(np.float64)
    count = np.ones(n)
    template = np.zeros_like(sampled)
    determined = np.zeros(n, dtype=bool)
    inverse_hessian = np.tile(np.eye(6), (n, 1, 1))

    def zero_mean(values: np.ndarray, points: np.ndarray) -> np.ndarray:
        """(n, M) window values minus their mean over the window, 0 where the window is cut."""
        values = values * weight[points]
        return (values - values.sum(axis=1, keepdims=True) / count[points, None]) * weight[points]

    def prepare(points: np.ndarray) -> None:
        """The template and the inverse Gauss-Newton Hessian of these windows (after a cut)."""
        count[points] = np.maximum(weight[points].sum(axis=1), 1.0)
        template[points] = zero_mean(sampled[points], points)
        weighted = descent[points] * weight[points, :, None]
        means = weighted.sum(axis=1)
        # Zero-mean windows: remove the part of the descent images a change of brightness explains.
        hessian = np.einsum("nmi,nmj->nij", weighted, descent[points])
        hessian -= means[:, :, None] * means[:, None, :] / count[points, None, None]
        eigenvalues = np.linalg.eigvalsh(hessian)
        determined[points] = eigenvalues[:, 0] > 1e-6 * np.maximum(eigenvalues[:, -1], 1e-12)
        hessian[~determined[points]] = np.eye(6)
        inverse_hessian[points] = np.linalg.inv(hessian)

    prepare(np.arange(n))
    warp = np.tile(np.eye(3), (n, 1, 1))  # (N, 3, 3): window offset (homogeneous) -> position in after
    warp[:, :2, 2] = initial_xy

    def warped_window(points: np.ndarray) -> np.ndarray:
        """The windows warped into ``after`` (zero mean), after cutting them where they left it."""
        (a, b, c), (d, e, f) = (warp[points, row, :, None].transpose(1, 0, 2) for row in (0, 1))
        moved_x, moved_y = a * x_offsets + b * y_offsets + c, d * x_offsets + e * y_offsets + f
        inside = in_frame(moved_x, moved_y)
        cut = (weight[points] > inside).any(axis=1)
        if cut.any():
            weight[points[cut]] *= inside[cut]
            prepare(points[cut])
        return zero_mean(_replicated_bilinear(after, moved_x, moved_y), points)

    active = np.flatnonzero(determined)
    previous = np.zeros((n, 6))
    for _ in range(int(max_iterations)):
        active = active[determined[active]]
        if len(active) == 0:
            break
        difference = warped_window(active) - template[active]
        gradient = np.einsum("nmi,nm->ni", descent[active], difference)
        update = np.einsum("nij,nj->ni", inverse_hessian[active], gradient)
        # A step that undoes the previous one oscillates about the optimum: take half of it and stop (as
        # OpenCV's Lucas-Kanade does).
        oscillates = (np.abs(update[:, [0, 3]] + previous[active][:, [0, 3]]) < epsilon).all(axis=1)
        update[oscillates] *= 0.5
        # Compose with the inverse of the increment [[1 + p1, p2, p0], [p4, 1 + p5, p3]].
        increment = np.tile(np.eye(3), (len(active), 1, 1))
        increment[:, :2, :2] += update[:, [[1, 2], [4, 5]]]
        increment[:, :2, 2] = update[:, [0, 3]]
        with np.errstate(divide="ignore", invalid="ignore"):
            warp[active] = warp[active] @ _affine_inverse(increment)
        previous[active] = update
        active = active[~oscillates & (np.abs(update[:, [0, 3]]).max(axis=1) >= epsilon)]
    tracked = warp[:, :2, 2].astype(np.float32)
    with np.errstate(invalid="ignore"):
        ok = (
            determined & np.isfinite(tracked).all(axis=1) & (np.abs(tracked - initial).max(axis=1) < min(window_px) / 2)
        )
    correlation = np.zeros(n)
    if ok.any():
        matched = warped_window(np.flatnonzero(ok))
        norms = np.sqrt((template[ok] ** 2).sum(axis=1) * (matched**2).sum(axis=1))
        correlation[ok] = (template[ok] * matched).sum(axis=1) / np.maximum(norms, 1e-12)
    return np.where(ok[:, None], tracked, initial).astype(np.float32), ok, correlation


def _affine_inverse(matrices: np.ndarray) -> np.ndarray:
    """The inverses of (n, 3, 3) affine matrices (last row 0, 0, 1) in closed form (inf or NaN where singular)."""
    linear = matrices[:, :2, :2]
    determinant = linear[:, 0, 0] * linear[:, 1, 1] - linear[:, 0, 1] * linear[:, 1, 0]
    inverse = np.zeros_like(matrices)
    inverse[:, 0, 0], inverse[:, 1, 1] = linear[:, 1, 1], linear[:, 0, 0]
    inverse[:, 0, 1], inverse[:, 1, 0] = -linear[:, 0, 1], -linear[:, 1, 0]
    inverse[:, :2, :2] /= determinant[:, None, None]
    inverse[:, :2, 2] = -np.einsum("nij,nj->ni", inverse[:, :2, :2], matrices[:, :2, 2])
    inverse[:, 2, 2] = 1.0
    return inverse


#: The CRC-64 polynomial of OpenIGTLink (ECMA-182), its x^64 term implied.
_ECMA_182 = 0x42F0E1EBA9EA3693


def _crc64_table() -> list[int]:
    """The CRC-64 of each byte value alone, shifted through the polynomial bit by bit."""
    table = []
    for byte in range(256):
        crc = byte << 56
        for _ in range(8):
            crc = ((crc << 1) ^ _ECMA_182) if crc >> 63 else crc << 1
            crc &= (1 << 64) - 1
        table.append(crc)
    return table


def crc64(data: bytes, crc: int = 0) -> int:
    """The OpenIGTLink CRC-64 of ``data`` continued from ``crc``: the ECMA-182 polynomial, bits not
    reflected, initial value 0, no final XOR, one table look-up a byte."""
    table = _crc64_table()
    for byte in data:
        crc = table[(crc >> 56) ^ byte] ^ ((crc << 8) & ((1 << 64) - 1))
    return crc
