"""Tissue stiffness from palpation: the quadratic force-displacement curve (paper eqs. 4-5).

``F(lambda) = c1 lambda^2 + c2 lambda + c3`` with force ``F`` in N and probe displacement
``lambda`` in mm; the dynamic stiffness is ``k(lambda) = 2 c1 lambda + c2`` in N/mm
(1 N/mm = 1000 N/m, the unit the paper quotes).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from .errors import InputError

__all__ = ["StiffnessProfile", "profiles_array"]


@dataclass(frozen=True)
class StiffnessProfile:
    """Coefficients of ``F = c1 lambda^2 + c2 lambda + c3`` (N/mm^2, N/mm, N)."""

    c1: float
    c2: float
    c3: float = 0.0

    def __post_init__(self) -> None:
        if not all(np.isfinite([self.c1, self.c2, self.c3])):
            raise InputError(f"StiffnessProfile: coefficients must be finite, got {self.as_tuple()}")

    @classmethod
    def constant(cls, stiffness_n_per_mm: float) -> "StiffnessProfile":
        """A linear tissue of constant stiffness (N/mm)."""
        return cls(0.0, float(stiffness_n_per_mm), 0.0)

    def as_tuple(self) -> tuple[float, float, float]:
        return (float(self.c1), float(self.c2), float(self.c3))

    def force_at(self, lambda_mm: np.ndarray | float) -> np.ndarray:
        """Force (N) at probe displacement ``lambda_mm``."""
        lam = np.asarray(lambda_mm, dtype=np.float64)
        return (self.c1 * lam + self.c2) * lam + self.c3

    def stiffness_at(self, lambda_mm: np.ndarray | float) -> np.ndarray:
        """Dynamic stiffness ``2 c1 lambda + c2`` (N/mm) at ``lambda_mm``."""
        return 2.0 * self.c1 * np.asarray(lambda_mm, dtype=np.float64) + self.c2

    def lambda_at(self, force_n: np.ndarray | float) -> np.ndarray:
        """Probe displacement (mm) where the curve reaches ``force_n``, on its rising branch.

        NaN where the curve never reaches the force. Uses ``2 (F - c3) / (c2 + sqrt(c2^2 + 4 c1 (F - c3)))``,
        exact as ``c1 -> 0``.
        """
        excess = np.asarray(force_n, dtype=np.float64) - self.c3
        discriminant = self.c2**2 + 4.0 * self.c1 * excess
        with np.errstate(invalid="ignore", divide="ignore"):
            denominator = self.c2 + np.sqrt(discriminant)
            lam = 2.0 * excess / denominator
        return np.where((discriminant >= 0) & (denominator > 0), lam, np.nan)


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
