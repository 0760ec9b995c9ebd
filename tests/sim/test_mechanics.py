"""Tests of the finite-element section mechanics (coarse meshes, cached solves)."""

from __future__ import annotations

import dataclasses
import time

import numpy as np
import pytest
from skfem import BilinearForm, LinearForm
from skfem.helpers import grad

from usdeform import _core
from usdeform.errors import InputError, UsdeformError
from usdeform.reference.mechanics import first_piola_and_tangent
from usdeform.sim.mechanics import (
    PROBE_WIDTH_MM,
    Layer,
    MechanicsConvergenceError,
    SectionSpec,
    cache_dir,
    fem,
    section_mesh,
    solve_section,
)
from usdeform.sim.mechanics import solution as solution_module

COARSE = SectionSpec(
    mesh_size_mm=4.0, vessel_radius_mm=6.0, vessel_depth_mm=20.0, shear_modulus_kpa=20.0, yeoh_c2=1.0, yeoh_c3=1.0
)
LAMBDA = np.linspace(0.0, 8.0, 5)


@pytest.fixture(scope="module")
def solution():
    return solve_section(COARSE, LAMBDA)


def _strain_energy(F, mu, c2, c3, kappa):
    J = F[0, 0] * F[1, 1] - F[0, 1] * F[1, 0]
    x = J ** (-2 / 3) * (np.sum(F * F) + 1) - 3
    return mu / 2 * (x + c2 * x**2 + c3 * x**3) + kappa / 4 * (J**2 - 1 - 2 * np.log(J))


@pytest.mark.parametrize("c2, c3", [(0.0, 0.0), (2.8, 5.0), (-0.19, 0.02)])
def test_stress_is_energy_derivative_and_tangent_is_stress_derivative(c2, c3):
    rng = np.random.default_rng(1)
    gradient = rng.normal(scale=0.2, size=(2, 2, 1, 1))
    mu, kappa = np.array([[0.02]]), np.array([[0.2]])
    yeoh = (np.array([[c2]]), np.array([[c3]]))
    no_pressure = np.zeros((1, 1))
    stress, tangent, _ = first_piola_and_tangent(gradient, mu, *yeoh, kappa, no_pressure)
    eps = 1e-6
    for k in range(2):
        for m in range(2):
            step = np.zeros_like(gradient)
            step[k, m] = eps
            energy_slope = (
                _strain_energy(np.eye(2) + (gradient + step)[..., 0, 0], mu[0, 0], c2, c3, kappa[0, 0])
                - _strain_energy(np.eye(2) + (gradient - step)[..., 0, 0], mu[0, 0], c2, c3, kappa[0, 0])
            ) / (2 * eps)
            assert energy_slope == pytest.approx(stress[k, m, 0, 0], rel=1e-6, abs=1e-10)
            plus = first_piola_and_tangent(gradient + step, mu, *yeoh, kappa, no_pressure)[0]
            minus = first_piola_and_tangent(gradient - step, mu, *yeoh, kappa, no_pressure)[0]
            np.testing.assert_allclose((plus - minus) / (2 * eps), tangent[:, :, k, m], rtol=1e-6, atol=1e-9)


def test_pressure_stress_is_cauchy_minus_p_identity():
    gradient = np.array([[0.1, 0.05], [-0.02, -0.2]])[..., None, None]
    zero = np.zeros((1, 1))
    stress, _, _ = first_piola_and_tangent(gradient, zero, zero, zero, zero, np.array([[0.003]]))
    F = np.eye(2) + gradient[..., 0, 0]
    cauchy = stress[..., 0, 0] @ F.T / np.linalg.det(F)
    np.testing.assert_allclose(cauchy, -0.003 * np.eye(2), atol=1e-15)


