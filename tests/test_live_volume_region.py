"""The compounded volume in a voxel box (``Compounder.volume_region`` over ``_core.Accumulator.volume_region``,
which the live service sends) against its NumPy twin (``usdeform.reference.volume_region``) on random inputs, and
against the box of the whole volume."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from kernel_inputs import random_frames, random_sweep_poses
from usdeform import reference
from usdeform.errors import InputError
from usdeform.volume import Compounder, VoxelGrid

SETTINGS = settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.too_slow])


def _random_box(rng: np.random.Generator, shape: tuple[int, ...]) -> tuple[tuple[int, ...], tuple[int, ...]]:
    lo = tuple(int(rng.integers(0, n)) for n in shape)
    hi = tuple(int(rng.integers(low + 1, n + 1)) for low, n in zip(lo, shape, strict=True))
    return lo, hi


@SETTINGS
@given(
    seed=st.integers(0, 2**32 - 1),
    n_frames=st.integers(1, 12),
    rows=st.integers(1, 24),
    cols=st.integers(1, 24),
    dtype=st.sampled_from([np.uint8, np.float32]),
    interpolation=st.sampled_from(["nearest", "linear"]),
    compounding=st.sampled_from(["mean", "max", "latest"]),
    masked=st.booleans(),
)
def test_volume_region_matches_reference(
    seed: int,
    n_frames: int,
    rows: int,
    cols: int,
    dtype: type,
    interpolation: str,
    compounding: str,
    masked: bool,
) -> None:
    rng = np.random.default_rng(seed)
    grid = VoxelGrid(tuple(int(n) for n in rng.integers(2, 24, 3)), np.diag([*rng.uniform(0.5, 2.0, 3), 1.0]))
    frames = random_frames(rng, n_frames, rows, cols, dtype)
    poses = random_sweep_poses(rng, n_frames, rows, cols, grid)
    valid = rng.random(frames.shape) < 0.7 if masked else None
    compounder = Compounder(grid, interpolation, compounding)  # type: ignore[arg-type]
    compounder.add_frames(frames, poses, valid=valid)
    whole = compounder.volume()
    assert whole.weight is not None
    for _ in range(3):
        lo, hi = _random_box(rng, grid.shape)
        region = compounder.volume_region(lo, hi)  # type: ignore[arg-type]
        image, weight = region.image, region.weight
        assert weight is not None
        # the box's grid: its voxel (0, 0, 0) is the whole grid's voxel lo, same spacing and axes
        np.testing.assert_allclose(
            region.grid.index_to_world @ [0, 0, 0, 1], grid.index_to_world @ [lo[2], lo[1], lo[0], 1]
        )
        np.testing.assert_array_equal(region.grid.index_to_world[:3, :3], grid.index_to_world[:3, :3])
        box = tuple(slice(low, high) for low, high in zip(lo, hi, strict=True))
        assert image.shape == weight.shape == tuple(high - low for low, high in zip(lo, hi, strict=True))
        assert image.dtype == weight.dtype == np.float32
        # The box of the whole volume, bit for bit.
        assert np.array_equal(image, whole.image[box]) and np.array_equal(weight, whole.weight[box])
        expected_image, expected_weight = reference.volume_region(
            frames,
            poses,
            grid,
            lo,  # type: ignore[arg-type]
            hi,  # type: ignore[arg-type]
            interpolation,
            compounding,
            valid=valid,
        )
        np.testing.assert_allclose(weight, expected_weight, rtol=1e-5, atol=1e-5)
        covered = expected_weight > 1e-4  # voxels reached only by vanishing trilinear weights are ill-conditioned
        np.testing.assert_allclose(image[covered], expected_image[covered], rtol=1e-4, atol=1e-3)
        assert np.all(image[expected_weight == 0] == 0)


@pytest.mark.parametrize(
    ("lo", "hi", "message"),
    [
        ((-1, 0, 0), (5, 4, 6), "lo: the z bound -1 is outside the grid's voxels 0..5 along z"),
        ((0, 4, 0), (5, 4, 6), "lo: the y bound 4 is outside the grid's voxels 0..4 along y"),
        ((0, 0, 0), (5, 4, 7), "hi: the x bound 7 must be above lo's 0 and at most the grid's 6 voxels along x"),
        ((2, 0, 0), (2, 4, 6), "hi: the z bound 2 must be above lo's 2 and at most the grid's 5 voxels along z"),
    ],
)
def test_a_bad_box_is_a_value_error_naming_the_bound(lo, hi, message) -> None:
    grid = VoxelGrid((5, 4, 6), np.eye(4))
    compounder = Compounder(grid)
    frames = np.zeros((1, 2, 2), np.uint8)
    for call in (
        lambda: compounder.volume_region(lo, hi),
        lambda: reference.volume_region(frames, np.eye(4)[np.newaxis], grid, lo, hi),
    ):
        with pytest.raises(InputError) as raised:
            call()
        assert isinstance(raised.value, ValueError) and str(raised.value) == message
