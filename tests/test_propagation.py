"""Stiffness propagation along a sweep (paper eqs. 12-14)."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from usdeform.correction import interpolate_profile, inverse_distance_weights, profiles_along_sweep
from usdeform.errors import InputError
from usdeform.regression import StiffnessProfile

coordinates = st.floats(-100, 100, allow_nan=False)


@settings(max_examples=100, deadline=None)
@given(
    position=st.tuples(coordinates, coordinates, coordinates),
    sampled=st.lists(st.tuples(coordinates, coordinates, coordinates), min_size=1, max_size=6, unique=True),
)
def test_weights_are_a_partition_of_unity(position, sampled) -> None:
    weights = inverse_distance_weights(np.array(position), np.array(sampled))
    assert weights.sum() == pytest.approx(1.0) and np.all(weights >= 0)


def test_weights_follow_eq_14() -> None:
    # Distances 5, 5 and 25 mm: raw weights 35/5, 35/5, 35/25 = 7, 7, 1.4, normalised by 15.4.
    np.testing.assert_allclose(inverse_distance_weights(5.0, [0.0, 10.0, 30.0]), [5 / 11, 5 / 11, 1 / 11])
    assert inverse_distance_weights(0.1, [0.0, 10.0, 30.0]).argmax() == 0


def test_exact_hit_takes_that_profile() -> None:
    profiles = [StiffnessProfile(0.1, 1.0), StiffnessProfile(0.2, 2.0), StiffnessProfile(0.3, 3.0)]
    assert interpolate_profile(10.0, [0.0, 10.0, 30.0], profiles) == profiles[1]
    np.testing.assert_array_equal(inverse_distance_weights(30.0, [0.0, 10.0, 30.0]), [0.0, 0.0, 1.0])


def test_mixed_profile_stiffness_is_the_weighted_stiffness() -> None:
    profiles = [StiffnessProfile(0.1, 1.0, 0.2), StiffnessProfile(0.3, 2.5, -0.1)]
    sampled = np.array([[0.0, 0.0, 0.0], [0.0, 40.0, 0.0]])
    position = np.array([0.0, 10.0, 0.0])
    mixed = interpolate_profile(position, sampled, profiles)
    weights = inverse_distance_weights(position, sampled)
    lam = np.linspace(0, 8, 9)
    np.testing.assert_allclose(mixed.stiffness_at(lam), weights @ [p.stiffness_at(lam) for p in profiles])
    table = profiles_along_sweep(np.array([[0.0, 0.0, 0.0], [0.0, 10.0, 0.0]]), sampled, profiles)
    np.testing.assert_allclose(table, [profiles[0].as_tuple(), mixed.as_tuple()])


def test_mismatched_inputs() -> None:
    with pytest.raises(InputError, match="one per sampled position"):
        interpolate_profile(1.0, [0.0, 2.0], [StiffnessProfile.UNIT])
    with pytest.raises(InputError, match="coordinates"):
        inverse_distance_weights(np.zeros(2), np.zeros((3, 3)))
