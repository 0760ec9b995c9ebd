"""Tissue stiffness from palpation: the quadratic force-displacement curve (paper eqs. 4-5).

``F(lambda) = c1 lambda^2 + c2 lambda + c3`` with force ``F`` in N and probe displacement
``lambda`` in mm from where the palpation started; the dynamic stiffness is ``k(lambda) = 2 c1 lambda
+ c2`` in N/mm (1 N/mm = 1000 N/m, the unit the paper quotes). Below ``lambda = 0`` (forces under a
contact preload ``c3``) the curve is extended linearly with the starting stiffness ``c2``: the
quadratic's curvature is not measured there, and it may not even reach 0 N.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..errors import FitError, InputError
from ..regression import StiffnessProfile

__all__ = ["StiffnessFit", "fit_stiffness"]


@dataclass(frozen=True, eq=False)
class StiffnessFit:
    """Polynomial fits of force against probe displacement from one palpation (paper Fig. 4).

    ``profile`` is the quadratic (eq. 4) used downstream; ``polynomials`` maps each fitted order to
    its coefficients (highest power first, N and mm) and ``r_squared`` to its R^2.
    """

    profile: StiffnessProfile
    polynomials: dict[int, np.ndarray]
    r_squared: dict[int, float]
    probe_displacement_mm: np.ndarray
    force_n: np.ndarray

    @property
    def stiffness_n_per_mm(self) -> np.ndarray:
        """Dynamic stiffness ``k = 2 c1 lambda + c2`` at every recorded sample, N/mm."""
        return self.profile.stiffness_at(self.probe_displacement_mm)

    @property
    def stiffness_mean_sd_n_per_m(self) -> tuple[float, float]:
        """Mean and standard deviation of the dynamic stiffness over the recorded samples, N/m
        (the paper's 3237 +/- 56 and 1489 +/- 617 N/m)."""
        stiffness = self.stiffness_n_per_mm * 1000.0
        return float(stiffness.mean()), float(stiffness.std())


def fit_stiffness(
    force_n: np.ndarray,
    probe_displacement_mm: np.ndarray,
    orders: tuple[int, ...] = (1, 2, 3),
    min_force_range_n: float = 0.5,
) -> StiffnessFit:
    """Least-squares polynomial fits ``F(lambda)`` of orders ``orders`` (2 is always fitted), with R^2.

    ``force_n`` (N, compression positive) and ``probe_displacement_mm`` (lambda_z, mm) are the
    palpation's samples. Raises :class:`FitError` for too few samples, a force that does not rise by
    at least ``min_force_range_n``, or a quadratic whose stiffness is not positive over the samples.
    """
    force = np.asarray(force_n, dtype=np.float64)
    lam = np.asarray(probe_displacement_mm, dtype=np.float64)
    if force.ndim != 1 or lam.shape != force.shape:
        raise InputError(
            f"force_n, probe_displacement_mm: expected two 1-D arrays of one length, "
            f"got shapes {force.shape} and {lam.shape}"
        )
    for name, values in (("force_n", force), ("probe_displacement_mm", lam)):
        bad = np.flatnonzero(~np.isfinite(values))
        if bad.size:
            raise InputError(f"{name}: non-finite value at sample {bad[0]}")
    orders = tuple(sorted(set(orders) | {2}))
    if force.size < max(orders) + 2:
        raise FitError(
            f"force_n: {force.size} samples are too few for a polynomial of order {max(orders)}; "
            f"need at least {max(orders) + 2}"
        )
    if np.ptp(force) < min_force_range_n:
        raise FitError(
            f"force_n: the force rises by only {np.ptp(force):.3g} N; a palpation must raise it by "
            f"at least {min_force_range_n} N"
        )
    if np.ptp(lam) <= 0:
        raise FitError("probe_displacement_mm: the probe did not move")
    total = np.sum((force - force.mean()) ** 2)
    polynomials, r_squared = {}, {}
    for order in orders:
        coefficients = np.polyfit(lam, force, order)
        residual = np.sum((np.polyval(coefficients, lam) - force) ** 2)
        polynomials[order], r_squared[order] = coefficients, float(1.0 - residual / total)
    profile = StiffnessProfile(*polynomials[2])
    stiffness = profile.stiffness_at(lam)
    if np.any(stiffness <= 0):
        worst = int(np.argmin(stiffness))
        raise FitError(
            f"the quadratic fit gives a non-positive stiffness {stiffness[worst]:.3g} N/mm at "
            f"lambda = {lam[worst]:.3g} mm (sample {worst}); the palpation is not a loading curve"
        )
    return StiffnessFit(profile, polynomials, r_squared, lam, force)