@pytest.mark.parametrize("probe_width", [PROBE_WIDTH_MM, 31.0])
def test_mesh_conforms_to_lumen_probe_edges_and_layers(probe_width):
    spec = dataclasses.replace(COARSE, layers=(Layer(3.0, 10.0), Layer(7.0, 15.0)), probe_width_mm=probe_width)
    mesh, in_lumen, material = section_mesh(spec)
    nodes = mesh.p.T
    assert np.any(np.all(np.isclose(nodes, [probe_width / 2, 0.0]), axis=1))
    assert np.any(np.all(np.isclose(nodes, [-probe_width / 2, 0.0]), axis=1))
    edge1, edge2 = nodes[mesh.t[1]] - nodes[mesh.t[0]], nodes[mesh.t[2]] - nodes[mesh.t[0]]
    areas = 0.5 * np.abs(edge1[:, 0] * edge2[:, 1] - edge1[:, 1] * edge2[:, 0])
    assert areas.sum() == pytest.approx(spec.width_mm * spec.depth_mm)
    lumen_area = areas[in_lumen].sum()
    assert lumen_area == pytest.approx(np.pi * spec.vessel_radius_mm**2, rel=0.05)
    depth_of_centroid = nodes[mesh.t].mean(axis=0)[:, 1]
    assert set(np.unique(material)) == {0, 1, 2}
    assert np.all(depth_of_centroid[material == 0] < 3.0) and np.all(depth_of_centroid[material == 2] > 10.0)


@pytest.mark.parametrize(
    "changes",
    [
        {"vessel_depth_mm": 3.0},  # vessel pokes out of the surface
        {"vessel_depth_mm": 57.0},  # ... out of the bottom
        {"vessel_center_x_mm": 58.0},  # ... out of the side
        {"width_mm": 100.0},  # narrower than 3 probe widths
        {"probe_width_mm": 45.0},  # ... the same, by a wider probe
        {"probe_width_mm": 0.0},
        {"depth_mm": "60"},
        {"contact": "glue"},
        {"poisson_ratio": 0.5},
        {"lumen_stiffness_ratio": 20.0},
        {"shear_modulus_kpa": -1.0},
        {"yeoh_c3": -1.0},
        {"yeoh_c2": -0.5, "yeoh_c3": 0.05},  # energy would decrease with I1bar at moderate strain
        {"layers": (Layer(70.0, 10.0),)},
        {"face_tilt_deg": 35.0},
        {"face_travel_deg": -31.0},
        {"face_tilt_deg": float("nan")},
        {"face_radius_mm": 10.0},  # smaller than half the face
        {"face_radius_mm": -60.0},
    ],
)
def test_bad_spec_raises_input_error(changes):
    with pytest.raises(InputError):
        dataclasses.replace(COARSE, **changes)


@pytest.mark.parametrize("steps", [[0.0, 2.0, 1.0], [1.0, 2.0], [0.0], [0.0, np.nan], [0.0, 30.0]])
def test_bad_probe_displacements_raise_input_error(steps):
    with pytest.raises(InputError):
        solve_section(COARSE, np.array(steps))


def test_force_starts_at_zero_and_grows_monotonically(solution):
    assert solution.force_n[0] == 0.0
    assert np.all(np.diff(solution.force_n) > 0)
    assert np.all(np.diff(solution.force_n, 2) > 0)  # stiffens (Yeoh c2, c3 > 0)


def test_newton_converges_within_few_iterations(solution):
    assert np.all(solution.newton_iterations[2:] <= 6)


def test_newton_converges_quadratically():
    problem = fem._SectionProblem(COARSE)
    half, _ = problem.solve_step(np.zeros(problem.basis.N), 0.5)
    one, _ = problem.solve_step(half, 1.0)
    u = 2 * one - half  # linear predictor of lambda = 1.5
    free, residuals = problem.free_dofs, []
    for _ in range(4):
        force, stiffness = problem.internal_force_and_tangent(u)
        residuals.append(np.abs(force[free]).max())
        u[free] += problem.solver.solve(stiffness, -force[free])
    contraction = np.array(residuals[1:]) / np.array(residuals[:-1])
    assert np.all(np.diff(contraction) < 0) and contraction[-1] < 1e-4  # superlinear (quadratic) convergence


