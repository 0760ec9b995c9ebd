"""Tissue stiffness from palpation: the quadratic force-displacement curve (paper eqs. 4-5).

``F(lambda) = c1 lambda^2 + c2 lambda + c3`` with force ``F`` in N and probe displacement
``lambda`` in mm from where the palpation started; the dynamic stiffness is ``k(lambda) = 2 c1 lambda
+ c2`` in N/mm (1 N/mm = 1000 N/m, the unit the paper quotes). Below ``lambda = 0`` (forces under a
contact preload ``c3``) the curve is extended linearly with the starting stiffness ``c2``: the
quadratic's curvature is not measured there, and it may not even reach 0 N.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import ClassVar

import numpy as np

from .errors import FitError, InputError

__all__ = ["StiffnessFit", "StiffnessProfile", "fit_stiffness", "profiles_array"]


@dataclass(frozen=True)
class StiffnessProfile:
    """Coefficients of ``F = c1 lambda^2 + c2 lambda + c3`` (N/mm^2, N/mm, N)."""

    c1: float
    c2: float
    c3: float = 0.0

    def __post_init__(self) -> None:
        for name in ("c1", "c2", "c3"):
            object.__setattr__(self, name, float(getattr(self, name)))
        if not all(np.isfinite([self.c1, self.c2, self.c3])):
            raise InputError(f"StiffnessProfile: coefficients must be finite, got {self.as_tuple()}")

    UNIT: ClassVar[StiffnessProfile]

    @classmethod
    def constant(cls, stiffness_n_per_mm: float) -> StiffnessProfile:
        """A linear tissue of constant stiffness (N/mm)."""
        return cls(0.0, float(stiffness_n_per_mm), 0.0)

    def as_tuple(self) -> tuple[float, float, float]:
        """``(c1, c2, c3)`` as floats."""
        return (float(self.c1), float(self.c2), float(self.c3))

    def force_at(self, lambda_mm: np.ndarray | float) -> np.ndarray:
        """Force (N) at probe displacement ``lambda_mm`` (linear below 0)."""
        lam = np.asarray(lambda_mm, dtype=np.float64)
        return (self.c1 * np.maximum(lam, 0.0) + self.c2) * lam + self.c3

    def stiffness_at(self, lambda_mm: np.ndarray | float) -> np.ndarray:
        """Dynamic stiffness ``2 c1 lambda + c2`` (N/mm) at ``lambda_mm`` (``c2`` below 0)."""
        return 2.0 * self.c1 * np.maximum(np.asarray(lambda_mm, dtype=np.float64), 0.0) + self.c2

    def lambda_at(self, force_n: np.ndarray | float) -> np.ndarray:
        """Probe displacement (mm) where the curve reaches ``force_n``, on its rising branch.

        NaN where the curve never reaches the force. Uses ``2 (F - c3) / (c2 + sqrt(c2^2 + 4 c1 (F - c3)))``,
        exact as ``c1 -> 0``, and ``(F - c3) / c2`` below the start.
        """
        excess = np.asarray(force_n, dtype=np.float64) - self.c3
        discriminant = self.c2**2 + 4.0 * self.c1 * excess
        with np.errstate(invalid="ignore", divide="ignore"):
            denominator = self.c2 + np.sqrt(discriminant)
            rising = np.where((discriminant >= 0) & (denominator > 0), 2.0 * excess / denominator, np.nan)
            below_start = excess / self.c2 if self.c2 > 0 else np.full_like(excess, np.nan)
        return np.where(excess < 0, below_start, rising)


#: 1 N/mm everywhere through the origin: with it ``h = F / k`` equals ``F`` numerically (force coupling).
StiffnessProfile.UNIT = StiffnessProfile(0.0, 1.0, 0.0)


def profiles_array(profiles: StiffnessProfile | Sequence[StiffnessProfile] | np.ndarray, n_frames: int) -> np.ndarray:
    """Per-frame ``(c1, c2, c3)`` as a float64 ``(n_frames, 3)`` array; one profile is repeated."""
    if isinstance(profiles, StiffnessProfile):
        return np.tile(np.asarray(profiles.as_tuple()), (n_frames, 1))
    if isinstance(profiles, np.ndarray):
        array = np.ascontiguousarray(profiles, dtype=np.float64)
    else:
        items = list(profiles)
        if not all(isinstance(p, StiffnessProfile) for p in items):
            raise InputError("profiles: expected a StiffnessProfile, a sequence of them, or an (n_frames, 3) array")
        array = np.array([p.as_tuple() for p in items], dtype=np.float64).reshape(-1, 3)
    if array.shape != (n_frames, 3):
        raise InputError(f"profiles: expected shape ({n_frames}, 3), one (c1, c2, c3) per frame, got {array.shape}")
    return array


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
