"""The coupled quadratic regression fit (paper eqs. 7-11), by exact least squares and by ADAM; the
cubic B-spline basis fitted by penalised least squares with a cross-validated smoothness."""

from __future__ import annotations

import warnings
from dataclasses import replace

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from usdeform.errors import FitError, InputError
from usdeform.regression import (
    SMOOTHNESS_GRID,
    BSplineDisplacementModel,
    DisplacementModel,
    Normalization,
    Observations,
    QuadraticDisplacementModel,
    StiffnessProfile,
    fit_regression,
)

ROWS, COLS = 96, 80


def planted_observations(
    model: DisplacementModel,
    profile: StiffnessProfile,
    rng: np.random.Generator,
    noise_px: float = 0.0,
    reference_force: float = 0.3,
) -> Observations:
    """Displacements of a grid of points from the reference force to 25 forces, from ``model``."""
    y, x = np.mgrid[3:ROWS:7, 2:COLS:6]
    points = np.stack([x.ravel(), y.ravel()], axis=1).astype(float)
    forces = np.linspace(1.0, 18.0, 25)

    def at(force: float) -> np.ndarray:
        field = model.displacement(force, profile, (ROWS, COLS))
        return field[:, y.ravel(), x.ravel()].T

    displacements = np.stack([at(f) - at(reference_force) for f in forces])
    displacements += rng.normal(0, noise_px, displacements.shape)
    valid = rng.random(displacements.shape[:2]) > 0.1
    displacements[~valid] = np.nan
    return Observations(points, displacements, valid, forces, reference_force, profile)


@pytest.fixture
def planted() -> tuple[QuadraticDisplacementModel, StiffnessProfile]:
    rng = np.random.default_rng(2)
    model = QuadraticDisplacementModel(rng.normal(0, 1, (2, 10)), Normalization.for_frames(ROWS, COLS, 20, 9, 4, 9))
    return model, StiffnessProfile(0.06, 1.3, 0.0)


def test_exact_solver_recovers_a_planted_model(planted) -> None:
    model, profile = planted
    fit = fit_regression([planted_observations(model, profile, np.random.default_rng(0))], (ROWS, COLS))
    assert fit.loss < 1e-20
    np.testing.assert_allclose(
        fit.model.displacement(12.0, profile, (ROWS, COLS)), model.displacement(12.0, profile, (ROWS, COLS)), atol=1e-8
    )


def test_adam_approaches_the_planted_model_and_never_beats_exact(planted) -> None:
    model, profile = planted
    observations = [planted_observations(model, profile, np.random.default_rng(s), noise_px=0.2) for s in (0, 1)]
    exact = fit_regression(observations, (ROWS, COLS), "exact")
    adam = fit_regression(observations, (ROWS, COLS), "adam")
    assert adam.iterations > 0 and exact.iterations == 0
    assert exact.loss <= adam.loss
    assert adam.loss < 1.5 * exact.loss  # ADAM converges close to the least-squares minimum
    error = np.abs(
        adam.model.displacement(12.0, profile, (ROWS, COLS)) - model.displacement(12.0, profile, (ROWS, COLS))
    )
    assert np.percentile(error, 95) < 0.5  # pixels


def test_constant_stiffness_makes_force_and_stiffness_coupling_agree(planted) -> None:
    """With k constant, h = F / k is F up to scale: both couplings predict the same displacements."""
    model, _ = planted
    flat = StiffnessProfile.constant(2.2)
    observations = [planted_observations(model, flat, np.random.default_rng(3), noise_px=0.3)]
    stiffness_fit = fit_regression(observations, (ROWS, COLS), coupling="stiffness")
    force_fit = fit_regression(observations, (ROWS, COLS), coupling="force")
    assert stiffness_fit.loss == pytest.approx(force_fit.loss, rel=1e-9)
    np.testing.assert_allclose(
        stiffness_fit.model.displacement(9.0, flat, (ROWS, COLS)),
        force_fit.model.displacement(9.0, StiffnessProfile(0.3, 5.0), (ROWS, COLS)),
        atol=1e-8,
    )


def test_stiffness_coupling_propagates_where_force_coupling_cannot(planted) -> None:
    """Fitted on a stiff tissue, only the stiffness-coupled model predicts a softer tissue's motion."""
    model, _ = planted
    stiff, soft = StiffnessProfile(0.02, 3.2), StiffnessProfile(0.08, 0.8)
    observations = [planted_observations(model, stiff, np.random.default_rng(4))]
    truth = model.displacement(6.0, soft, (ROWS, COLS))
    by_stiffness = fit_regression(observations, (ROWS, COLS), coupling="stiffness").model
    by_force = fit_regression(observations, (ROWS, COLS), coupling="force").model
    error_stiffness = np.abs(by_stiffness.displacement(6.0, soft, (ROWS, COLS)) - truth).max()
    error_force = np.abs(by_force.displacement(6.0, soft, (ROWS, COLS)) - truth).max()
    assert error_stiffness < 1e-6 < error_force