@pytest.mark.parametrize("face", [{}, {"face_tilt_deg": 8.0}, {"contact": "slide", "lumen_pressure_kpa": 2.0}])
def test_reusing_the_tangent_in_newton_s_last_steps_keeps_full_newton_s_state(face, monkeypatch):
    """Modified Newton (the factor of the tangent kept once the steps are small and contracting) converges to
    full Newton's state, and factorises less."""
    spec, steps = dataclasses.replace(COARSE, **face), np.array([0.0, 1.0, 2.0, 3.0, 4.0])
    solver_class, counts = _core.SymmetricSolver, {}

    def solved(reuse_below_mm: float) -> dict:
        monkeypatch.setattr(fem, "_REUSE_TANGENT_BELOW_MM", reuse_below_mm)
        calls = [0]

        class CountingSolver:
            def __init__(self, indptr, indices):
                self.solver = solver_class(indptr, indices)

            def factorize(self, values):
                calls[0] += 1
                return self.solver.factorize(values)

        monkeypatch.setattr(_core, "SymmetricSolver", CountingSolver)
        try:
            return fem._solve_uncached(spec, steps)
        finally:
            monkeypatch.setattr(_core, "SymmetricSolver", solver_class)
            counts[reuse_below_mm] = calls[0]

    reuse_below_mm = fem._REUSE_TANGENT_BELOW_MM
    full, modified = solved(0.0), solved(reuse_below_mm)
    np.testing.assert_allclose(modified["displacement_dofs"], full["displacement_dofs"], rtol=0, atol=1e-12)
    np.testing.assert_allclose(modified["force_n"], full["force_n"], rtol=1e-12, atol=1e-12)
    assert counts[reuse_below_mm] < 0.8 * counts[0.0]
    # a kept factor whose every step is refused: the tangent is factorised at every iteration, as full Newton does
    monkeypatch.setattr(fem, "_REUSED_STEP_CONTRACTION", 0.0)
    refused = solved(reuse_below_mm)
    np.testing.assert_array_equal(refused["displacement_dofs"], full["displacement_dofs"])
    np.testing.assert_array_equal(refused["newton_iterations"], full["newton_iterations"])
    assert counts[reuse_below_mm] == counts[0.0]


@LinearForm
def _internal_force_form(v, w):
    return np.einsum("ij...,ij...->...", w["stress"], grad(v))


@BilinearForm
def _tangent_form(u, v, w):
    return np.einsum("ijkl...,kl...,ij...->...", w["tangent"], grad(u), grad(v))


@pytest.mark.parametrize("contact", ["stick", "slide"])
def test_assembly_matches_scikit_fem_forms(contact):
    """The section's compiled element loop against scikit-fem's form assembly of the same integrals."""
    spec = dataclasses.replace(
        COARSE, contact=contact, lumen_pressure_kpa=1.5, layers=(Layer(thickness_mm=5.0, shear_modulus_kpa=40.0),)
    )
    problem = fem._SectionProblem(spec)
    u = np.random.default_rng(4).normal(scale=0.01, size=problem.basis.N)
    force, values = problem.internal_force_and_tangent(u)
    stress, tangent, _ = first_piola_and_tangent(
        problem.basis.interpolate(u).grad,
        problem.shear_modulus,
        problem.yeoh_c2,
        problem.yeoh_c3,
        problem.bulk_modulus,
        problem.lumen_pressure,
    )
    np.testing.assert_allclose(force, _internal_force_form.assemble(problem.basis, stress=stress), atol=1e-12)
    expected = _tangent_form.assemble(problem.basis, tangent=tangent).tocsr()[problem.free_dofs][:, problem.free_dofs]
    rhs = np.random.default_rng(5).normal(size=len(problem.free_dofs))
    np.testing.assert_allclose(problem.solver.solve(values, expected @ rhs), rhs, rtol=1e-8, atol=1e-8)
    np.testing.assert_allclose(np.sort(values), np.sort(expected.tocsr().data), rtol=1e-10, atol=1e-14)


