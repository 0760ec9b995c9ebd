"""The Rust kernels against their NumPy twins (usdeform.reference) on random inputs."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
import scipy.sparse
from hypothesis import HealthCheck, example, given, settings
from hypothesis import strategies as st

from kernel_inputs import (
    random_bspline_model,
    random_frames,
    random_model,
    random_profile,
    random_sweep_poses,
    random_tracking_pair,
)
from usdeform import _core, reference
from usdeform.correction import correct_frames
from usdeform.regression import Normalization, QuadraticDisplacementModel, StiffnessProfile, profiles_array
from usdeform.volume import Compounder, VoxelGrid, compound_frames

SETTINGS = settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.too_slow])
seeds = st.integers(0, 2**32 - 1)
sizes = st.integers(1, 40)
#: Random models of both spatial bases: the paper's quadratic and the cubic B-spline.
models = st.sampled_from([random_model, random_bspline_model])


@SETTINGS
@given(seed=seeds, rows=sizes, cols=sizes, h_mm=st.floats(-20, 20), make_model=models)
def test_regression_rate_matches_reference(seed: int, rows: int, cols: int, h_mm: float, make_model) -> None:
    model = make_model(np.random.default_rng(seed), rows, cols)
    expected = reference.regression_rate(model, h_mm, (rows, cols))
    np.testing.assert_allclose(model.rate(h_mm, (rows, cols)), expected, rtol=1e-12, atol=1e-9)


@SETTINGS
@given(
    seed=seeds,
    force=st.floats(-0.2, 40),
    n_intervals=st.integers(1, 300),
    integration=st.sampled_from(["force", "displacement"]),
)
def test_force_integrals_match_reference(seed: int, force: float, n_intervals: int, integration: str) -> None:
    rng = np.random.default_rng(seed)
    model = replace(random_model(rng, 16, 16, n_intervals), integration=integration)
    profile = random_profile(rng)
    expected = reference.force_integrals(force, profile, model.normalization, integration)
    np.testing.assert_allclose(model.force_integrals(force, profile), expected, rtol=1e-11, atol=1e-14)


@SETTINGS
@given(
    c1=st.one_of(st.just(0.0), st.floats(1e-12, 1e-6), st.floats(-0.05, 30)),
    c2=st.floats(0.02, 5),
    c3=st.floats(-2, 5),
    force=st.floats(-1, 60),
    power=st.integers(0, 2),
    extra=st.integers(0, 1),
)
@example(c1=5e-324, c2=1.0, c3=0.5, force=30.0, power=2, extra=1)  # subnormal: the twin's 1 / c1 overflowed
def test_closed_form_stiffness_integrals_match_quadrature(
    c1: float, c2: float, c3: float, force: float, power: int, extra: int
) -> None:
    """Every branch of the closed form (linear continuation, series for nearly linear profiles,
    exact for strongly stiffening ones) against Gauss-Legendre quadrature."""
    profile = StiffnessProfile(c1, c2, c3)
    top = max(force, 0.0)
    if top > c3 and c2**2 + 4 * c1 * (top - c3) <= 0.05 * c2**2:
        return  # beyond (or at) the peak of a softening profile: refused by both
    normalization = Normalization(1.0, 1.0, 1.0, 1.0, 1.0, 1.0)
    model = QuadraticDisplacementModel(np.zeros((2, 10)), normalization, frame_shape=(2, 2))
    integration = "displacement" if extra else "force"
    expected = reference.force_integrals(force, profile, normalization, integration)[power]
    got = replace(model, integration=integration).force_integrals(force, profile)[power]
    assert got == pytest.approx(expected, rel=1e-10, abs=1e-13)


@SETTINGS
@given(
    seed=seeds,
    rows=sizes,
    cols=sizes,
    force=st.floats(0, 40),
    make_model=models,
    integration=st.sampled_from(["force", "displacement"]),
    coupling=st.sampled_from(["stiffness", "force"]),
)
def test_integrated_displacement_matches_reference(
    seed: int, rows: int, cols: int, force: float, make_model, integration: str, coupling: str
) -> None:
    rng = np.random.default_rng(seed)
    model = replace(make_model(rng, rows, cols), integration=integration, coupling=coupling)
    profile = random_profile(rng)
    expected = reference.integrated_displacement(model, force, profile, (rows, cols))
    np.testing.assert_allclose(model.displacement(force, profile, (rows, cols)), expected, rtol=1e-10, atol=1e-9)


def test_integral_of_constant_stiffness_equals_closed_form() -> None:
    """With k constant, D(F) = A F_n + B int h_n dF_n + C int h_n^2 dF_n has a closed form."""
    rng = np.random.default_rng(7)
    model = random_model(rng, 20, 30, n_intervals=5)
    k, force = 2.5, 12.0
    n = model.normalization
    terms = (
        force / n.force_scale,
        force**2 / (2 * k) / (n.h_scale * n.force_scale),
        force**3 / (3 * k**2) / (n.h_scale**2 * n.force_scale),
    )
    np.testing.assert_allclose(model.force_integrals(force, StiffnessProfile.constant(k)), terms, rtol=1e-12)


def assert_warped_alike(got: np.ndarray, expected: np.ndarray) -> None:
    """A kernel's warp against its twin's: uint8 within one level at a few pixels (both round to nearest;
    a sum within 1 ulp of .5 may round either way), float32 to single precision."""
    if got.dtype == np.uint8:
        assert np.abs(got.astype(int) - expected.astype(int)).max(initial=0) <= 1
        assert np.count_nonzero(got != expected) <= max(2, 1e-3 * got.size)
    else:
        np.testing.assert_allclose(got, expected, rtol=1e-5, atol=1e-3)


@SETTINGS
@given(
    seed=seeds,
    n_frames=st.integers(1, 4),
    rows=sizes,
    cols=sizes,
    dtype=st.sampled_from([np.uint8, np.float32]),
    fill=st.floats(0, 255),
    integration=st.sampled_from(["force", "displacement"]),
    coupling=st.sampled_from(["stiffness", "force"]),
    make_model=models,
)
def test_warp_matches_reference(
    seed: int,
    n_frames: int,
    rows: int,
    cols: int,
    dtype: type,
    fill: float,
    integration: str,
    coupling: str,
    make_model,
) -> None:
    rng = np.random.default_rng(seed)
    model = replace(make_model(rng, rows, cols), integration=integration, coupling=coupling)
    frames = random_frames(rng, n_frames, rows, cols, dtype)
    forces = rng.uniform(0, model.normalization.force_scale * 1.2, n_frames)
    profiles = profiles_array([random_profile(rng) for _ in range(n_frames)], n_frames)
    got, valid = correct_frames(frames, forces, profiles, model, fill=fill, return_mask=True)
    expected, expected_valid = reference.warp_frames(frames, forces, profiles, model, fill=fill, return_mask=True)
    assert got.dtype == frames.dtype and got.shape == frames.shape
    assert valid.dtype == bool and valid.shape == frames.shape
    # Only a source exactly on the frame's border could be judged differently by the two.
    assert np.count_nonzero(valid != expected_valid) <= max(1, 1e-3 * valid.size)
    assert np.array_equal(correct_frames(frames, forces, profiles, model, fill=fill), got)
    assert_warped_alike(got, expected)


@SETTINGS
@given(
    seed=seeds,
    n_frames=st.integers(1, 3),
    rows=sizes,
    cols=sizes,
    dtype=st.sampled_from([np.uint8, np.float32]),
    fill=st.floats(0, 255),
    scale_px=st.floats(0, 30),
)
def test_field_warp_matches_reference(
    seed: int, n_frames: int, rows: int, cols: int, dtype: type, fill: float, scale_px: float
) -> None:
    rng = np.random.default_rng(seed)
    frames = random_frames(rng, n_frames, rows, cols, dtype)
    fields = rng.normal(0.0, scale_px, (n_frames, 2, rows, cols))
    fields[rng.random(fields.shape) < 0.01] = np.nan  # a NaN source is outside: fill, not valid
    got, valid = _core.warp_by_field(frames, fields, fill=fill)
    assert got.dtype == frames.dtype and got.shape == frames.shape and valid.shape == frames.shape
    one, one_valid = _core.warp_by_field(frames, fields, fill=fill, threads=1)
    assert np.array_equal(one, got) and np.array_equal(one_valid, valid)  # the same for any thread count
    for index in range(n_frames):
        expected, expected_valid = reference.warp_frame(frames[index], fields[index], fill)
        assert np.array_equal(valid[index], expected_valid)
        assert_warped_alike(got[index], expected)


def test_warp_against_opencv_remap_inside_the_frame() -> None:
    """Away from the borders our bilinear warp is OpenCV's remap with the same map."""
    import cv2

    rng = np.random.default_rng(3)
    rows, cols = 64, 80
    model = random_model(rng, rows, cols)
    profile = random_profile(rng)
    frame = random_frames(rng, 1, rows, cols, np.float32)[0]
    force = 0.5 * model.normalization.force_scale
    lateral, axial = model.displacement(force, profile, (rows, cols))
    y, x = np.mgrid[0:rows, 0:cols].astype(np.float32)
    map_x, map_y = x + lateral.astype(np.float32), y + axial.astype(np.float32)
    expected = cv2.remap(frame, map_x, map_y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=0)
    got = correct_frames(frame, force, profile, model)
    inside = (map_x >= 1) & (map_y >= 1) & (map_x <= cols - 2) & (map_y <= rows - 2)
    assert inside.mean() > 0.3
    # OpenCV quantises the interpolation weights to 1/32 of a pixel.
    np.testing.assert_allclose(got[inside], expected[inside], atol=0.05 * np.abs(frame).max())


