"""A sensor drift that the recordings cannot tell from a stiffer tissue is reported as unidentified and held at zero,
decided from the force design's own information, not from the kind of recording."""

from types import SimpleNamespace

import numpy as np
import pytest

from usdeform.gap.folds import LINEAR_IDENTIFIED_BY, linear_parameters, unidentified_linear
from usdeform.gap.linear_fits import MAX_DRIFT_N_PER_S

RAMP_N_PER_S = 5.0


def _fold(force_n: np.ndarray, time_s: np.ndarray, drift: float, bias: float, seed: int, recordings: int = 2):
    """A fold of force-controlled palpations of a tissue whose law (exponential) no cubic takes up exactly, read by a
    sensor with ``bias`` (N) and ``drift`` (N/s), 0.05 N of noise."""
    lam_grid = np.linspace(0.0, 20.0, 2001)
    law = 1.5 * (np.exp(0.15 * lam_grid) - 1)
    rng = np.random.default_rng(seed)
    cases = []
    for _ in range(recordings):
        observation = SimpleNamespace(
            force_n=force_n + bias + drift * time_s + 0.05 * rng.standard_normal(len(time_s)),
            time_s=time_s,
            probe_displacement_mm=np.interp(force_n, law, lam_grid),
        )
        section = SimpleNamespace(fields={}, contact_reaction_n=lambda weights: 0.0)
        cases.append(SimpleNamespace(observation=observation, section=section, fit=np.arange(len(time_s)) % 2 == 0))
    return SimpleNamespace(cases=cases)


def _ramp_only(drift: float, seed: int = 1):
    time_s = np.linspace(0.0, 3.0, 80)
    return _fold(0.3 + RAMP_N_PER_S * time_s, time_s, drift, 2.0, seed, recordings=4)


def _up_hold_down(drift: float, seed: int = 2):
    time_s = np.linspace(0.0, 8.0, 160)
    force = np.where(time_s > 5.0, 15.3 - RAMP_N_PER_S * (time_s - 5.0), 0.3 + RAMP_N_PER_S * time_s)
    return _fold(np.clip(force, 0.3, 15.3), time_s, drift, 2.0, seed)


@pytest.mark.parametrize("drift", [0.0, 0.1])
def test_a_drift_on_ramp_only_palpations_is_unidentified_and_the_offset_is_fitted_without_it(drift):
    fold = _ramp_only(drift)
    free, errors = linear_parameters(fold, {"force_sensor_error": {}})
    # time is a function of the indentation on a steady force ramp: the free drift goes to its bound, its error is
    # several times its whole range
    assert errors["drift_n_per_s"] > 2 * MAX_DRIFT_N_PER_S
    assert abs(free["drift_n_per_s"]) == pytest.approx(MAX_DRIFT_N_PER_S)
    assert unidentified_linear([errors]) == ["drift_n_per_s"]
    assert LINEAR_IDENTIFIED_BY["drift_n_per_s"] in ("hold", "ramp_speed")
    held, held_errors = linear_parameters(fold, {"force_sensor_error": {"drift_n_per_s": 0.0}})
    assert set(held) == {"offset_n"}
    assert held["offset_n"] == pytest.approx(2.0, abs=0.2)
    assert held_errors["offset_n"] < 0.1


@pytest.mark.parametrize("drift", [0.0, 0.1])
def test_a_drift_with_a_hold_and_unloading_is_identified_and_fitted(drift):
    values, errors = linear_parameters(_up_hold_down(drift), {"force_sensor_error": {}})
    assert unidentified_linear([errors]) == []
    assert values["drift_n_per_s"] == pytest.approx(drift, abs=0.02)
    assert values["offset_n"] == pytest.approx(2.0, abs=0.3)


def test_an_exactly_collinear_drift_is_not_hidden_by_a_pseudo_inverse():
    # an elastic law inside the cubic basis: time is exactly a cubic in lambda plus a constant
    fold = _ramp_only(0.0)
    lam = np.linspace(0.0, 10.0, 80)
    noise = 0.05 * np.random.default_rng(3).standard_normal(len(lam))
    for case in fold.cases:
        force = 0.8 * lam + 0.02 * lam**3
        case.observation = SimpleNamespace(
            force_n=force + 2.0 + noise, time_s=force / RAMP_N_PER_S, probe_displacement_mm=lam
        )
    _, errors = linear_parameters(fold, {"force_sensor_error": {}})
    assert errors["drift_n_per_s"] > 100 * MAX_DRIFT_N_PER_S


def test_a_drift_held_at_a_known_weight_value_leaves_the_offset_of_ramp_only_palpations_as_it_is():
    """Ramp-only palpations read by a sensor drifting 0.1 N/s: the elastic law takes up the drift (time follows the
    indentation), so the offset comes out the same held at zero or at the known 0.1 N/s. What a known drift changes
    is the drift that compensation undoes over a sweep, which lasts minutes."""
    fold = _ramp_only(0.1)
    at_zero, _ = linear_parameters(fold, {"force_sensor_error": {"drift_n_per_s": 0.0}})
    known, _ = linear_parameters(fold, {"force_sensor_error": {"drift_n_per_s": 0.1}})
    assert set(known) == {"offset_n"} and known["offset_n"] == pytest.approx(2.0, abs=0.15)
    assert known["offset_n"] == pytest.approx(at_zero["offset_n"], abs=0.02)


def test_the_drift_known_weights_identify_is_their_inverse_variance_mean():
    from usdeform.gap.sensor_calibration import known_sensor

    def weight(drift, error, offset=0.5):
        return {
            "offset_n": offset,
            "offset_uncertainty_n": 0.01,
            "drift_n_per_s": drift,
            "drift_uncertainty_n_per_s": error,
        }

    found = known_sensor([weight(0.02, 0.001), weight(0.05, 0.002), weight(None, None)])
    assert found.finding == "error"
    assert found.drift_n_per_s == pytest.approx((0.026, (1 / (1e6 + 2.5e5)) ** 0.5))
    assert known_sensor([weight(None, None, offset=0.0)]).drift_n_per_s is None
    assert known_sensor([]) == known_sensor([]).__class__(None, None)