def test_boundary_conditions(solution):
    bottom = np.column_stack([np.linspace(-60, 60, 31), np.full(31, 60.0)])
    face = np.column_stack([np.linspace(-18.75, 18.75, 31), np.zeros(31)])
    for lam in (3.0, 8.0):
        np.testing.assert_allclose(solution.displacement(bottom, lam), 0.0, atol=1e-12)
        np.testing.assert_allclose(solution.displacement(face, lam), np.tile([0.0, lam], (31, 1)), atol=1e-10)
    beside = solution.displacement(np.array([[30.0, 0.0]]), 8.0)[0]
    assert 0 < beside[1] < 8.0  # the free surface beside the probe is dragged down, less than the face


def test_symmetric_problem_gives_symmetric_field(solution):
    rng = np.random.default_rng(0)
    points = np.column_stack([rng.uniform(-55, 55, 50), rng.uniform(0, 60, 50)])
    mirrored = points * [-1, 1]
    u, u_mirrored = solution.displacement(points, 8.0), solution.displacement(mirrored, 8.0)
    np.testing.assert_allclose(u[:, 0], -u_mirrored[:, 0], atol=1e-3)
    np.testing.assert_allclose(u[:, 1], u_mirrored[:, 1], atol=1e-3)


def test_displacement_is_linear_in_lambda_between_steps(solution):
    points = np.array([[5.0, 10.0], [-20.0, 30.0]])
    middle = solution.displacement(points, 3.0)
    expected = 0.5 * (solution.displacement(points, 2.0) + solution.displacement(points, 4.0))
    np.testing.assert_allclose(middle, expected, atol=1e-12)


def test_the_locator_remembers_its_last_queries_and_answers_each_as_a_fresh_search(solution, monkeypatch):
    """A grid and a lumen's wall queried in turn are located once each; a fifth distinct query drops the oldest;
    a remembered answer is the fresh search's, read-only."""
    nodes = solution._fields[0][0].nodes
    elements = solution._fields[0][0].elements
    locator = solution_module._TriangleLocator(nodes, elements)
    rng = np.random.default_rng(3)
    queries = [np.column_stack([rng.uniform(-20, 20, 50), rng.uniform(1, 40, 50)]) for _ in range(5)]
    searches = []
    search = locator._locate
    monkeypatch.setattr(locator, "_locate", lambda points: searches.append(len(points)) or search(points))
    for _ in range(3):
        for query in queries[:2]:
            found, coordinates = locator.locate(query.copy())
            fresh_found, fresh_coordinates = solution_module._TriangleLocator(nodes, elements).locate(query)
            np.testing.assert_array_equal(found, fresh_found)
            np.testing.assert_array_equal(coordinates, fresh_coordinates)
            assert not found.flags.writeable and not coordinates.flags.writeable
    assert len(searches) == 2
    for query in queries[2:]:
        locator.locate(query)
    locator.locate(queries[1])  # still remembered (four kept)
    assert len(searches) == 5
    locator.locate(queries[0])  # the oldest, dropped for the fifth
    assert len(searches) == 6


def test_points_outside_the_section(solution):
    outside = np.array([[0.0, -1.0], [70.0, 10.0]])
    with pytest.raises(InputError, match="outside the section"):
        solution.displacement(outside, 4.0)
    assert np.all(np.isnan(solution.displacement(outside, 4.0, outside="nan")))
    with pytest.raises(InputError):
        solution.displacement(np.zeros((3, 3)), 4.0)
    with pytest.raises(InputError):
        solution.displacement(np.zeros((1, 2)), 9.0)  # beyond the solved lambda range


def test_lumen_compresses(solution):
    areas = [solution.lumen_area_mm2(lam) for lam in LAMBDA]
    assert areas[0] == pytest.approx(np.pi * 36.0, rel=1e-3)
    assert np.all(np.diff(areas) < 0)
    wall = solution.lumen_boundary(8.0, n_points=64)
    assert wall.shape == (64, 2)
    height, width = np.ptp(wall[:, 1]), np.ptp(wall[:, 0])
    assert height < 12.0 - 1.0 and width > 12.0  # flattened: shorter, wider


