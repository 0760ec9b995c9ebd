"""Fitting a displacement model to measured displacements (paper eq. 11): :func:`fit_regression`."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from functools import partial

import numpy as np
import scipy.linalg
from threadpoolctl import ThreadpoolController

from ..errors import FitError, InputError
from ..options import ANCHORS, COUPLINGS, INTEGRATIONS, SOLVERS, Anchor, Basis, Coupling, Integration, Solver
from ._anchored import VesselAnchoredModel
from ._basis import BSPLINE_MIN_FUNCTIONS, M_TERMS, _roughness, bspline_vector, regression_vector
from ._model import (
    N_INTERVALS,
    BSplineDisplacementModel,
    DeformationModel,
    DisplacementModel,
    QuadraticDisplacementModel,
)
from ._observations import Observations, SpatialVector, _normalization_for, _Samples, _samples, _VesselPart
from ._smoothness import _cross_validated_smoothness, _penalised_solve

#: NumPy's and SciPy's BLAS, the libraries a fit calls (both loaded by the imports above), found once:
#: finding them reads the process's memory map, which takes longer than a small fit's solve.
_THREADPOOLS = ThreadpoolController()


@dataclass(frozen=True, eq=False)
class RegressionFit:
    """A fitted model, its loss (eq. 11, in normalised units: the mean over the tracked samples of the
    squared error summed over both components, plus ``wall_weight`` times that mean over the wall
    samples, without the smoothness penalty), the solver and its iterations (0 for the exact solver),
    the samples (tracked and wall) and the smoothness weight used (0 where nothing is penalised: the
    quadratic basis without a vessel part).

    ``fitted`` is the model as fitted; :attr:`model` the same where it lives in image coordinates
    alone (what the kernels and code written for :class:`DisplacementModel` take), an error for a
    :class:`VesselAnchoredModel`."""

    fitted: DeformationModel
    loss: float
    solver: Solver
    iterations: int
    n_samples: int
    smoothness: float = 0.0

    @property
    def model(self) -> DisplacementModel:
        """The fitted model in image coordinates; FitError for a vessel-anchored fit (see :attr:`fitted`)."""
        if self.fitted.anchor != "image":
            raise FitError(
                "model: this fit is vessel-anchored (anchor='vessel'); take fit.fitted (a VesselAnchoredModel, "
                "which correct_frames, correct_recording, correct_and_compound and save_model take)"
            )
        return self.fitted.image_model


def _adam(
    design: np.ndarray, targets: np.ndarray, learning_rate: float, max_iterations: int, tolerance: float
) -> tuple[np.ndarray, int]:
    """Full-batch ADAM (Kingma and Ba 2014, beta1 0.9, beta2 0.999) from K = 0 on the eq. 11 loss of
    the weighted rows (``sum((A K^T - b)^2)``, the mean squared error without wall samples); stops
    when the loss improves by less than ``tolerance`` (relative) over 100 iterations.

    The loss is quadratic, so its gradient ``2 (K A^T A - b^T A)`` needs only the 10 x 10 Gram
    matrix: each iteration costs O(100), not O(samples), with the same iterates.
    """
    gram, moment = design.T @ design, targets.T @ design
    target_energy = float(np.sum(targets**2))

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


def _spatial_basis(basis: Basis | tuple[str, int, int]) -> tuple[SpatialVector, tuple[int, ...]]:
    """The terms function and the coefficient shape of ``basis``: ``"quadratic"`` or
    ``("bspline", n_x, n_y)``."""
    if basis == "quadratic":
        return regression_vector, (2, len(M_TERMS))
    if (
        isinstance(basis, tuple)
        and len(basis) == 3
        and basis[0] == "bspline"
        and all(isinstance(n, (int, np.integer)) and n >= BSPLINE_MIN_FUNCTIONS for n in basis[1:])
    ):
        n_functions = (int(basis[2]), int(basis[1]))
        return partial(bspline_vector, n_functions=n_functions), (2, 3, *n_functions)
    raise InputError(
        f"basis: expected 'quadratic' or ('bspline', n_x, n_y) with n_x, n_y integers >= "
        f"{BSPLINE_MIN_FUNCTIONS}, got {basis!r}"
    )


def _frame_shape_of(observations: Sequence[Observations], frame_shape: tuple[int, int] | None) -> tuple[int, int]:
    """The frame shape the observations were tracked on: ``frame_shape`` if given, else theirs."""
    carried = {o.frame_shape for o in observations if o.frame_shape is not None}
    if frame_shape is not None:
        shape = (int(frame_shape[0]), int(frame_shape[1]))
        if carried - {shape}:
            raise InputError(f"frame_shape: {shape} differs from the observations' frame shape {sorted(carried)}")
        return shape
    if len(carried) != 1:
        found = f"they carry {sorted(carried)}" if carried else "they carry none"
        raise InputError(f"frame_shape: expected the observations to carry one frame shape, {found}; pass frame_shape")
    return carried.pop()


def fit_regression(
    observations: Sequence[Observations],
    frame_shape: tuple[int, int] | None = None,
    solver: Solver = "exact",
    *,
    coupling: Coupling = "stiffness",
    learning_rate: float = 0.01,
    max_iterations: int = 50_000,
    tolerance: float = 1e-7,
    integration: Integration = "force",
    basis: Basis | tuple[str, int, int] = "quadratic",
    smoothness: float | None = None,
    n_folds: int = 5,
    wall_observations: Sequence[Observations] | None = None,
    wall_weight: float = 1.0,
    anchor: Anchor = "image",
) -> RegressionFit:
    """Fit the displacement model to measured displacements (paper eq. 11).

    Inputs are normalised to [0, 1] as the paper says. The loss is the mean squared error over the
    tracked samples plus ``wall_weight`` times the mean squared error over the vessel-wall samples.

    Parameters
    ----------
    observations : sequence of Observations
        One per palpation: the tissue tracks (and boundary rows).
    frame_shape : tuple of int, optional
        ``(rows, cols)`` of the frames; None: the one the observations carry.
    solver : {"exact", "adam"}
        The least-squares solution the loss has (it is quadratic in K), or the paper's ADAM with
        step ``learning_rate``, at most ``max_iterations`` and a relative ``tolerance``.
    coupling : {"stiffness", "force"}
        ``h = F / k`` (the paper) or the force-based baseline ``h = F``.
    learning_rate, max_iterations, tolerance
        ADAM's settings.
    integration : {"force", "displacement"}
        Integrate the rate over force or over probe displacement.
    basis : "quadratic" or ("bspline", n_x, n_y)
        The paper's quadratic, or a :class:`BSplineDisplacementModel` (exact solver only) whose
        loss adds ``smoothness`` times the summed squared second differences of each force term's
        coefficient grid (normalised units); without ``smoothness`` the weight is chosen by
        ``n_folds``-fold cross-validation over spatial regions (see :data:`SMOOTHNESS_GRID`). A
        finer grid (12 x 12, 16 x 16 on a 256 x 256 frame: knots 20-30 pixels apart) can follow a
        vessel's local collapse; the cross-validated penalty keeps it smooth where nothing is
        observed (benches/bench_wall.py measures the grids).
    smoothness : float, optional
        The B-spline smoothness weight.
    n_folds : int
        Folds of the cross-validation.
    wall_observations : sequence of Observations, optional
        Displacements of the vessel wall (:func:`usdeform.fitting.track_vessel_wall`), any
        number of palpations, as constraints of their own weight.
    wall_weight : float
        Weight of the wall samples' mean squared error against the tracks' (>= 0).
    anchor : {"image", "vessel"}
        A model in image coordinates, or a :class:`VesselAnchoredModel` (exact solver): the basis
        plus a finer B-spline part on a window around each palpation's lumen
        (``Observations.vessel``, at least one needed), which correction moves and scales with the
        lumen of the frame it corrects, and a part of its own for each further vessel
        (``Observations.other_vessels``: a vein collapses more than the artery beside it). For vessels
        that move along the sweep, differ in size or in lumen stiffness.

    Returns
    -------
    RegressionFit
        The model (with the frame shape) and the fit's loss and settings.
    """
    if solver not in SOLVERS:
        raise InputError(f"solver: expected one of {SOLVERS}, got {solver!r}")
    if coupling not in COUPLINGS:
        raise InputError(f"coupling: expected one of {COUPLINGS}, got {coupling!r}")
    if integration not in INTEGRATIONS:
        raise InputError(f"integration: expected one of {INTEGRATIONS}, got {integration!r}")
    spatial_vector, coefficient_shape = _spatial_basis(basis)
    is_spline = len(coefficient_shape) == 4
    if anchor not in ANCHORS:
        raise InputError(f"anchor: expected one of {ANCHORS}, got {anchor!r}")
    # B-splines and the vessel part are penalised by their roughness, with the smoothness chosen by
    # cross-validation (the quadratic under a vessel part is not penalised).
    penalised = is_spline or anchor == "vessel"
    if penalised and solver != "exact":
        raise InputError(
            f"solver: the B-spline basis and the vessel-anchored model are fitted by the exact solver only, "
            f"got {solver!r}"
        )
    if smoothness is not None and not (penalised and np.isfinite(smoothness) and smoothness >= 0):
        raise InputError(
            f"smoothness: expected a finite value >= 0 with a B-spline basis or anchor='vessel', got {smoothness!r} "
            f"with basis {basis!r}"
        )
    if int(n_folds) < 2:
        raise InputError(f"n_folds: expected at least 2, got {n_folds}")
    if not (np.isfinite(wall_weight) and wall_weight >= 0):
        raise InputError(f"wall_weight: expected a finite weight >= 0, got {wall_weight!r}")
    observations = list(observations)
    walls = list(wall_observations or [])
    if not observations:
        raise FitError("observations: need at least one palpation")
    frame_shape = _frame_shape_of(observations + walls, frame_shape)
    rows, cols = frame_shape
    for name, group in (("observations", observations), ("wall_observations", walls)):
        for number, o in enumerate(group):
            outside = (o.points_px < 0) | (o.points_px > [cols - 1, rows - 1])
            if np.any(outside):
                raise InputError(
                    f"{name}[{number}].points_px: points outside the {rows} x {cols} frame_shape; "
                    "the frame shape sets the model's normalisation and must be the frames' own"
                )
    normalization = _normalization_for(observations + walls, frame_shape, coupling, integration)
    vessels: list[_VesselPart] = []
    if anchor == "vessel":
        vessels = _VesselPart.for_observations(observations + walls)
        if not vessels:
            raise FitError(
                "observations: anchor='vessel' needs the lumen of at least one palpation's lowest-force frame "
                "(Observations.vessel, set where the vessel wall is measured)"
            )
    n_image_terms = int(np.prod(coefficient_shape[1:]))
    n_terms = n_image_terms + sum(3 * vessel.n_inner**2 for vessel in vessels)
    problem = partial(
        _samples,
        normalization=normalization,
        coupling=coupling,
        integration=integration,
        spatial_vector=spatial_vector,
        n_terms=n_terms,
        vessels=vessels,
    )
    samples = _Samples.weighted(problem(observations), problem(walls) if wall_weight > 0 else [], wall_weight)
    n_samples = samples.n_samples
    # BLAS on one thread: OpenBLAS's threaded routines round differently with the thread count, and
    # the fit must not depend on it (the systems are a few hundred unknowns: one thread is fast).
    with _THREADPOOLS.limit(limits=1, user_api="blas"):
        if penalised:
            if is_spline:
                roughness = _roughness((coefficient_shape[2], coefficient_shape[3]))
            else:
                roughness = np.zeros((n_image_terms, n_image_terms))
            if vessels:
                roughness = scipy.linalg.block_diag(roughness, *(vessel.roughness() for vessel in vessels))
            gram, moment, _ = samples.normal_equations()
            rank = np.linalg.matrix_rank(gram + roughness, hermitian=True) if n_samples else 0
            if rank < n_terms:
                raise FitError(
                    f"observations: {n_samples} valid samples with the smoothness penalty reach rank "
                    f"{rank} of the {n_terms} coefficients; track more points over more distinct "
                    "forces, or use fewer basis functions"
                )
            if smoothness is None:
                smoothness, _ = _cross_validated_smoothness(samples, roughness, int(n_folds))
            coefficients = _penalised_solve(samples, gram, moment, roughness, float(smoothness))
            iterations = 0
            image_type = BSplineDisplacementModel if is_spline else QuadraticDisplacementModel
            image_model = image_type(
                coefficients[:, :n_image_terms].reshape(coefficient_shape),
                normalization,
                N_INTERVALS,
                coupling,
                integration,
                frame_shape,
            )
            model: DeformationModel = image_model
            if vessels:
                first = n_image_terms
                parts = []
                for vessel in vessels:
                    size = 3 * vessel.n_inner**2
                    grid = coefficients[:, first : first + size].reshape(2, 3, vessel.n_inner, vessel.n_inner)
                    parts.append((grid, vessel.reference))
                    first += size
                model = VesselAnchoredModel(
                    image_model, parts[0][0], parts[0][1], vessels[0].window_radii, other_vessels=tuple(parts[1:])
                )
        else:
            dense, targets = samples.design()
            if dense.shape[0] < n_terms or np.linalg.matrix_rank(dense) < n_terms:
                raise FitError(
                    f"observations: {n_samples} valid samples with design rank "
                    f"{np.linalg.matrix_rank(dense) if dense.shape[0] else 0} cannot determine the 10 terms of K; "
                    "track more points over more distinct forces"
                )
            if solver == "exact":
                coefficients = np.linalg.lstsq(dense, targets, rcond=None)[0].T
                iterations = 0
            else:
                coefficients, iterations = _adam(dense, targets, learning_rate, max_iterations, tolerance)
            model = QuadraticDisplacementModel(
                coefficients, normalization, N_INTERVALS, coupling, integration, frame_shape
            )
        loss = samples.squared_error(coefficients)
    return RegressionFit(model, loss, solver, iterations, n_samples, float(smoothness or 0.0))