@SETTINGS
@given(
    seed=seeds,
    n_frames=st.integers(1, 20),
    rows=st.integers(1, 24),
    cols=st.integers(1, 24),
    dtype=st.sampled_from([np.uint8, np.float32]),
    interpolation=st.sampled_from(["nearest", "linear"]),
    compounding=st.sampled_from(["mean", "max", "latest"]),
    masked=st.booleans(),
)
def test_compounding_matches_reference(
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
    grid = VoxelGrid(tuple(rng.integers(2, 24, 3)), np.diag([*rng.uniform(0.5, 2.0, 3), 1.0]))
    frames = random_frames(rng, n_frames, rows, cols, dtype)
    poses = random_sweep_poses(rng, n_frames, rows, cols, grid)
    valid = rng.random(frames.shape) < 0.7 if masked else None
    volume = compound_frames(frames, poses, grid, interpolation, compounding, valid=valid)
    image, weight = reference.compound_frames(frames, poses, grid, interpolation, compounding, valid=valid)
    np.testing.assert_allclose(volume.weight, weight, rtol=1e-5, atol=1e-5)
    covered = weight > 1e-4  # voxels reached only by vanishing trilinear weights are ill-conditioned
    np.testing.assert_allclose(volume.image[covered], image[covered], rtol=1e-4, atol=1e-3)
    assert np.all(volume.image[weight == 0] == 0)


@pytest.mark.parametrize("dtype", [np.uint8, np.float32])
@pytest.mark.parametrize("interpolation", ["nearest", "linear"])
@pytest.mark.parametrize("make_model", [random_model, random_bspline_model])
def test_fused_correction_and_compounding_equals_the_two_steps(dtype: type, interpolation: str, make_model) -> None:
    rng = np.random.default_rng(11)
    rows, cols, n_frames = 30, 40, 37  # more than one internal batch of frames
    grid = VoxelGrid((20, 22, 24), np.diag([1.5, 1.5, 1.5, 1.0]))
    model = make_model(rng, rows, cols)
    frames = random_frames(rng, n_frames, rows, cols, dtype)
    poses = random_sweep_poses(rng, n_frames, rows, cols, grid)
    forces = rng.uniform(0, model.normalization.force_scale, n_frames)
    profile = random_profile(rng)
    corrected, valid = correct_frames(frames, forces, profile, model, fill=7, return_mask=True)
    assert 0 < valid.mean() < 1  # the edges are sampled from outside the frames
    for exclude_invalid, mask in [(True, valid), (False, None)]:
        fused = Compounder(grid, interpolation, "mean")
        fused.add_corrected_frames(frames, poses, forces, profile, model, fill=7, exclude_invalid=exclude_invalid)
        two_steps = compound_frames(corrected, poses, grid, interpolation, "mean", valid=mask)
        assert np.array_equal(fused.volume().image, two_steps.image)
        assert np.array_equal(fused.volume().weight, two_steps.weight)


def test_invalid_pixels_are_left_out_of_image_and_coverage() -> None:
    """A frame shifted half out of itself: the fill never reaches the volume, nor the coverage."""
    rows, cols = 20, 30
    coefficients = np.zeros((2, 10))
    coefficients[0, 9] = 14.5  # constant lateral shift, pixels at unit force
    normalization = Normalization.for_frames(rows, cols, max_force_n=1.0, max_h_mm=1.0)
    shift = QuadraticDisplacementModel(coefficients, normalization, frame_shape=(rows, cols))
    frames = np.full((1, rows, cols), 100, dtype=np.uint8)
    pose = np.eye(4)[np.newaxis]
    grid = VoxelGrid((1, rows, cols), np.eye(4))
    force = 1.0
    _, valid = correct_frames(frames, force, StiffnessProfile.UNIT, shift, fill=0, return_mask=True)
    assert 0.3 < valid.mean() < 0.7
    compounder = Compounder(grid)
    compounder.add_corrected_frames(frames, pose, force, StiffnessProfile.UNIT, shift, fill=0)
    volume = compounder.volume()
    assert np.array_equal(volume.weight[0] > 0, valid[0])
    assert np.all(volume.image[0][valid[0]] == 100)


@SETTINGS
@given(seed=seeds, n=st.integers(1, 60), density=st.floats(0.0, 0.3), definite=st.booleans())
def test_symmetric_solver_matches_reference(seed: int, n: int, density: float, definite: bool) -> None:
    """Random symmetric sparse matrices, positive definite or indefinite (a negative diagonal block),
    with both triangles stored as the FEM stores them and diagonals dominant enough to be regular."""
    rng = np.random.default_rng(seed)
    off_diagonal = scipy.sparse.random(n, n, density, random_state=rng, data_rvs=lambda k: rng.uniform(-1, 1, k))
    symmetric = off_diagonal + off_diagonal.T
    magnitude = np.asarray(abs(symmetric).sum(axis=1)).ravel() + rng.uniform(0.5, 2.0, n)
    signs = np.where(rng.random(n) < 0.3, -1.0, 1.0) if not definite else np.ones(n)
    matrix = (symmetric + scipy.sparse.diags(signs * magnitude)).tocsc()
    matrix.sort_indices()
    rhs = rng.normal(size=n)
    indptr, indices = matrix.indptr.astype(np.int64), matrix.indices.astype(np.int64)
    solver, twin = _core.SymmetricSolver(indptr, indices), reference.SymmetricSolver(indptr, indices)
    solved = solver.solve(matrix.data, rhs)
    np.testing.assert_allclose(solved, twin.solve(matrix.data, rhs), rtol=1e-9, atol=1e-12)
    # a kept factor solves any right-hand side as a solve of its own does, bit for bit
    factor, twin_factor = solver.factorize(matrix.data), twin.factorize(matrix.data)
    for other in (rhs, rng.normal(size=n)):
        np.testing.assert_array_equal(factor.solve(other), solver.solve(matrix.data, other))
        np.testing.assert_allclose(factor.solve(other), twin_factor.solve(other), rtol=1e-9, atol=1e-12)


@SETTINGS
@given(
    seed=seeds,
    n_elements=st.integers(1, 40),
    n_points=st.integers(1, 7),
    strain=st.floats(0.0, 0.3),
    with_tangent=st.booleans(),
    free_share=st.floats(0.0, 1.0),
)
def test_hyperelastic_section_matches_reference(
    seed: int, n_elements: int, n_points: int, strain: float, with_tangent: bool, free_share: float
) -> None:
    """Random elements (shared DOFs, random gradients and weights, Yeoh materials with either sign of c2, some with
    lumen pressure) at a random displacement of up to ``strain``, a random share of the element-matrix entries in the
    free-free block, slots shared between elements: forces and tangent entries agree within 1e-10 relative and the
    smallest det F within 1e-12 (forces near zero within 1e-12 of their stress scale); an inverted element is
    reported by both."""
    rng = np.random.default_rng(seed)
    n_dofs = 12 + 2 * n_elements
    element_dofs = np.stack([rng.choice(n_dofs, 12, replace=False) for _ in range(n_elements)]).astype(np.int64)
    gradients = rng.normal(scale=0.5, size=(n_elements, n_points, 6, 2))
    weights = rng.uniform(0.1, 2.0, size=(n_elements, n_points))
    shear = rng.uniform(0.005, 0.05, n_elements)
    materials = (
        shear,
        rng.uniform(-0.3, 3.0, n_elements),
        rng.uniform(0.0, 5.0, n_elements),
        shear * rng.uniform(5.0, 50.0, n_elements),
        np.where(rng.random(n_elements) < 0.3, rng.uniform(0.0, 0.003, n_elements), 0.0),
    )
    n_entries = 50
    slots = rng.integers(0, n_entries, (n_elements, 144))
    entry_slots = np.where(rng.random((n_elements, 144)) < free_share, slots, -1)
    u = rng.normal(scale=strain / 3, size=n_dofs)
    arguments = (n_dofs, element_dofs, gradients, weights, *materials, entry_slots.astype(np.int64), n_entries)
    force, tangent, det = _core.HyperelasticSection(*arguments).assemble(u, 0.7, with_tangent)
    expected_force, expected_tangent, expected_det = reference.HyperelasticSection(*arguments).assemble(
        u, 0.7, with_tangent
    )
    if expected_det <= 0:
        assert det <= 0
        return
    assert det == pytest.approx(expected_det, abs=1e-12)
    stress_scale = materials[3].max() * np.abs(gradients).max() * weights.max()  # N/mm: the forces' rounding scale
    np.testing.assert_allclose(force, expected_force, rtol=1e-10, atol=1e-12 * stress_scale)
    if with_tangent:
        assert tangent is not None and expected_tangent is not None
        scale = np.abs(expected_tangent).max() + 1e-30
        np.testing.assert_allclose(tangent, expected_tangent, rtol=1e-10, atol=1e-10 * scale)
    else:
        assert tangent is None


@SETTINGS
@given(
    seed=seeds,
    rows=st.integers(24, 72),
    cols=st.integers(24, 72),
    window=st.tuples(st.integers(3, 15), st.integers(3, 15)),
    speckle_px=st.floats(0.7, 3.0),
    flat_gradient=st.booleans(),
)
def test_affine_lucas_kanade_matches_reference(
    seed: int, rows: int, cols: int, window: tuple[int, int], speckle_px: float, flat_gradient: bool
) -> None:
    """Random speckle under a random affine motion (frames of 24 to 72 pixels a side), windows of 7 x 7 to 31 x 31
    pixels anywhere (cut at either frame's edge, some wholly outside), started about 1 px off; with
    ``flat_gradient`` no window determines its warp. Same ok flags, ``initial`` where not ok, and where both
    converge the positions within 1e-3 px and the correlations within 1e-6, but for at most one window in 25 whose
    result rounding alone moves (within 0.01 px): measured on 13849 windows ok in both (600 random pairs), no flag
    differed, one position by 2.7e-3 px and one correlation by 2.7e-5, all others within 2e-6 px and 3e-7.
    Smaller windows are nearly singular: see the next test. A window that converges on no match (correlation below
    the tracker's 0.2 acceptance in either, e.g. -0.15 for a 7 x 11 window cut by a 24-row frame's edge) stops
    wherever rounding took its iteration (1.8 px apart in that case): only its flag is compared, and one such flag
    in 25 may differ (a 7 x 7 window on a 24-pixel frame, correlation -0.35, stopped 3.1 px from its start in
    NumPy and beyond the 3.5 px limit in Rust)."""
    rng = np.random.default_rng(seed)
    images, start, initial, _ = random_tracking_pair(rng, rows, cols, 25, speckle_px)
    if flat_gradient:
        images = (images[0], np.zeros_like(images[1]), images[2], images[3])
    window_px = (2 * window[0] + 1, 2 * window[1] + 1)
    tracked, ok, correlation = _core.affine_lucas_kanade(*images, start, initial, window_px)
    expected, expected_ok, expected_correlation = reference.affine_lucas_kanade(*images, start, initial, window_px)
    assert tracked.dtype == np.float32 and tracked.shape == start.shape and correlation.dtype == np.float64
    # a window on no match wanders wherever rounding takes it and can cross the half-window limit in one only
    no_match = np.where(ok, correlation, expected_correlation) < 0.2
    assert np.array_equal(ok[~no_match], expected_ok[~no_match]) and np.count_nonzero(ok != expected_ok) <= 1
    assert not (flat_gradient and ok.any())
    matched = ok & (np.minimum(correlation, expected_correlation) >= 0.2)
    position_error = np.abs(tracked - expected).max(axis=1)[matched]
    correlation_error = np.abs(correlation - expected_correlation)[matched]
    assert position_error.max(initial=0) <= 0.01
    assert np.count_nonzero((position_error > 1e-3) | (correlation_error > 1e-6)) <= 1
    np.testing.assert_array_equal(tracked[~ok], initial[~ok])
    np.testing.assert_array_equal(correlation[~ok], 0.0)


def test_affine_lucas_kanade_on_tiny_windows_mostly_matches_reference() -> None:
    """Windows of 3 x 3 to 5 x 7 pixels fit six parameters to 9-35 pixels: their Hessian is nearly singular and
    rounding alone (the order of the sums) can move the result. Measured on 400 random pairs (about 2000 such
    windows ok in both): 8 ok flags differed, 20 correlations by more than 1e-6, a few positions by up to 1.3 px;
    from 7 x 7 on none did. Held here to that: nearly all flags equal, most windows within the strict tolerances."""
    same_flags = close = both = 0
    for seed in range(60):
        rng = np.random.default_rng(seed)
        images, start, initial, _ = random_tracking_pair(rng, *rng.integers(8, 72, 2), 25, rng.uniform(0.7, 3.0))
        window_px = tuple(int(side) for side in rng.integers(1, 4, 2) * 2 + 1)
        tracked, ok, correlation = _core.affine_lucas_kanade(*images, start, initial, window_px)
        expected, expected_ok, expected_correlation = reference.affine_lucas_kanade(*images, start, initial, window_px)
        same_flags += np.count_nonzero(ok == expected_ok)
        agree = ok & expected_ok
        both += np.count_nonzero(agree)
        close += np.count_nonzero(
            (np.abs(tracked - expected).max(axis=1) <= 1e-3)
            & (np.abs(correlation - expected_correlation) <= 1e-6)
            & agree
        )
    assert same_flags >= 0.99 * 60 * 25 and close >= 0.97 * both and both > 200


def test_affine_lucas_kanade_recovers_a_known_affine_motion() -> None:
    """Both follow the motion that made ``after`` (speckle under a few per cent strain, noise) from 1 px off, to
    a few hundredths of a pixel for windows inside the frame."""
    images, start, initial, truth = random_tracking_pair(np.random.default_rng(4), 96, 112, 400)
    window_px = (21, 21)
    inside = np.all((start >= 12) & (start <= np.array([112, 96]) - 13), axis=1)
    for tracked, ok, correlation in (
        _core.affine_lucas_kanade(*images, start[inside], initial[inside], window_px),
        reference.affine_lucas_kanade(*images, start[inside], initial[inside], window_px),
    ):
        assert ok.all() and np.median(correlation) > 0.95
        errors = np.abs(tracked - truth[inside]).max(axis=1)
        assert np.percentile(errors, 90) < 0.05, np.percentile(errors, [50, 90, 100])


def _splat_points(
    rng: np.random.Generator, n: int, rows: int, cols: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """``n`` points for the bilinear splat on a (rows, cols) grid: a third anywhere from 3 cells before the grid to 3
    beyond it on every side, a third on cell edges (whole numbers from -1 to one beyond the last cell, -0.0, and the
    last position whose four cells are on the grid: just below the last index), a third crowded on a few cells;
    weights from 1e-3 to 1e3."""
    kind = rng.integers(0, 3, n)
    fine_col, fine_row = rng.uniform(-3, cols + 3, n), rng.uniform(-3, rows + 3, n)
    for values, cells in ((fine_col, cols), (fine_row, rows)):
        edges = np.concatenate([np.arange(-1.0, cells + 1), [-0.0, np.nextafter(cells - 1.0, -np.inf)]])
        on_edge = kind == 1
        values[on_edge] = rng.choice(edges, np.count_nonzero(on_edge))
        crowded = kind == 2
        values[crowded] = rng.choice(rng.uniform(0, cells, 3), np.count_nonzero(crowded))
    magnitude = 10.0 ** rng.uniform(-3, 3, n)
    return fine_col, fine_row, rng.normal(size=n) * magnitude, rng.normal(size=n) * magnitude


@SETTINGS
@given(
    seed=seeds,
    rows=st.integers(1, 40),
    cols=st.one_of(st.integers(1, 40), st.integers(2000, 20000)),
    n=st.one_of(st.just(0), st.integers(1, 3000)),
)
@example(seed=0, rows=1, cols=7, n=50)
@example(seed=1, rows=9, cols=1, n=50)
@example(seed=2, rows=2, cols=2, n=200)
@example(seed=3, rows=30, cols=30, n=0)
def test_splat_bilinear_matches_reference(seed: int, rows: int, cols: int, n: int) -> None:
    """The splat's float32 grids equal the twin's np.bincount sums bit for bit: points inside, outside on every side
    and on cell edges, empty input, grids of one row or column; wide grids (2000 columns and more) are summed by
    bands of a few rows in the kernel."""
    points = _splat_points(np.random.default_rng(seed), n, rows, cols)
    real, imag = _core.splat_bilinear(*points, (rows, cols))
    expected_real, expected_imag = reference.splat_bilinear(*points, (rows, cols))
    assert real.dtype == imag.dtype == np.float32 and real.shape == imag.shape == (rows, cols)
    np.testing.assert_array_equal(real, expected_real)
    np.testing.assert_array_equal(imag, expected_imag)


def test_splat_bilinear_of_simulated_scatterers_matches_reference() -> None:
    """A frame's worth of scatterers as the simulator splats them (256 x 256 pixels oversampled 3 times with a
    margin, random order), bit for bit; and a point at a known position spreads to its four cells as expected."""
    rng = np.random.default_rng(7)
    n, shape = 150_000, (3 * 256 + 20, 3 * 256 + 38)
    points = (
        rng.uniform(-30, shape[1] + 30, n),
        rng.uniform(-3, shape[0], n),
        rng.normal(size=n),
        rng.normal(size=n),
    )
    grids, twin_grids = _core.splat_bilinear(*points, shape), reference.splat_bilinear(*points, shape)
    for grid, twin_grid in zip(grids, twin_grids, strict=True):
        np.testing.assert_array_equal(grid, twin_grid)
    real, imag = _core.splat_bilinear(np.array([1.25]), np.array([2.5]), np.array([2.0]), np.array([-4.0]), (4, 5))
    expected = np.zeros((4, 5), np.float32)
    expected[2:4, 1:3] = [[0.375, 0.125], [0.375, 0.125]]
    np.testing.assert_array_equal(real, 2 * expected)
    np.testing.assert_array_equal(imag, -4 * expected)


def _blurred_speckle(rng: np.random.Generator, rows: int, cols: int, shift: tuple[int, int]) -> tuple:
    """Two uint8 frames of blurred speckle (smooth, so that bilinear samples land near rounding ties), the
    second moved by ``shift`` (rows, cols) pixels plus noise of +-3 gray levels."""
    import cv2

    base = cv2.GaussianBlur(rng.integers(0, 256, (rows + 8, cols + 8)).astype(np.uint8), (0, 0), rng.uniform(0.5, 2))
    moved = base[4 + shift[0] : 4 + shift[0] + rows, 4 + shift[1] : 4 + shift[1] + cols].astype(np.int16)
    noisy = np.clip(moved + rng.integers(-3, 4, moved.shape), 0, 255).astype(np.uint8)
    return np.ascontiguousarray(base[4 : 4 + rows, 4 : 4 + cols]), noisy


@SETTINGS
@given(
    seed=seeds,
    rows=st.integers(3, 70),
    cols=st.integers(3, 70),
    window=st.tuples(st.integers(0, 12), st.integers(0, 12)),
)
def test_patch_correlation_matches_reference(seed: int, rows: int, cols: int, window: tuple[int, int]) -> None:
    """Patches of 1 x 1 to 25 x 25 pixels around points anywhere (some beyond the frame: its edge replicated)
    in blurred speckle: the same 8-bit samples as ``cv2.remap`` (measured: none of 400000 random samples differs),
    so the correlations agree within 1e-9; the same at any thread count."""
    rng = np.random.default_rng(seed)
    before, after = _blurred_speckle(rng, rows, cols, tuple(rng.integers(-4, 5, 2)))
    window_px = (2 * window[0] + 1, 2 * window[1] + 1)
    start = rng.uniform(-5, [cols + 5, rows + 5], (60, 2)).astype(np.float32)
    end = (start + rng.normal(0, 3, start.shape)).astype(np.float32)
    correlation = _core.patch_correlation(before, after, start, end, window_px)
    expected = reference.patch_correlation(before, after, start, end, window_px)
    np.testing.assert_allclose(correlation, expected, atol=1e-9)
    np.testing.assert_array_equal(_core.patch_correlation(before, after, start, end, window_px, threads=1), correlation)


@SETTINGS
@given(
    seed=seeds,
    rows=st.integers(26, 90),
    cols=st.integers(26, 90),
    half_patch=st.integers(5, 12),
    spacing=st.integers(4, 12),
    search=st.integers(0, 9),
)
# cv2's float32 correlation 1.96e-4 below the float64 value, which the Rust peak equals to 1e-8
@example(seed=4083188, rows=26, cols=82, half_patch=5, spacing=5, search=6)
def test_block_match_matches_reference(
    seed: int, rows: int, cols: int, half_patch: int, spacing: int, search: int
) -> None:
    """Blocks of 11 x 11 to 25 x 25 (the tracker's: 25) in blurred speckle moved by up to 4 px, searched over
    +-0 to 9 px: the same nodes, peaks on the edge and, within 1e-3 px, flows as ``cv2.matchTemplate``, whose
    float32 correlation moves the peaks by up to a few 1e-4 (measured on 11243 nodes of 300 random pairs: flows
    within 3.4e-4 px, peaks within 4.8e-5; a search of the inputs found 1.96e-4); the same at any thread count."""
    rng = np.random.default_rng(seed)
    before, after = (frame.astype(np.float32) for frame in _blurred_speckle(rng, rows, cols, rng.integers(-4, 5, 2)))
    patch = 2 * half_patch + 1
    flow, peak, on_edge = _core.block_match(before, after, patch, spacing, search)
    expected_flow, expected_peak, expected_on_edge = reference.block_match(before, after, patch, spacing, search)
    assert flow.shape == expected_flow.shape and flow.dtype == np.float32
    np.testing.assert_allclose(flow, expected_flow, atol=1e-3)
    np.testing.assert_allclose(peak, expected_peak, atol=5e-4)
    np.testing.assert_array_equal(on_edge, expected_on_edge)
    threaded = _core.block_match(before, after, patch, spacing, search, threads=1)
    for ours, one_thread in zip((flow, peak, on_edge), threaded, strict=True):
        np.testing.assert_array_equal(ours, one_thread)


def test_patch_kernels_refuse_bad_input_with_named_errors() -> None:
    """Non-finite points, even windows, mismatched frames and a wrong dtype: InputError naming the argument."""
    from usdeform.errors import InputError

    frame = np.zeros((20, 20), np.uint8)
    points = np.full((3, 2), 5.0, np.float32)
    cases = [
        (lambda: _core.patch_correlation(frame, frame, points, np.full((3, 2), np.nan, np.float32), (5, 5)), "end"),
        (lambda: _core.patch_correlation(frame, frame, points, points, (4, 5)), "window_px"),
        (lambda: _core.patch_correlation(frame, frame[:10], points, points, (5, 5)), "after"),
        (lambda: _core.patch_correlation(frame, frame, points, points[:2], (5, 5)), "end"),
        (lambda: _core.block_match(frame, frame, 5, 4, 2), "before"),
        (lambda: _core.block_match(frame.astype(np.float32), frame.astype(np.float32), 5, 0, 2), "spacing"),
        (lambda: _core.block_match(frame.astype(np.float32), frame.astype(np.float32), -5, 4, 2), "patch"),
    ]
    for call, argument in cases:
        with pytest.raises(InputError, match=argument):
            call()