def test_inverse_map_round_trip(solution):
    rng = np.random.default_rng(2)
    reference = np.column_stack([rng.uniform(-40, 40, 40), rng.uniform(1, 59, 40)])
    deformed = reference + solution.displacement(reference, 6.0)
    np.testing.assert_allclose(solution.deformed_position_inverse(deformed, 6.0), reference, atol=1e-5)
    above_tissue = np.array([[0.0, 3.0]])  # under the probe the tissue starts at z = lambda
    assert np.all(np.isnan(solution.deformed_position_inverse(above_tissue, 6.0)))


def test_force_and_probe_displacement_interpolation(solution):
    forces = solution.force_at(np.array([0.0, 3.0, 8.0]))
    assert forces[0] == 0.0 and forces[2] == solution.force_n[-1]
    np.testing.assert_allclose(solution.probe_displacement_at_force(forces), [0.0, 3.0, 8.0])
    with pytest.raises(InputError):
        solution.probe_displacement_at_force(solution.force_n[-1] + 1.0)


def test_solutions_are_cached_on_disk(solution):
    path = cache_dir() / f"{COARSE.cache_key(LAMBDA)}.npz"
    assert path.exists() and not list(path.parent.glob("*.tmp"))
    solution_module._loaded_solutions.clear()  # load from disk, not from memory
    start = time.perf_counter()
    again = solve_section(COARSE, LAMBDA)
    assert time.perf_counter() - start < 0.5
    np.testing.assert_array_equal(again.force_n, solution.force_n)
    assert COARSE.cache_key(LAMBDA) != dataclasses.replace(COARSE, poisson_ratio=0.44).cache_key(LAMBDA)
    assert COARSE.cache_key(LAMBDA) != COARSE.cache_key(LAMBDA * 1.01)


def test_corrupt_cache_entry_is_solved_again():
    spec = dataclasses.replace(COARSE, vessel_depth_mm=25.0)
    steps = np.array([0.0, 2.0])
    path = cache_dir() / f"{spec.cache_key(steps)}.npz"
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_bytes(b"not a zip file")
    assert solve_section(spec, steps).force_n[1] > 0
    assert path.stat().st_size > 1000


def test_modulus_scaling_scales_force_and_keeps_field():
    steps = np.array([0.0, 2.0, 4.0])
    base = solve_section(COARSE, steps)
    doubled = solve_section(COARSE.scaled(2.0), steps)
    np.testing.assert_allclose(doubled.force_n, 2.0 * base.force_n, rtol=1e-7)
    points = np.array([[0.0, 14.0], [10.0, 30.0]])
    np.testing.assert_allclose(doubled.displacement(points, 4.0), base.displacement(points, 4.0), atol=1e-7)
    np.testing.assert_allclose(base.scaled(2.0).force_n, doubled.force_n, rtol=1e-7)


def test_mesh_convergence_of_force():
    steps = np.array([0.0, 4.0])
    coarse = solve_section(COARSE, steps).force_n[1]
    fine = solve_section(dataclasses.replace(COARSE, mesh_size_mm=3.0), steps).force_n[1]
    assert coarse == pytest.approx(fine, rel=0.02)


def test_default_variants_are_the_ideal_section():
    ideal = dataclasses.replace(COARSE, layers=(), contact="stick", lumen_pressure_kpa=0.0)
    assert ideal == COARSE and ideal.cache_key(LAMBDA) == COARSE.cache_key(LAMBDA)


def test_sliding_contact_lets_the_surface_slip_and_softens(solution):
    sliding = solve_section(dataclasses.replace(COARSE, contact="slide"), LAMBDA)
    assert np.all(sliding.force_n[1:] < solution.force_n[1:])
    face = np.column_stack([np.linspace(-18.0, 18.0, 13), np.zeros(13)])
    slip = sliding.displacement(face, 8.0)
    assert np.abs(slip[:, 0]).max() > 0.02  # the surface slips along the face (sticking: exactly 0)
    np.testing.assert_allclose(slip[:, 0], -slip[::-1, 0], atol=1e-6)
    np.testing.assert_allclose(slip[:, 1], 8.0, atol=1e-10)


