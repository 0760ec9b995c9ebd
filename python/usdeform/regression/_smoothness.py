"""The smoothness weight of a penalised fit, chosen by cross-validation over regions of the frame."""

from __future__ import annotations

import warnings
from collections.abc import Callable

import numpy as np
import scipy.linalg

from ..errors import FitError
from ._observations import _Samples


def _solve_normal_equations(system: np.ndarray, moment: np.ndarray) -> np.ndarray:
    """``system^-1 moment`` for a symmetric positive semi-definite ``system`` (Cholesky; least squares
    where it is singular)."""
    try:
        return scipy.linalg.solve(system, moment, assume_a="pos")
    except (np.linalg.LinAlgError, scipy.linalg.LinAlgError):
        return np.linalg.lstsq(system, moment, rcond=None)[0]


def _penalised_solve(
    samples: _Samples, gram: np.ndarray, moment: np.ndarray, roughness: np.ndarray, smoothness: float
) -> np.ndarray:
    """K (2, n_terms) minimising ``sum((A K^T - b)^2) + smoothness * sum(|R K^T|^2)`` for the
    weighted samples with normal equations ``gram``, ``moment`` and ``roughness = R^T R``: from the
    normal equations when penalised, else as the least-squares solution of ``A K^T = b`` (no squared
    condition number where nothing regularises)."""
    if smoothness > 0:
        return _solve_normal_equations(gram + smoothness * roughness, moment).T
    design, targets = samples.design()
    return np.linalg.lstsq(design, targets, rcond=None)[0].T


def _penalised_solver(gram: np.ndarray, moment: np.ndarray, roughness: np.ndarray) -> Callable[[float], np.ndarray]:
    """A function of the smoothness weight s giving ``(gram + s roughness)^-1 moment``.

    Many weights are tried on one fold, so the pair is diagonalised once: the generalised
    eigenvectors V of ``roughness V = (gram + roughness) V diag(mu)`` (V^T (gram + roughness) V = I)
    give ``gram + s roughness = V^-T diag(1 - mu + s mu) V^-1``, and each weight then costs a
    matrix product instead of a factorisation. Where ``gram + roughness`` is singular, each weight
    is solved directly."""
    try:
        mu, vectors = scipy.linalg.eigh(roughness, gram + roughness)
    except (np.linalg.LinAlgError, scipy.linalg.LinAlgError):
        return lambda smoothness: _solve_normal_equations(gram + smoothness * roughness, moment)
    projected = vectors.T @ moment
    return lambda smoothness: vectors @ (projected / (np.maximum(1.0 - mu, 0.0) + smoothness * mu)[:, None])


#: Smoothness weights of the cross-validation's coarse search, one per decade. Where the best of them
#: is an end of the grid the search widens by decades past it (see :func:`_cross_validated_smoothness`),
#: then refines the best weight by half and quarter decades.
SMOOTHNESS_GRID = tuple(10.0 ** np.arange(-10, 5))
#: Decades the search may widen past each end of :data:`SMOOTHNESS_GRID`.
SMOOTHNESS_WIDENING_DECADES = 8
#: Below this weight relative to the Gram matrix's scale the penalty no longer changes the solution
#: (double precision): a search that ends there has found that the data need no smoothing.
NEGLIGIBLE_RELATIVE_SMOOTHNESS = 1e-12
#: Side, in blocks, of the square grid of spatial regions the cross-validation holds out.
CV_REGIONS_PER_SIDE = 4


