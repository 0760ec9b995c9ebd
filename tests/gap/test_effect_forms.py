"""The library's new effect forms on stand-in observations (no FEM): a late force stream reads the force of an
earlier indentation, and out-of-plane drift decorrelates frames apart in time at the same indentation."""

from types import SimpleNamespace

import numpy as np
import pytest

from usdeform.gap.benchmark import EFFECT_RANGES, draw_effect
from usdeform.gap.benchmark_scoring import fitted_magnitude
from usdeform.gap.detectability import LARGEST_REALISTIC, protocol_text
from usdeform.gap.linear_fits import force_columns
from usdeform.gap.models import EFFECT_BY_ID, EFFECTS, _correlation_factor, contact_reaction
from usdeform.sim import ImageLatency


def _ramp(rate_mm_s=2.0, hold_s=2.0, depth_mm=6.0, n=200):
    """Load at ``rate_mm_s``, hold, unload: time (s) and lambda (mm)."""
    ramp_s = depth_mm / rate_mm_s
    time = np.linspace(0.0, 2 * ramp_s + hold_s, n)
    lam = np.clip(np.minimum(time, 2 * ramp_s + hold_s - time) * rate_mm_s, 0.0, depth_mm)
    return time, lam


def test_a_force_latency_evaluates_the_force_at_an_earlier_indentation():
    time, lam = _ramp()
    observation = SimpleNamespace(time_s=time, probe_displacement_mm=lam)
    on_time = force_columns(observation, {})
    late = force_columns(observation, {"force_latency": {"delay_s": 0.15}})
    loading = (time > 0.5) & (time < 2.5)
    np.testing.assert_allclose(late[loading, 0], lam[loading] - 2.0 * 0.15, atol=1e-9)
    holding = (time > 3.5) & (time < 4.5)
    np.testing.assert_allclose(late[holding], on_time[holding])  # no residual at a constant indentation
    # the force reads contact later too (a lumen's push at contact steps later)
    section = SimpleNamespace(contact_reaction_n=lambda weights: 0.5)
    first_contact = np.argmax(contact_reaction(observation, section, {"force_latency": {"delay_s": 0.15}}) > 0)
    assert time[first_contact] == pytest.approx(0.15, abs=2 * (time[1] - time[0]))


def test_out_of_plane_drift_decorrelates_pairs_apart_in_time_at_the_same_indentation():
    time = np.arange(6) * 1.0
    partner = np.array([[-1, 0, 1, 2, 3, 0]])  # the last frame with the first, 5 s apart
    observation = SimpleNamespace(time_s=time, correlation_partner=partner)
    steps = np.zeros((1, 6))  # every pair at the same indentation (a hold)
    motion = {"shift_mm_per_mm": 0.3, "jitter_mm": 0.0}
    still = _correlation_factor(observation, steps, {"out_of_plane_motion": motion})
    drifting = _correlation_factor(observation, steps, {"out_of_plane_motion": motion | {"drift_mm_per_s": 0.2}})
    np.testing.assert_allclose(still[0, 1:], 1.0)
    sigma = 1.5 / 2.355
    np.testing.assert_allclose(drifting[0, 1:4], np.exp(-(0.2**2) / (2 * sigma**2)))
    assert drifting[0, 5] == pytest.approx(np.exp(-(1.0**2) / (2 * sigma**2)))


def test_every_library_effect_has_a_realistic_top_a_protocol_and_a_benchmark_draw():
    time, lam = _ramp()
    case = SimpleNamespace(observation=SimpleNamespace(time_s=time, probe_displacement_mm=lam))
    for model in EFFECTS:
        assert set(LARGEST_REALISTIC[model.effect]) == set(model.parameters) or model.effect == "force_sensor_error"
        assert protocol_text(model.effect, [case])
        assert model.effect in EFFECT_RANGES
    effect, parameters, magnitude = draw_effect("force_latency", np.random.default_rng(0), 20.0, 10.0)
    assert isinstance(effect, ImageLatency) and effect.image_delay_s == 0 and effect.force_delay_s == magnitude
    assert fitted_magnitude("force_latency", {"delay_s": -parameters["delay_s"]}, 10.0) == magnitude
    assert EFFECT_BY_ID["out_of_plane_motion"].parameters[-1] == "drift_mm_per_s"
