"""The coupled quadratic displacement regression (paper eqs. 7-9 and 12).

``d(x, y, h) = K @ M(x, y, h)`` with ``M = [x^2, y^2, h^2, xy, xh, yh, x, y, h, 1]`` on normalised
inputs and ``h = F / k`` (mm). The displacement at force ``F`` is the integral of ``d`` over the
normalised force from 0 to ``F``, with the stiffness ``k`` held constant on each of ``n_intervals``
equal force intervals. Displacements are in pixels, ``(lateral, axial)`` = ``(x, y)``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from . import _core
from .errors import InputError
from .stiffness import StiffnessProfile

__all__ = ["Normalization", "QuadraticDisplacementModel", "M_TERMS"]

#: Names of the regression terms, in the order of the columns of K.
M_TERMS = ("x^2", "y^2", "h^2", "xy", "xh", "yh", "x", "y", "h", "1")


@dataclass(frozen=True)
class Normalization:
    """Scales between physical values and the regression's normalised [0, 1] inputs.

    ``x_n = x / x_scale`` and ``y_n = y / y_scale`` (pixels), ``F_n = F / force_scale`` (N),
    ``h_n = h / h_scale`` (mm); the model's normalised output is multiplied by ``lateral_scale``
    and ``axial_scale`` to give pixels.
    """

    x_scale: float
    y_scale: float
    force_scale: float
    h_scale: float
    lateral_scale: float = 1.0
    axial_scale: float = 1.0

    def __post_init__(self) -> None:
        values = self.as_array()
        if not np.all(np.isfinite(values)):
            raise InputError(f"Normalization: values must be finite, got {values.tolist()}")
        if np.any(values[:4] <= 0):
            raise InputError(f"Normalization: x_scale, y_scale, force_scale, h_scale must be positive, got {values[:4].tolist()}")

    @classmethod
    def for_frames(cls, rows: int, cols: int, max_force_n: float, max_h_mm: float,
                   lateral_scale: float = 1.0, axial_scale: float = 1.0) -> "Normalization":
        """Pixel coordinates, force and h each mapped onto [0, 1] over a frame of ``rows x cols``."""
        return cls(float(max(cols - 1, 1)), float(max(rows - 1, 1)), float(max_force_n), float(max_h_mm),
                   float(lateral_scale), float(axial_scale))

    def as_array(self) -> np.ndarray:
        return np.array([self.x_scale, self.y_scale, self.force_scale, self.h_scale,
                         self.lateral_scale, self.axial_scale], dtype=np.float64)


@dataclass(frozen=True)
class QuadraticDisplacementModel:
    """``K`` (2 x 10: lateral row, axial row, columns in the order of :data:`M_TERMS`) with its
    normalisation and the number of force intervals of the integral."""

    coefficients: np.ndarray
    normalization: Normalization
    n_intervals: int = 64

    def __post_init__(self) -> None:
        coefficients = np.array(self.coefficients, dtype=np.float64)
        if coefficients.shape != (2, 10):
            raise InputError(f"coefficients: expected shape (2, 10), got {coefficients.shape}")
        if not np.all(np.isfinite(coefficients)):
            raise InputError("coefficients: contain non-finite values")
        if int(self.n_intervals) < 1:
            raise InputError(f"n_intervals: expected at least 1, got {self.n_intervals}")
        coefficients.setflags(write=False)
        object.__setattr__(self, "coefficients", coefficients)
        object.__setattr__(self, "n_intervals", int(self.n_intervals))

    def rate(self, h_mm: float, shape: tuple[int, int]) -> np.ndarray:
        """``d(x, y, h)`` on a ``(rows, cols)`` pixel grid: (2, rows, cols), pixels per unit normalised force."""
        rows, cols = shape
        return _core.regression_rate(self.coefficients, self.normalization.as_array(), float(h_mm), rows, cols)

    def force_integrals(self, force_n: float, profile: StiffnessProfile) -> tuple[float, float, float]:
        """Normalised force integrals of ``1``, ``h`` and ``h^2`` from 0 to ``force_n``."""
        return _core.force_integrals(float(force_n), profile.as_tuple(), self.normalization.as_array(), self.n_intervals)

    def displacement(self, force_n: float, profile: StiffnessProfile, shape: tuple[int, int]) -> np.ndarray:
        """``D(x, y, F)``: where each zero-force pixel sits at ``force_n``, (2, rows, cols) pixels."""
        rows, cols = shape
        return _core.integrated_displacement(self.coefficients, self.normalization.as_array(), float(force_n),
                                             profile.as_tuple(), self.n_intervals, rows, cols)