def _cross_validated_smoothness(
    samples: _Samples, roughness: np.ndarray, n_folds: int
) -> tuple[float, dict[float, float]]:
    """The smoothness weight with the least held-out weighted squared error over ``n_folds`` folds of
    whole spatial regions, and the held-out error of every log10 weight tried.

    The frame is cut into ``CV_REGIONS_PER_SIDE``^2 blocks by the samples' normalised reference
    positions, and each fold holds out some blocks with all their frames (assigned by a fixed
    shuffle, so the choice is reproducible). Holding out regions tests what the smoothness is for:
    bridging places without observations (a vessel's lumen, a shadow). Holding out whole frames does
    not: the neighbouring forces of the same points predict a frame well at any smoothness, so that
    criterion favours the smallest weight tried.

    The search tries :data:`SMOOTHNESS_GRID`; while the best weight is an end of the weights tried
    it widens by a decade past that end (at most :data:`SMOOTHNESS_WIDENING_DECADES`; downwards only
    while the penalty still changes the solution, :data:`NEGLIGIBLE_RELATIVE_SMOOTHNESS`), so that
    the optimum lies inside the range searched; it warns where it does not. The best weight is then
    refined by half and quarter decades. Each trial solves the penalised normal equations from
    per-fold Gram matrices, so it costs O(n_terms^3); ``roughness`` is the penalty's ``R^T R``."""
    sampled = samples.sampled_points
    positions = np.concatenate([p.positions[mask] for p, mask in zip(samples.palpations, sampled, strict=True)])
    block = np.clip(np.floor(positions * CV_REGIONS_PER_SIDE), 0, CV_REGIONS_PER_SIDE - 1).astype(int)
    region_ids, region_of_point = np.unique(block[:, 1] * CV_REGIONS_PER_SIDE + block[:, 0], return_inverse=True)
    if len(region_ids) < 2:
        raise FitError(
            "observations: choosing the smoothness by cross-validation needs observations in at least 2 regions "
            "of the frame; pass smoothness"
        )
    fold = (np.random.default_rng(0).permutation(len(region_ids)) % min(n_folds, len(region_ids)))[region_of_point]
    # A point's samples all share its reference position, so each fold holds whole points.
    fold_of_points = np.split(fold, np.cumsum([int(mask.sum()) for mask in sampled])[:-1])
    folds = [
        [_points_in(mask, of_points == k) for mask, of_points in zip(sampled, fold_of_points, strict=True)]
        for k in np.unique(fold)
    ]
    grams, moments, energies = zip(*(samples.normal_equations(points) for points in folds), strict=True)
    gram_all, moment_all = sum(grams), sum(moments)
    negligible = float(np.log10(NEGLIGIBLE_RELATIVE_SMOOTHNESS * np.abs(gram_all).max() / np.abs(roughness).max()))

    solvers = [
        _penalised_solver(gram_all - gram, moment_all - moment, roughness)
        for gram, moment in zip(grams, moments, strict=True)
    ]

    def held_out_error(log_smoothness: float) -> float:
        error = 0.0
        for solve, gram, moment, energy in zip(solvers, grams, moments, energies, strict=True):
            solution = solve(10.0**log_smoothness)
            error += float(np.sum(solution * (gram @ solution)) - 2 * np.sum(solution * moment) + energy)
        return error

    errors = {float(v): held_out_error(float(v)) for v in np.log10(SMOOTHNESS_GRID)}
    lowest, highest = min(errors), max(errors)
    while True:
        best = min(errors, key=errors.__getitem__)
        if best == max(errors) and best < highest + SMOOTHNESS_WIDENING_DECADES:
            errors[best + 1.0] = held_out_error(best + 1.0)
        elif best == min(errors) and best > max(lowest - SMOOTHNESS_WIDENING_DECADES, negligible):
            errors[best - 1.0] = held_out_error(best - 1.0)
        else:
            break
    if best == max(errors) or (best == min(errors) and best > negligible):
        warnings.warn(
            f"smoothness: the cross-validated optimum lies at the end of the searched range "
            f"(10^{best:g}); pass smoothness to choose it yourself",
            stacklevel=3,
        )
    for step in (0.5, 0.25):
        for candidate in (best - step, best + step):
            if min(errors) <= candidate <= max(errors) and candidate not in errors:
                errors[candidate] = held_out_error(candidate)
        best = min(errors, key=errors.__getitem__)
    return float(10.0**best), errors


def _points_in(mask: np.ndarray, chosen: np.ndarray) -> np.ndarray:
    """The mask of all points that are set in ``mask`` and, among those (in order), ``chosen``."""
    points = np.zeros_like(mask)
    points[np.flatnonzero(mask)[chosen]] = True
    return points