def test_degenerate_data_is_a_fit_error(planted) -> None:
    model, profile = planted
    observations = planted_observations(model, profile, np.random.default_rng(0))
    one_point = Observations(
        observations.points_px[:1],
        observations.displacements_px[:, :1],
        observations.valid[:, :1],
        observations.forces_n,
        0.3,
        profile,
    )
    with pytest.raises(FitError, match="cannot determine the 10 terms"):
        fit_regression([one_point], (ROWS, COLS))
    with pytest.raises(FitError, match="at least one palpation"):
        fit_regression([], (ROWS, COLS))
    with pytest.raises(InputError, match="solver"):
        fit_regression([observations], (ROWS, COLS), solver="sgd")


def test_observations_validate_shapes() -> None:
    with pytest.raises(InputError, match="expected shapes"):
        Observations(
            np.zeros((5, 2)), np.zeros((3, 4, 2)), np.ones((3, 4), bool), np.ones(3), 0.0, StiffnessProfile.UNIT
        )


def test_displacement_integration_propagates_a_linear_tissue_by_its_stiffness(planted) -> None:
    """Integrated over probe displacement, a model fitted on one tissue predicts another from its
    stiffness alone, where the paper's force integral keeps most of the stiff tissue's response."""
    model, _ = planted
    planted_model = QuadraticDisplacementModel(model.coefficients, model.normalization, integration="displacement")
    stiff, soft = StiffnessProfile(0.02, 3.2), StiffnessProfile(0.08, 0.8)
    observations = [planted_observations(planted_model, stiff, np.random.default_rng(5))]
    fit = fit_regression(observations, (ROWS, COLS), integration="displacement")
    assert fit.model.integration == "displacement" and fit.loss < 1e-20
    np.testing.assert_allclose(
        fit.model.displacement(6.0, soft, (ROWS, COLS)), planted_model.displacement(6.0, soft, (ROWS, COLS)), atol=1e-6
    )


def test_bspline_fit_recovers_a_planted_bspline_field(planted) -> None:
    _, profile = planted
    rng = np.random.default_rng(8)
    model = BSplineDisplacementModel(rng.normal(0, 1, (2, 3, 5, 6)), Normalization.for_frames(ROWS, COLS, 20, 9, 4, 9))
    observations = [planted_observations(model, profile, np.random.default_rng(0))]
    truth = model.displacement(12.0, profile, (ROWS, COLS))
    exact = fit_regression(observations, (ROWS, COLS), basis=("bspline", 6, 5), smoothness=0.0)
    assert isinstance(exact.model, BSplineDisplacementModel) and exact.model.n_functions == (5, 6)
    assert exact.loss < 1e-20
    np.testing.assert_allclose(exact.model.displacement(12.0, profile, (ROWS, COLS)), truth, atol=1e-8)
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # the search ends where the penalty no longer matters: no warning
        chosen = fit_regression(observations, (ROWS, COLS), basis=("bspline", 6, 5))
    assert chosen.smoothness < min(SMOOTHNESS_GRID)  # noise-free data: the least smoothing predicts best
    error = np.abs(chosen.model.displacement(12.0, profile, (ROWS, COLS)) - truth).max()
    assert error < 0.02 * np.abs(truth).max()


def test_bspline_basis_holds_the_quadratic_model_exactly(planted) -> None:
    """Every spatial part of the paper's model is a polynomial of degree <= 2, inside the cubic spline space."""
    model, profile = planted
    fit = fit_regression(
        [planted_observations(model, profile, np.random.default_rng(0))],
        (ROWS, COLS),
        basis=("bspline", 4, 4),
        smoothness=0.0,
    )
    assert fit.loss < 1e-20
    np.testing.assert_allclose(
        fit.model.displacement(12.0, profile, (ROWS, COLS)), model.displacement(12.0, profile, (ROWS, COLS)), atol=1e-8
    )


def test_cross_validated_smoothness_tames_noise_on_a_fine_basis(planted) -> None:
    model, profile = planted
    observations = [planted_observations(model, profile, np.random.default_rng(0), noise_px=1.0)]
    truth = model.displacement(12.0, profile, (ROWS, COLS))

    def rms_error(fit) -> float:
        return float(np.sqrt(np.mean((fit.model.displacement(12.0, profile, (ROWS, COLS)) - truth) ** 2)))

    chosen = fit_regression(observations, (ROWS, COLS), basis=("bspline", 10, 12))
    unpenalised = fit_regression(observations, (ROWS, COLS), basis=("bspline", 10, 12), smoothness=0.0)
    assert chosen.smoothness > min(SMOOTHNESS_GRID)
    assert unpenalised.loss < chosen.loss  # the penalty trades training fit ...
    assert rms_error(chosen) < 0.2 * rms_error(unpenalised)  # ... for a far better field


