"""Palpations measured in threads: the same measurements at any thread count, errors named in order."""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping

import numpy as np
import pytest

from usdeform.errors import InputError
from usdeform.fitting import measure_positions
from usdeform.sim import coarse_phantom, simulate_palpation


@pytest.fixture(scope="module")
def palpations():
    phantom = coarse_phantom()
    recordings = [
        simulate_palpation(phantom, position, 12.0, n_frames=16, seed=number, rows=96, cols=96)[0]
        for number, position in enumerate((10.0, 40.0))
    ]
    return recordings, phantom.base_section.depth_mm


def assert_same(one: object, two: object) -> None:
    """``one`` and ``two`` hold equal values (arrays bit for bit), field by field."""
    assert type(one) is type(two)
    if dataclasses.is_dataclass(one):
        for field in dataclasses.fields(one):
            assert_same(getattr(one, field.name), getattr(two, field.name))
    elif isinstance(one, np.ndarray):
        np.testing.assert_array_equal(one, two)
    elif isinstance(one, Mapping):
        assert list(one) == list(two)
        for key in one:
            assert_same(one[key], two[key])
    elif isinstance(one, (list, tuple)):
        assert len(one) == len(two)
        for first, second in zip(one, two, strict=True):
            assert_same(first, second)
    else:
        assert one == two


def test_palpations_measured_in_threads_equal_those_measured_one_by_one(palpations) -> None:
    recordings, layer_mm = palpations
    one, sampled_one = measure_positions(recordings, layer_mm, threads=1)
    two, sampled_two = measure_positions(recordings, layer_mm, threads=2)
    assert len(one) == 2 and one[0].tracked.valid.any()
    for first, second in zip(one, two, strict=True):
        assert_same(dataclasses.replace(first, seconds=0.0), dataclasses.replace(second, seconds=0.0))
    np.testing.assert_array_equal(sampled_one.positions_mm, sampled_two.positions_mm)


def test_a_palpation_without_poses_is_named_before_any_is_tracked(palpations) -> None:
    recordings, layer_mm = palpations
    posed = recordings[1]
    without = dataclasses.replace(posed, pose_valid=np.zeros_like(posed.pose_valid))
    with pytest.raises(InputError, match="second: no frame has a valid probe pose"):
        measure_positions([recordings[0], without], layer_mm, names=["first", "second"], threads=2)


def test_threads_out_of_range_are_refused(palpations) -> None:
    recordings, layer_mm = palpations
    with pytest.raises(InputError, match="threads: expected 1 to"):
        measure_positions(recordings, layer_mm, threads=0)
