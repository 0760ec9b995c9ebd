"""The cubic B-spline spatial basis: its exact properties and input checks (its kernels are held to
their NumPy twins with the quadratic model's in test_kernels_equivalence.py)."""

from __future__ import annotations

import numpy as np
import pytest

from usdeform import _core
from usdeform.errors import InputError
from usdeform.regression import BSplineDisplacementModel, Normalization, StiffnessProfile, bspline_basis


@pytest.mark.parametrize("n_functions", [4, 5, 11])
def test_basis_is_a_partition_of_unity_also_beyond_the_unit_interval(n_functions: int) -> None:
    u = np.linspace(-0.3, 1.3, 97)
    basis = bspline_basis(u, n_functions)
    assert basis.shape == (n_functions, u.size)
    np.testing.assert_allclose(basis.sum(axis=0), 1.0, rtol=0, atol=1e-13)
    inside = (u >= 0) & (u <= 1)
    assert np.all(basis[:, inside] >= -1e-15)
    assert np.all(np.count_nonzero(np.abs(basis) > 1e-15, axis=0) <= 4)


def test_constant_coefficients_give_a_constant_field() -> None:
    rows, cols = 17, 23
    normalization = Normalization.for_frames(rows, cols, 10.0, 4.0, lateral_scale=3.0, axial_scale=-2.0)
    coefficients = np.zeros((2, 3, 6, 5))
    coefficients[0, 0] = 0.75  # lateral, force term 1
    coefficients[1, 2] = -1.5  # axial, force term h^2
    model = BSplineDisplacementModel(coefficients, normalization, n_intervals=8)
    profile = StiffnessProfile.constant(2.0)
    one, _, h2 = model.force_integrals(6.0, profile)
    lateral, axial = model.displacement(6.0, profile, (rows, cols))
    np.testing.assert_allclose(lateral, 3.0 * 0.75 * one, rtol=1e-13)
    np.testing.assert_allclose(axial, -2.0 * -1.5 * h2, rtol=1e-13)


@pytest.mark.parametrize("shape", [(2, 3, 3, 6), (2, 3, 6, 2), (2, 10, 4), (2, 3, 4), (3, 3, 4, 4)])
def test_bad_coefficient_shapes_are_rejected_by_the_model(shape: tuple[int, ...]) -> None:
    normalization = Normalization.for_frames(8, 8, 1.0, 1.0)
    with pytest.raises(InputError, match=r"^coefficients: expected shape \(2, 3, n_y, n_x\)"):
        BSplineDisplacementModel(np.zeros(shape), normalization)


@pytest.mark.parametrize("shape", [(2, 3, 3, 6), (2, 4, 5, 6), (2, 11), (2, 3, 4, 4, 1)])
def test_bad_coefficient_shapes_are_rejected_by_the_compiled_model(shape: tuple[int, ...]) -> None:
    normalization = Normalization.for_frames(8, 8, 1.0, 1.0).as_array()
    with pytest.raises(InputError, match=r"^coefficients: expected shape .*\(2, 3, n_y, n_x\)"):
        _core.Model(
            "bspline",
            np.zeros(shape),
            normalization,
            n_intervals=4,
            coupling="stiffness",
            integration="force",
            frame_shape=(8, 8),
        )