@pytest.mark.parametrize(
    ("arguments", "message"),
    [
        ({"basis": "cubic"}, r"^basis: expected 'quadratic' or \('bspline', n_x, n_y\)"),
        ({"basis": ("bspline", 3, 5)}, r"^basis: expected"),
        ({"basis": ("bspline", 5, 5), "solver": "adam"}, r"^solver: the B-spline basis and the vessel-anchored"),
        ({"smoothness": 1.0}, r"^smoothness: expected a finite value >= 0 with a B-spline basis"),
        ({"basis": ("bspline", 5, 5), "smoothness": -1.0}, r"^smoothness:"),
        ({"basis": ("bspline", 5, 5), "n_folds": 1}, r"^n_folds: expected at least 2"),
    ],
)
def test_bad_bspline_fit_arguments_are_input_errors(planted, arguments: dict, message: str) -> None:
    model, profile = planted
    with pytest.raises(InputError, match=message):
        fit_regression([planted_observations(model, profile, np.random.default_rng(0))], (ROWS, COLS), **arguments)


def test_too_fine_a_spline_for_the_points_is_a_fit_error(planted) -> None:
    model, profile = planted
    observations = planted_observations(model, profile, np.random.default_rng(0))
    few_points = Observations(
        observations.points_px[:3],
        observations.displacements_px[:, :3],
        observations.valid[:, :3],
        observations.forces_n,
        0.3,
        profile,
    )
    with pytest.raises(FitError, match=r"reach rank \d+ of the 192 coefficients"):
        fit_regression([few_points], (ROWS, COLS), basis=("bspline", 8, 8), smoothness=0.0)


def test_frame_shape_must_hold_the_points(planted) -> None:
    model, profile = planted
    observations = planted_observations(model, profile, np.random.default_rng(0))
    with pytest.raises(InputError, match=r"observations\[0\].points_px: points outside the 40 x 40 frame_shape"):
        fit_regression([observations], (40, 40))
    with pytest.raises(InputError, match="reference_force_n"):
        Observations(
            observations.points_px,
            observations.displacements_px,
            observations.valid,
            observations.forces_n,
            float("nan"),
            profile,
        )


def test_the_frame_shape_comes_from_the_observations(planted) -> None:
    model, profile = planted
    observations = planted_observations(model, profile, np.random.default_rng(0))
    carried = replace(observations, frame_shape=(ROWS, COLS))
    fit = fit_regression([carried])
    assert fit.model.frame_shape == (ROWS, COLS)
    np.testing.assert_array_equal(
        fit.model.coefficients, fit_regression([observations], (ROWS, COLS)).model.coefficients
    )
    with pytest.raises(InputError, match="frame_shape: expected the observations to carry one frame shape"):
        fit_regression([observations])
    with pytest.raises(InputError, match=r"frame_shape: \(64, 64\) differs from the observations' frame shape"):
        fit_regression([carried], (64, 64))
    with pytest.raises(InputError, match="frame_shape: expected the observations to carry one frame shape"):
        fit_regression([carried, replace(observations, frame_shape=(ROWS + 1, COLS))])


def direct_design(
    observations: Observations, normalization: Normalization, n_functions: tuple[int, int], integration: str
) -> tuple[np.ndarray, np.ndarray]:
    """The B-spline design rows and normalised targets written out sample by sample (the definition
    the fit's per-point sums factor): row = bspline_vector at the sample's point with the frame's
    force integrals minus the reference frame's."""
    from usdeform.regression import bspline_vector, force_terms

    reference = np.array(
        force_terms(observations.reference_force_n, observations.profile, normalization, 64, integration)
    )
    rows, targets = [], []
    for frame, force in enumerate(observations.forces_n):
        integrals = np.array(force_terms(force, observations.profile, normalization, 64, integration)) - reference
        for point in np.flatnonzero(observations.valid[frame]):
            x_n = observations.points_px[point, 0] / normalization.x_scale
            y_n = observations.points_px[point, 1] / normalization.y_scale
            rows.append(bspline_vector(np.array(x_n), np.array(y_n), tuple(integrals), n_functions))
            targets.append(
                observations.displacements_px[frame, point] / [normalization.lateral_scale, normalization.axial_scale]
            )
    n_terms = 3 * n_functions[0] * n_functions[1]
    return np.array(rows).reshape(-1, n_terms), np.array(targets).reshape(-1, 2)


