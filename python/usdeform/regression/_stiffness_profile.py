"""A stiffness profile: the force-displacement curve ``F(lambda) = c1 lambda^2 + c2 lambda + c3`` (paper eq. 4)
the model's ``h = F / k`` reads its stiffness from.

Force ``F`` in N and probe displacement ``lambda`` in mm from where the palpation started; the dynamic
stiffness is ``k(lambda) = 2 c1 lambda + c2`` in N/mm. Below ``lambda = 0`` (forces under a contact preload
``c3``) the curve is extended linearly with the starting stiffness ``c2``.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import ClassVar

import numpy as np

from ..errors import InputError

__all__ = ["StiffnessProfile", "profiles_array"]


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