def test_a_wider_probe_face_presses_more_tissue_down(solution):
    wide = solve_section(dataclasses.replace(COARSE, probe_width_mm=COARSE.width_mm / 3), LAMBDA)
    assert np.all(wide.force_n[1:] > 1.05 * solution.force_n[1:])
    edge = np.array([[COARSE.width_mm / 6, 0.0]])  # on the wide face, beside the default one
    np.testing.assert_allclose(wide.displacement(edge, 8.0), [[0.0, 8.0]], atol=1e-10)
    assert solution.displacement(edge, 8.0)[0, 1] < 7.0
    deep = np.array([[0.0, 45.0]])
    assert wide.displacement(deep, 8.0)[0, 1] > solution.displacement(deep, 8.0)[0, 1]


def test_soft_layers_change_force_and_field(solution):
    skin_fat = (Layer(2.0, 60.0, 1.0, 1.0), Layer(8.0, 5.0, 1.0, 1.0))
    layered = solve_section(dataclasses.replace(COARSE, layers=skin_fat), LAMBDA)
    assert np.all(layered.force_n[1:] < solution.force_n[1:])
    point = np.array([[0.0, 12.0]])  # in the base material below a soft fat layer: displaced less
    assert layered.displacement(point, 8.0)[0, 1] < solution.displacement(point, 8.0)[0, 1] - 0.2


def test_lumen_pressure_distends_the_lumen_and_changes_the_force(solution):
    pressurised = solve_section(dataclasses.replace(COARSE, lumen_pressure_kpa=2.0), LAMBDA)
    assert pressurised.lumen_area_mm2(0.0) > solution.lumen_area_mm2(0.0) + 1.0
    assert pressurised.lumen_area_mm2(8.0) > solution.lumen_area_mm2(8.0) + 1.0
    assert pressurised.force_n[0] > 0  # the distended vessel pushes on the probe already at lambda = 0
    assert np.all(np.abs(pressurised.force_n - solution.force_n) > 0.05)


def test_newton_failure_names_the_step(monkeypatch):
    monkeypatch.setattr(fem, "_MAX_NEWTON_ITERATIONS", 1)
    monkeypatch.setattr(fem, "_MAX_STEP_HALVINGS", 1)
    spec = dataclasses.replace(COARSE, vessel_depth_mm=30.0)
    with pytest.raises(MechanicsConvergenceError, match="load step 1") as failure:
        solve_section(spec, np.array([0.0, 4.0]), use_cache=False)
    assert isinstance(failure.value, UsdeformError)


def _surface_gap_and_reaction(spec: SectionSpec, lam: float):
    """Per face node: the face's depth minus the surface's (mm, >= 0 where the surface is below the face) and the
    node's reaction (N/mm, compression positive), from a fresh solve up to ``lam``."""
    problem = fem._SectionProblem(spec)
    u, _, _ = fem._continuation(problem.solve_step, 0.0, lam, np.zeros(problem.basis.N), "test", None, 0.5)
    force, _ = problem.internal_force_and_tangent(u, with_tangent=False)
    face_depth = lam - problem.face_gap_mm
    return u[problem.face_z_dofs] - face_depth, force[problem.face_z_dofs]