@settings(max_examples=25, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(
    seed=st.integers(0, 2**32 - 1),
    n_points=st.integers(1, 30),
    n_frames=st.integers(1, 8),
    n_functions=st.tuples(st.integers(4, 7), st.integers(4, 7)),
    integration=st.sampled_from(["force", "displacement"]),
)
def test_normal_equations_from_point_sums_equal_the_design_matrix_products(
    seed: int, n_points: int, n_frames: int, n_functions: tuple[int, int], integration: str
) -> None:
    """The fit never builds the design matrix: its A^T A, A^T b, b^T b and squared error, summed per
    point over frames, equal those of the rows written out one by one."""
    from usdeform.regression._fit import _spatial_basis
    from usdeform.regression._observations import _samples

    rng = np.random.default_rng(seed)
    points = rng.uniform(0, [COLS - 1, ROWS - 1], (n_points, 2))
    valid = rng.random((n_frames, n_points)) > 0.3
    observations = Observations(
        points,
        np.where(valid[..., None], rng.normal(0, 3, (n_frames, n_points, 2)), np.nan),
        valid,
        rng.uniform(0.5, 18, n_frames),
        0.3,
        StiffnessProfile(0.06, 1.3, 0.0),
    )
    normalization = Normalization.for_frames(ROWS, COLS, 20, 9, 4, 9)
    basis = ("bspline", n_functions[1], n_functions[0])
    (palpation,) = _samples(
        [observations],
        normalization,
        "stiffness",
        integration,
        _spatial_basis(basis)[0],
        3 * n_functions[0] * n_functions[1],
    )
    weight = rng.uniform(0.1, 2)
    palpation = replace(palpation, row_scale=np.sqrt(weight))
    design, targets = direct_design(observations, normalization, n_functions, integration)
    design, targets = (
        design * np.sqrt(weight),
        targets * np.sqrt(weight),
    )
    gram, moment, energy = palpation.normal_equations(np.ones(n_points, dtype=bool))
    size = np.abs(design).max(initial=1.0) * np.abs(targets).max(initial=1.0)  # entries' scale
    np.testing.assert_allclose(gram, design.T @ design, rtol=0, atol=1e-13 * size**2)
    np.testing.assert_allclose(moment, design.T @ targets, rtol=0, atol=1e-13 * size**2)
    assert energy == pytest.approx(float(np.sum(targets**2)), rel=1e-12)
    dense_design, dense_targets = palpation.design()
    np.testing.assert_allclose(dense_design, design, rtol=1e-13, atol=1e-15 * size)
    np.testing.assert_allclose(dense_targets, targets, rtol=1e-13, atol=1e-15 * size)
    coefficients = rng.normal(0, 1, (2, design.shape[1]))
    assert palpation.squared_error(coefficients) == pytest.approx(
        float(np.sum((design @ coefficients.T - targets) ** 2)), rel=1e-10, abs=1e-300
    )


def test_penalised_bspline_fit_solves_the_normal_equations_of_the_rows(planted) -> None:
    """At a given smoothness the fit is the solution of the penalised normal equations of the rows
    written out one by one (tracks and wall, each weighted by its mean)."""
    from usdeform.regression._basis import _second_differences

    model, profile = planted
    tracks = planted_observations(model, profile, np.random.default_rng(0), noise_px=0.5)
    wall = planted_observations(model, profile, np.random.default_rng(1), noise_px=0.5)
    fit = fit_regression(
        [tracks], (ROWS, COLS), basis=("bspline", 6, 5), smoothness=1e-3, wall_observations=[wall], wall_weight=2.0
    )
    normalization = fit.model.normalization
    parts = [direct_design(o, normalization, (5, 6), "force") for o in (tracks, wall)]
    weights = [1.0 / len(parts[0][0]), 2.0 / len(parts[1][0])]
    design = np.concatenate([d * np.sqrt(w) for (d, _), w in zip(parts, weights, strict=True)])
    targets = np.concatenate([b * np.sqrt(w) for (_, b), w in zip(parts, weights, strict=True)])
    penalty = _second_differences((5, 6))
    expected = np.linalg.solve(design.T @ design + 1e-3 * penalty.T @ penalty, design.T @ targets).T
    np.testing.assert_allclose(
        fit.model.coefficients.reshape(2, -1), expected, rtol=1e-9, atol=1e-9 * np.abs(expected).max()
    )
    assert fit.loss == pytest.approx(float(np.sum((design @ expected.T - targets) ** 2)), rel=1e-9)
