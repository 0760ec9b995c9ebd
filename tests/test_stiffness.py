"""Stiffness fits from palpation (paper eqs. 4-5, Fig. 4)."""

from __future__ import annotations

import numpy as np
import pytest

from usdeform.errors import FitError, InputError
from usdeform.fitting import fit_stiffness
from usdeform.regression import StiffnessProfile


def test_quadratic_is_recovered_with_its_stiffness_statistics() -> None:
    rng = np.random.default_rng(1)
    lam = np.linspace(0.0, 9.0, 80)
    truth = StiffnessProfile(0.12, 0.45, 0.05)
    fit = fit_stiffness(truth.force_at(lam) + rng.normal(0, 0.02, lam.size), lam)
    np.testing.assert_allclose(fit.profile.as_tuple(), truth.as_tuple(), atol=0.03)
    assert fit.r_squared[1] < fit.r_squared[2] <= fit.r_squared[3] + 1e-12
    assert fit.r_squared[2] > 0.999
    mean, sd = fit.stiffness_mean_sd_n_per_m
    stiffness = truth.stiffness_at(lam) * 1000
    assert mean == pytest.approx(stiffness.mean(), rel=0.02) and sd == pytest.approx(stiffness.std(), rel=0.05)


def test_lambda_at_inverts_force_at() -> None:
    profile = StiffnessProfile(0.3, 1.1, -0.2)
    lam = np.linspace(0, 10, 11)
    np.testing.assert_allclose(profile.lambda_at(profile.force_at(lam)), lam, atol=1e-12)
    assert np.isnan(StiffnessProfile(-0.5, 2.0).lambda_at(5.0))  # beyond the curve's peak of 2 N


@pytest.mark.parametrize(
    ("force", "lam", "error", "message"),
    [
        (np.ones(3), np.arange(3.0), FitError, "too few"),
        (np.full(10, 2.0), np.arange(10.0), FitError, "rises by only"),
        (np.arange(10.0), np.zeros(10), FitError, "did not move"),
        (np.r_[np.arange(9.0), np.nan], np.arange(10.0), InputError, "force_n: non-finite value at sample 9"),
        (np.arange(10.0), np.arange(9.0), InputError, "one length"),
        (10 - 0.3 * (np.arange(10.0) - 2) ** 2, np.arange(10.0), FitError, "non-positive stiffness"),
    ],
)
def test_bad_palpations_are_rejected(force, lam, error, message: str) -> None:
    with pytest.raises(error, match=message):
        fit_stiffness(force, lam)


def test_a_preloaded_palpation_corrects_from_zero_force() -> None:
    """A palpation started at a 3 N preload: below it the curve continues with the starting stiffness."""
    from kernel_inputs import random_model
    from usdeform.correction import correct_frames

    lam = np.linspace(0.0, 8.0, 40)
    preloaded = StiffnessProfile(0.1, 1.0, 3.0)  # the quadratic alone bottoms out at 0.5 N
    fit = fit_stiffness(preloaded.force_at(lam), lam)
    np.testing.assert_allclose(fit.profile.as_tuple(), preloaded.as_tuple(), atol=1e-9)
    np.testing.assert_allclose(preloaded.lambda_at([0.0, 1.0, 3.0]), [-3.0, -2.0, 0.0])
    np.testing.assert_allclose(preloaded.stiffness_at([-2.0, 0.0, 1.0]), [1.0, 1.0, 1.2])
    np.testing.assert_allclose(preloaded.force_at(preloaded.lambda_at([0.5, 2.0, 9.0])), [0.5, 2.0, 9.0])
    model = random_model(np.random.default_rng(0), 16, 16)
    frames = np.full((1, 16, 16), 100, np.uint8)
    assert correct_frames(frames, [10.0], fit.profile, model).shape == frames.shape


def test_a_force_gain_error_scales_the_stiffness_and_leaves_lambda_and_force_over_stiffness_unchanged():
    # why diagnosis.json's record_next calls a sensor's gain error ambiguous with tissue stiffness, and why it
    # leaves the correction unchanged: every force read (1 + g) times too high fits a (1 + g) times stiffer curve
    rng = np.random.default_rng(3)
    lam = np.sort(rng.uniform(0.0, 6.0, 40))
    force = 0.08 * lam**2 + 0.9 * lam + rng.normal(0.0, 0.05, lam.size)
    true_fit, read_fit = fit_stiffness(force, lam), fit_stiffness(1.15 * force, lam)
    np.testing.assert_allclose(read_fit.profile.stiffness_at(lam), 1.15 * true_fit.profile.stiffness_at(lam))
    forces = np.linspace(0.5, 8.0, 9)
    np.testing.assert_allclose(read_fit.profile.lambda_at(1.15 * forces), true_fit.profile.lambda_at(forces))
    np.testing.assert_allclose(
        1.15 * forces / read_fit.profile.stiffness_at(read_fit.profile.lambda_at(1.15 * forces)),
        forces / true_fit.profile.stiffness_at(true_fit.profile.lambda_at(forces)),
    )
