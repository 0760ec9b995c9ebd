"""Kernel output is bit-identical for any thread count and any batching of the frames."""

from __future__ import annotations

import itertools

import numpy as np
import pytest

import kernel_inputs
from kernel_inputs import (
    anchored_sweep_case,
    random_bspline_model,
    random_frames,
    random_model,
    random_profile,
    random_sweep_poses,
)
from usdeform import _core
from usdeform.correction import correct_frames
from usdeform.correction._vessel import correct_vessel_anchored
from usdeform.volume import Compounder, VoxelGrid

THREAD_COUNTS = (1, 2, 3, 8)
ROWS, COLS, N_FRAMES = 48, 40, 40


@pytest.fixture(scope="module")
def sweep():
    rng = np.random.default_rng(5)
    grid = VoxelGrid((30, 34, 38), np.diag([0.9, 1.1, 1.0, 1.0]))
    model = random_model(rng, ROWS, COLS)
    frames = random_frames(rng, N_FRAMES, ROWS, COLS, np.float32)
    poses = random_sweep_poses(rng, N_FRAMES, ROWS, COLS, grid)
    forces = rng.uniform(0, model.normalization.force_scale, N_FRAMES)
    return grid, model, frames, poses, forces, random_profile(rng)


@pytest.mark.parametrize("basis", ["quadratic", "bspline"])
def test_warp_is_identical_for_any_thread_count(sweep, basis: str) -> None:
    _, model, frames, _, forces, profile = sweep
    if basis == "bspline":
        quadratic, model = model, random_bspline_model(np.random.default_rng(6), ROWS, COLS)
        forces = forces * (model.normalization.force_scale / quadratic.normalization.force_scale)  # its fitted range
    results = [correct_frames(frames, forces, profile, model, threads=n) for n in THREAD_COUNTS]
    assert all(np.array_equal(results[0], r) for r in results[1:])


@pytest.mark.parametrize("interpolation", ["nearest", "linear"])
@pytest.mark.parametrize("compounding", ["mean", "max", "latest"])
def test_compounding_is_identical_for_any_thread_count_and_batching(
    sweep, interpolation: str, compounding: str
) -> None:
    grid, model, frames, poses, forces, profile = sweep
    volumes = []
    for threads, batch in zip(THREAD_COUNTS, (N_FRAMES, 7, 1, 16), strict=False):
        compounder = Compounder(grid, interpolation, compounding)
        for start in range(0, N_FRAMES, batch):
            part = slice(start, start + batch)
            compounder.add_corrected_frames(frames[part], poses[part], forces[part], profile, model, threads=threads)
        volumes.append(compounder.volume())
    assert volumes[0].weight.sum() > 0
    for volume in volumes[1:]:
        assert np.array_equal(volumes[0].image, volume.image)
        assert np.array_equal(volumes[0].weight, volume.weight)


def anchored_sweep(seed: int, lumenless: tuple[int, ...] = ()):
    """A vessel-anchored model and a sweep following its lumen, with no lumen in the frames ``lumenless``."""
    centres = np.column_stack([np.linspace(14, 26, N_FRAMES), 22 + 3 * np.sin(np.arange(N_FRAMES) / 5)])
    centres[list(lumenless)] = -1000.0  # drawn outside the frame
    grid = VoxelGrid((30, 34, 38), np.diag([0.9, 1.1, 1.0, 1.0]))
    model, frames, poses, forces, profile = anchored_sweep_case(
        np.random.default_rng(seed), ROWS, COLS, centres, 6.0, grid
    )
    return grid, model, frames, poses, forces, profile


def test_vessel_anchored_compounding_is_identical_for_any_thread_count() -> None:
    """The default path: the lumen search runs on a thread of its own beside the insertion, or takes
    turns with it on one thread; the lumens and the volume do not depend on it."""
    grid, model, frames, poses, forces, profile = anchored_sweep(9)
    volumes, lumens = [], []
    for threads in THREAD_COUNTS:
        compounder = Compounder(grid, "nearest", "mean")
        compounder.add_corrected_frames(frames, poses, forces, profile, model, threads=threads)
        volumes.append(compounder.volume())
        lumens.append(correct_vessel_anchored(frames, forces, profile, model, threads=threads)[2])
    assert volumes[0].weight.sum() > 0 and sum(lumen is not None for lumen in lumens[0]) > N_FRAMES // 2
    for volume, found in zip(volumes[1:], lumens[1:], strict=True):
        assert np.array_equal(volumes[0].image, volume.image)
        assert np.array_equal(volumes[0].weight, volume.weight)
        assert found == lumens[0]


@pytest.mark.parametrize("threads", [1, 2])
def test_vessel_anchored_compounding_is_identical_for_any_batching(threads: int) -> None:
    """A sweep added in batches gives the volume of one call: each batch's lumen search goes on from
    where the previous batch left it (frames 7 and 20, first of their batches, show no lumen)."""
    grid, model, frames, poses, forces, profile = anchored_sweep(9, lumenless=(7, 20))
    volumes = []
    for bounds in ((0, N_FRAMES), (0, 7, 20, N_FRAMES)):
        compounder = Compounder(grid, "nearest", "mean")
        for start, stop in itertools.pairwise(bounds):
            part = slice(start, stop)
            compounder.add_corrected_frames(frames[part], poses[part], forces[part], profile, model, threads=threads)
        volumes.append(compounder.volume())
    assert volumes[0].weight.sum() > 0
    assert np.array_equal(volumes[0].image, volumes[1].image)
    assert np.array_equal(volumes[0].weight, volumes[1].weight)


def test_affine_lucas_kanade_is_identical_for_any_thread_count() -> None:
    images, start, initial, _ = kernel_inputs.random_tracking_pair(np.random.default_rng(8), 70, 90, 300)
    results = [_core.affine_lucas_kanade(*images, start, initial, (21, 15), threads=n) for n in THREAD_COUNTS]
    assert results[0][1].sum() > 100
    for result in results[1:]:
        for got, expected in zip(result, results[0], strict=True):
            assert np.array_equal(got, expected)