@pytest.mark.parametrize(
    "face", [{"face_tilt_deg": 8.0}, {"face_radius_mm": 40.0}, {"face_tilt_deg": -5.0, "contact": "slide"}]
)
def test_a_face_that_is_not_flat_and_level_meets_the_surface_progressively(face, solution):
    spec = dataclasses.replace(COARSE, **face)
    gap_mm, reaction = _surface_gap_and_reaction(spec, 3.0)
    assert gap_mm.min() > -1e-5  # no node of the surface above the face
    touching = np.abs(gap_mm) < 1e-5
    assert 0 < touching.sum() < len(touching)  # part of the face is in contact at 3 mm
    assert reaction[touching].min() > -1e-6 * np.abs(reaction).max()  # the face only pushes
    np.testing.assert_allclose(reaction[~touching], 0.0, atol=1e-6 * np.abs(reaction).max())
    tilted = solve_section(spec, LAMBDA)
    assert np.all(tilted.force_n[1:] < solution.force_n[1:])  # less of the face presses at a given lambda
    assert np.all(np.diff(tilted.force_n) > 0)


def test_a_tilted_face_touches_first_with_its_lower_edge_and_mirrors_the_other_tilt():
    right = dataclasses.replace(COARSE, face_tilt_deg=6.0, vessel_center_x_mm=4.0)
    left = dataclasses.replace(COARSE, face_tilt_deg=-6.0, vessel_center_x_mm=-4.0)
    half = right.probe_width_mm / 2
    np.testing.assert_allclose(
        right.face_gap_mm(np.array([half, 0.0, -half])),
        [0.0, half * np.tan(np.radians(6)), 2 * half * np.tan(np.radians(6))],
    )
    solved_right, solved_left = solve_section(right, LAMBDA), solve_section(left, LAMBDA)
    # the same up to the mesh, which is not mirror-symmetric about a vessel off the centre
    np.testing.assert_allclose(solved_right.force_n, solved_left.force_n, rtol=1e-3)
    points = np.column_stack([np.linspace(-30, 30, 13), np.linspace(2, 40, 13)])
    u_right, u_left = solved_right.displacement(points, 4.0), solved_left.displacement(points * [-1, 1], 4.0)
    np.testing.assert_allclose(u_right, u_left * [-1, 1], atol=0.02)
    edge = solved_right.displacement(np.array([[half - 0.5, 0.0], [-half + 0.5, 0.0]]), 2.0)
    assert edge[0, 1] > 1.5 > edge[1, 1]  # the lower (+x) edge has pressed the surface down, the other not yet


def test_a_flat_level_face_keeps_its_cache_key():
    explicit = dataclasses.replace(COARSE, face_tilt_deg=0.0, face_radius_mm=float("inf"))
    assert explicit.cache_key(LAMBDA) == COARSE.cache_key(LAMBDA)
    assert dataclasses.replace(COARSE, face_tilt_deg=1.0).cache_key(LAMBDA) != COARSE.cache_key(LAMBDA)


def test_a_face_pressed_off_the_normal_drags_the_sticking_surface_with_it(solution):
    oblique = solve_section(dataclasses.replace(COARSE, face_travel_deg=10.0), LAMBDA)
    face = np.column_stack([np.linspace(-18.0, 18.0, 13), np.zeros(13)])
    slope = np.tan(np.radians(10.0))
    np.testing.assert_allclose(oblique.displacement(face, 8.0), np.tile([8.0 * slope, 8.0], (13, 1)), atol=1e-10)
    deep = np.array([[0.0, 10.0]])
    assert oblique.displacement(deep, 8.0)[0, 0] > solution.displacement(deep, 8.0)[0, 0] + 0.3
    # a tilted face caught the surface at different lambdas: each node has moved sideways since it was caught
    spec = dataclasses.replace(COARSE, face_tilt_deg=6.0, face_travel_deg=-6.0)
    problem = fem._SectionProblem(spec)
    u, _, _ = fem._continuation(problem.solve_step, 0.0, 4.0, np.zeros(problem.basis.N), "test", None, 0.5)
    caught = problem.in_contact
    assert 0 < caught.sum() < len(caught)
    lateral = u[problem.face_x_dofs[caught]]
    np.testing.assert_allclose(lateral - problem.stick_anchor_mm[caught], 4.0 * np.tan(np.radians(-6.0)), atol=1e-12)
    assert lateral.min() < lateral.max() - 0.05  # the nodes caught first (the +x edge, lower) have moved furthest
