"""The coupled quadratic displacement regression (paper eqs. 7-9 and 12).

``d(x, y, h) = K @ M(x, y, h)`` with ``M = [x^2, y^2, h^2, xy, xh, yh, x, y, h, 1]`` on normalised
inputs and ``h = F / k`` (mm). The displacement at force ``F`` is the integral of ``d`` over the
normalised force from 0 to ``F``, with the stiffness ``k`` held constant on each of ``n_intervals``
equal force intervals. Displacements are in pixels, ``(lateral, axial)`` = ``(x, y)``.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from . import _core
from .errors import FitError, InputError
from .stiffness import StiffnessProfile

__all__ = [
    "M_TERMS",
    "Normalization",
    "Observations",
    "QuadraticDisplacementModel",
    "RegressionFit",
    "fit_regression",
    "force_terms",
    "regression_vector",
]

#: How the model couples force and tissue: ``h = F / k`` (the paper) or ``h = F`` (Sun et al. 2010).
COUPLINGS = ("stiffness", "force")
#: What the rate is integrated over: force (the paper's eq. 8) or probe displacement (``dlambda = dF / k``).
INTEGRATIONS = ("force", "displacement")

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


def force_terms(force_n: float, profile: StiffnessProfile, normalization: Normalization, n_intervals: int,
                integration: str = "force") -> tuple[float, float, float]:
    """Normalised integrals of ``1``, ``h`` and ``h^2`` from 0 to ``force_n`` (eq. 8), over force or,
    with ``integration="displacement"``, over probe displacement (normalised by ``h_scale``)."""
    return _core.force_integrals(float(force_n), profile.as_tuple(), normalization.as_array(), int(n_intervals),
                                 integration)


@dataclass(frozen=True, eq=False)
class QuadraticDisplacementModel:
    """``K`` (2 x 10: lateral row, axial row, columns in the order of :data:`M_TERMS`) with its
    normalisation, the number of force intervals of the integral, the ``coupling``: ``"stiffness"``
    (``h = F / k``, the paper) or ``"force"`` (``h = F``, the force-based baseline of Sun et al.
    2010, which ignores the stiffness profile it is given), and the ``integration`` variable:
    ``"force"`` (the paper's eq. 8) or ``"displacement"`` (over lambda, ``dlambda = dF / k``: every
    term then follows a change of stiffness; see :mod:`usdeform.experiments.paper_2d`)."""

    coefficients: np.ndarray
    normalization: Normalization
    n_intervals: int = 64
    coupling: str = "stiffness"
    integration: str = "force"

    def __post_init__(self) -> None:
        coefficients = np.array(self.coefficients, dtype=np.float64, order="C")
        if coefficients.shape != (2, 10):
            raise InputError(f"coefficients: expected shape (2, 10), got {coefficients.shape}")
        if not np.all(np.isfinite(coefficients)):
            raise InputError("coefficients: contain non-finite values")
        if int(self.n_intervals) < 1:
            raise InputError(f"n_intervals: expected at least 1, got {self.n_intervals}")
        if self.coupling not in COUPLINGS:
            raise InputError(f"coupling: expected one of {COUPLINGS}, got {self.coupling!r}")
        if self.integration not in INTEGRATIONS:
            raise InputError(f"integration: expected one of {INTEGRATIONS}, got {self.integration!r}")
        coefficients.setflags(write=False)
        object.__setattr__(self, "coefficients", coefficients)
        object.__setattr__(self, "n_intervals", int(self.n_intervals))

    def rate(self, h_mm: float, shape: tuple[int, int]) -> np.ndarray:
        """``d(x, y, h)`` on a ``(rows, cols)`` pixel grid: (2, rows, cols), pixels per unit normalised force."""
        rows, cols = shape
        return _core.regression_rate(self.coefficients, self.normalization.as_array(), float(h_mm), rows, cols)

    def coupled_profile(self, profile: StiffnessProfile) -> StiffnessProfile:
        """The profile the model actually uses: ``profile``, or 1 N/mm everywhere for force coupling."""
        return profile if self.coupling == "stiffness" else StiffnessProfile.UNIT

    def force_integrals(self, force_n: float, profile: StiffnessProfile) -> tuple[float, float, float]:
        """Normalised force integrals of ``1``, ``h`` and ``h^2`` from 0 to ``force_n``."""
        return force_terms(force_n, self.coupled_profile(profile), self.normalization, self.n_intervals,
                           self.integration)

    def displacement(self, force_n: float, profile: StiffnessProfile, shape: tuple[int, int]) -> np.ndarray:
        """``D(x, y, F)``: where each zero-force pixel sits at ``force_n``, (2, rows, cols) pixels."""
        rows, cols = shape
        return _core.integrated_displacement(self.coefficients, self.normalization.as_array(), float(force_n),
                                             self.coupled_profile(profile).as_tuple(), self.n_intervals, rows, cols,
                                             self.integration)


def regression_vector(x_n: np.ndarray, y_n: np.ndarray, h_terms: tuple[float, float, float]) -> np.ndarray:
    """``M`` of paper eq. 7 with its ``(1, h, h^2)`` factors replaced by ``h_terms``: shape (10, *x_n.shape).

    ``h_terms = (1, h, h^2)`` gives ``M(x, y, h)``; the force integrals of ``1, h, h^2`` give the
    integral of ``M`` over force (eq. 8), which is how the displacement is linear in ``K``.
    """
    one, h, h2 = h_terms
    return np.stack([x_n**2 * one, y_n**2 * one, np.full_like(x_n, h2), x_n * y_n * one, x_n * h, y_n * h,
                     x_n * one, y_n * one, np.full_like(x_n, h), np.full_like(x_n, one)])


@dataclass(frozen=True, eq=False)
class Observations:
    """Measured displacements of one palpation, from its reference (lowest-force) frame.

    ``points_px`` (N, 2) are the tracked points' (x, y) in the reference frame; ``displacements_px``
    (M, N, 2) their (lateral, axial) displacement to each of M frames, trusted where ``valid`` (M, N);
    ``forces_n`` (M,) the frames' forces and ``reference_force_n`` the reference frame's (N);
    ``profile`` the palpation's stiffness profile.
    """

    points_px: np.ndarray
    displacements_px: np.ndarray
    valid: np.ndarray
    forces_n: np.ndarray
    reference_force_n: float
    profile: StiffnessProfile

    def __post_init__(self) -> None:
        points = np.asarray(self.points_px, dtype=np.float64)
        displacements = np.asarray(self.displacements_px, dtype=np.float64)
        valid = np.asarray(self.valid, dtype=bool)
        forces = np.asarray(self.forces_n, dtype=np.float64)
        if points.ndim != 2 or points.shape[1] != 2:
            raise InputError(f"points_px: expected shape (n_points, 2), got {points.shape}")
        expected = (forces.shape[0], points.shape[0], 2) if forces.ndim == 1 else None
        if expected is None or displacements.shape != expected or valid.shape != expected[:2]:
            raise InputError(f"displacements_px, valid, forces_n: expected shapes (M, N, 2), (M, N), (M,) with "
                             f"N = {points.shape[0]} points, got {displacements.shape}, {valid.shape}, {forces.shape}")
        if not np.all(np.isfinite(displacements[valid])) or not np.all(np.isfinite(forces)):
            raise InputError("displacements_px, forces_n: non-finite values where valid")
        for name, value in (("points_px", points), ("displacements_px", displacements), ("valid", valid),
                            ("forces_n", forces)):
            object.__setattr__(self, name, value)
        object.__setattr__(self, "reference_force_n", float(self.reference_force_n))


@dataclass(frozen=True, eq=False)
class RegressionFit:
    """A fitted model, its loss (eq. 11, in normalised units, mean over samples of the squared
    error summed over both components), the solver and its iterations (0 for the exact solver)."""

    model: QuadraticDisplacementModel
    loss: float
    solver: str
    iterations: int
    n_samples: int


def _normalization_for(observations: Sequence[Observations], frame_shape: tuple[int, int], coupling: str,
                       integration: str) -> Normalization:
    """Scales mapping the data onto [0, 1]: pixel coordinates, force, h (and lambda when integrating
    over it) and each displacement component."""
    max_force = max(float(np.max(np.abs(o.forces_n))) for o in observations)
    max_h = 0.0
    for o in observations:
        profile = o.profile if coupling == "stiffness" else StiffnessProfile.UNIT
        lam = profile.lambda_at(o.forces_n)
        max_h = max(max_h, float(np.max(np.abs(o.forces_n) / profile.stiffness_at(lam))))
        if integration == "displacement":
            max_h = max(max_h, float(np.max(np.abs(lam - profile.lambda_at(0.0)))))
    measured = np.concatenate([o.displacements_px[o.valid] for o in observations])
    lateral, axial = (float(np.max(np.abs(measured[:, c]))) if measured.size else 1.0 for c in (0, 1))
    rows, cols = frame_shape
    return Normalization.for_frames(rows, cols, max_force or 1.0, max_h or 1.0, lateral or 1.0, axial or 1.0)


def _least_squares_problem(observations: Sequence[Observations], normalization: Normalization, n_intervals: int,
                           coupling: str, integration: str) -> tuple[np.ndarray, np.ndarray]:
    """Design matrix A (samples, 10) and normalised targets b (samples, 2), so that the loss of K
    is ``mean(sum((A @ K.T - b)^2, axis=1))``. Each row is the integrated ``M`` at the frame's force
    minus that at the reference force, since displacements are measured from the reference frame."""
    rows_a, rows_b = [], []
    for o in observations:
        profile = o.profile if coupling == "stiffness" else StiffnessProfile.UNIT
        x_n = o.points_px[:, 0] / normalization.x_scale
        y_n = o.points_px[:, 1] / normalization.y_scale
        reference = regression_vector(x_n, y_n, force_terms(o.reference_force_n, profile, normalization, n_intervals,
                                                            integration))
        for frame, force in enumerate(o.forces_n):
            keep = o.valid[frame]
            at_force = regression_vector(x_n, y_n, force_terms(force, profile, normalization, n_intervals, integration))
            rows_a.append((at_force - reference)[:, keep].T)
            rows_b.append(o.displacements_px[frame, keep] / [normalization.lateral_scale, normalization.axial_scale])
    return np.concatenate(rows_a), np.concatenate(rows_b)


def _loss(design: np.ndarray, targets: np.ndarray, coefficients: np.ndarray) -> float:
    return float(np.mean(np.sum((design @ coefficients.T - targets) ** 2, axis=1)))


def _adam(design: np.ndarray, targets: np.ndarray, learning_rate: float, max_iterations: int,
          tolerance: float) -> tuple[np.ndarray, int]:
    """Full-batch ADAM (Kingma and Ba 2014, beta1 0.9, beta2 0.999) from K = 0 on the eq. 11 loss;
    stops when the loss improves by less than ``tolerance`` (relative) over 100 iterations.

    The loss is quadratic, so its gradient ``2/n (K A^T A - b^T A)`` needs only the 10 x 10 Gram
    matrix: each iteration costs O(100), not O(samples), with the same iterates.
    """
    n_samples = design.shape[0]
    gram, moment = design.T @ design / n_samples, targets.T @ design / n_samples
    target_energy = float(np.sum(targets**2)) / n_samples

    def loss(coefficients: np.ndarray) -> float:
        return float(np.sum(coefficients @ gram * coefficients) - 2 * np.sum(coefficients * moment) + target_energy)

    coefficients = np.zeros((2, design.shape[1]))
    first, second = np.zeros_like(coefficients), np.zeros_like(coefficients)
    beta1, beta2, epsilon = 0.9, 0.999, 1e-8
    previous = np.inf
    for iteration in range(1, max_iterations + 1):
        gradient = 2.0 * (coefficients @ gram - moment)
        first = beta1 * first + (1 - beta1) * gradient
        second = beta2 * second + (1 - beta2) * gradient**2
        step = (first / (1 - beta1**iteration)) / (np.sqrt(second / (1 - beta2**iteration)) + epsilon)
        coefficients = coefficients - learning_rate * step
        if iteration % 100 == 0:
            current = loss(coefficients)
            if np.isfinite(previous) and previous - current <= tolerance * previous:
                return coefficients, iteration
            previous = current
    return coefficients, max_iterations


def fit_regression(observations: Sequence[Observations], frame_shape: tuple[int, int], solver: str = "exact",
                   coupling: str = "stiffness", n_intervals: int = 64, learning_rate: float = 0.01,
                   max_iterations: int = 50_000, tolerance: float = 1e-7,
                   integration: str = "force") -> RegressionFit:
    """Fit ``K`` of the coupled quadratic regression to measured displacements (paper eq. 11).

    ``solver="exact"`` solves the least-squares problem the loss is (it is quadratic in K);
    ``solver="adam"`` runs the paper's ADAM with step ``learning_rate``. ``coupling="force"`` fits
    the force-based baseline (``h = F``); ``integration="displacement"`` integrates the rate over
    probe displacement instead of force. Inputs are normalised to [0, 1] as the paper says.
    """
    if solver not in ("exact", "adam"):
        raise InputError(f"solver: expected 'exact' or 'adam', got {solver!r}")
    if coupling not in COUPLINGS:
        raise InputError(f"coupling: expected one of {COUPLINGS}, got {coupling!r}")
    if integration not in INTEGRATIONS:
        raise InputError(f"integration: expected one of {INTEGRATIONS}, got {integration!r}")
    observations = list(observations)
    if not observations:
        raise FitError("observations: need at least one palpation")
    normalization = _normalization_for(observations, frame_shape, coupling, integration)
    design, targets = _least_squares_problem(observations, normalization, n_intervals, coupling, integration)
    if design.shape[0] < 10 or np.linalg.matrix_rank(design) < 10:
        raise FitError(f"observations: {design.shape[0]} valid samples with design rank "
                       f"{np.linalg.matrix_rank(design) if design.size else 0} cannot determine the 10 terms of K; "
                       "track more points over more distinct forces")
    if solver == "exact":
        coefficients = np.linalg.lstsq(design, targets, rcond=None)[0].T
        iterations = 0
    else:
        coefficients, iterations = _adam(design, targets, learning_rate, max_iterations, tolerance)
    model = QuadraticDisplacementModel(coefficients, normalization, n_intervals, coupling, integration)
    return RegressionFit(model, _loss(design, targets, coefficients), solver, iterations, design.shape[0])
