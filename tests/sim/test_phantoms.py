"""Tests of the phantom presets and of sections varying along the sweep (coarse meshes)."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from usdeform.errors import InputError
from usdeform.sim.mechanics import SectionSpec, Vessel, section_mesh, solve_section
from usdeform.sim.phantoms import (
    Phantom,
    artery_vein_phantom,
    branching_phantom,
    compliant_vessel_phantom,
    soft_phantom,
    stiff_phantom,
)


def _coarse(phantom: Phantom) -> Phantom:
    """The preset on a coarse mesh, 3 geometry knots (0, 40, 80 mm) and 12 lambda steps."""
    return dataclasses.replace(phantom.with_section_changes(mesh_size_mm=3.0), geometry_knots=3, n_probe_steps=12)


@pytest.fixture(scope="module")
def stiff():
    return _coarse(stiff_phantom())


@pytest.fixture(scope="module")
def soft():
    return _coarse(soft_phantom())


def _stiffness_statistics(solution, max_force_n):
    """Mean and SD of k = 2 c1 lam + c2 (N/m) over the palpation range, and R^2 of orders 1, 2, 3."""
    lam = np.linspace(0.0, float(solution.probe_displacement_at_force(max_force_n)), 60)
    force = solution.force_at(lam)
    r_squared = []
    for order in (1, 2, 3):
        fit = np.polyval(np.polyfit(lam, force, order), lam)
        r_squared.append(1 - np.sum((force - fit) ** 2) / np.sum((force - force.mean()) ** 2))
    c1, c2, _ = np.polyfit(lam, force, 2)
    k = (2 * c1 * lam + c2) * 1e3  # N/mm -> N/m
    return k.mean(), k.std(), np.array(r_squared), 2 * c1 * 1e3


def test_stiff_preset_is_nearly_linear_at_3200_n_per_m(stiff):
    solution = stiff.solution_at(0.0)
    assert solution.force_n[-1] > stiff.max_force_n
    mean, sd, r_squared, slope = _stiffness_statistics(solution, stiff.max_force_n)
    assert mean == pytest.approx(3237, rel=0.06)
    assert 15 < sd < 150 and slope > 0  # paper: 3237 +/- 56 N/m
    assert r_squared[0] > 0.999 and r_squared[1] > 0.9995


def test_soft_preset_is_nonlinear_at_1500_n_per_m(soft):
    solution = soft.solution_at(0.0)
    assert solution.force_n[-1] > soft.max_force_n
    mean, sd, r_squared, slope = _stiffness_statistics(solution, soft.max_force_n)
    assert mean == pytest.approx(1489, rel=0.08)
    assert sd == pytest.approx(617, rel=0.15)  # paper: 1489 +/- 617 N/m
    assert slope > 100  # dk/dlam in N/m per mm: clearly stiffening
    assert r_squared[0] < 0.98  # a line does not explain it ...
    assert r_squared[1] > 0.998  # ... a quadratic does ...
    assert r_squared[2] - r_squared[1] < 0.002  # ... and a cubic adds little


def test_soft_phantom_is_about_half_as_stiff_as_the_stiff_one(stiff, soft):
    stiff_mean = _stiffness_statistics(stiff.solution_at(0.0), stiff.max_force_n)[0]
    soft_mean = _stiffness_statistics(soft.solution_at(0.0), soft.max_force_n)[0]
    assert 0.35 < soft_mean / stiff_mean < 0.6


def test_vessel_areas_match_the_paper():
    assert np.pi * stiff_phantom().base_section.vessel_radius_mm ** 2 == pytest.approx(224, rel=0.01)
    assert np.pi * soft_phantom().base_section.vessel_radius_mm ** 2 == pytest.approx(57, rel=0.01)


@pytest.mark.parametrize("make", [stiff_phantom, soft_phantom])
def test_stiffness_and_vessel_vary_smoothly_along_the_sweep(make):
    phantom = make()
    assert phantom.length_mm >= 60
    s = np.linspace(0.0, phantom.length_mm, 161)
    scale = phantom.stiffness_scale_at(s)
    assert scale[0] == 1.0 and np.all(scale > 0)
    assert np.abs(np.diff(scale)).max() < 0.01  # smooth at 0.5 mm sampling
    assert (
        abs(phantom.stiffness_scale_at(20.0) - phantom.stiffness_scale_at(0.0)) > 0.03
    )  # positions 20 mm apart differ
    sections = [phantom.section_at(v) for v in s]
    depth = np.array([sec.vessel_depth_mm for sec in sections])
    assert np.ptp(depth) > 1.0 and np.abs(np.diff(depth)).max() < 0.1
    modulus = np.array([sec.shear_modulus_kpa for sec in sections])
    np.testing.assert_allclose(modulus, phantom.base_section.shear_modulus_kpa * scale)


def test_solution_at_a_knot_is_the_scaled_knot_solve(stiff):
    s = 40.0  # a knot of the coarse phantom
    solution = stiff.solution_at(s)
    knot = solve_section(stiff.unscaled_section_at(s), stiff.probe_displacement_mm)
    np.testing.assert_allclose(solution.force_n, stiff.stiffness_scale_at(s) * knot.force_n, rtol=1e-12)
    assert solution.spec == stiff.section_at(s)


def test_solution_between_knots_is_continuous_and_uses_local_vessel(stiff):
    near_knot = stiff.solution_at(39.9)
    at_knot = stiff.solution_at(40.0)
    assert near_knot.force_n[-1] == pytest.approx(at_knot.force_n[-1], rel=2e-3)
    between = stiff.solution_at(20.0)
    assert between.spec.vessel_depth_mm == stiff.section_at(20.0).vessel_depth_mm
    lam = float(between.probe_displacement_mm[-1])
    assert between.lumen_area_mm2(0.0) == pytest.approx(np.pi * between.spec.vessel_radius_mm**2, rel=1e-3)
    assert between.lumen_area_mm2(lam) < 0.9 * between.lumen_area_mm2(0.0)
    rng = np.random.default_rng(3)
    reference = np.column_stack([rng.uniform(-40, 40, 20), rng.uniform(1, 59, 20)])
    deformed = reference + between.displacement(reference, lam)
    np.testing.assert_allclose(between.deformed_position_inverse(deformed, lam), reference, atol=1e-5)


def test_softest_position_still_reaches_the_maximum_force(soft):
    softest_scale = soft.stiffness_scale_at(np.linspace(0.0, soft.length_mm, 161)).min()
    # the vessel geometry changes the force by a few per cent only: keep a 10 % margin for it
    assert soft.solution_at(0.0).force_n[-1] * softest_scale > 1.1 * soft.max_force_n


def test_variants_pass_through_the_phantom(stiff):
    sliding = stiff.with_section_changes(contact="slide")
    assert sliding.section_at(10.0).contact == "slide"
    assert sliding.section_at(10.0).shear_modulus_kpa == stiff.section_at(10.0).shear_modulus_kpa


@pytest.mark.parametrize("s", [-1.0, 80.5, np.nan])
def test_positions_outside_the_phantom_raise(stiff, s):
    with pytest.raises(InputError):
        stiff.section_at(s)
    with pytest.raises(InputError):
        stiff.solution_at(s)


def test_phantom_rejects_a_vessel_leaving_the_section():
    with pytest.raises(InputError):
        dataclasses.replace(stiff_phantom(), vessel_shift_depth_mm=40.0)


def test_blend_between_knots_approximates_a_direct_solve(stiff):
    s = 20.0  # midway between the coarse phantom's knots at 0 and 40 mm
    blended = stiff.solution_at(s)
    direct = solve_section(stiff.unscaled_section_at(s), stiff.probe_displacement_mm).scaled(
        float(stiff.stiffness_scale_at(s))
    )
    lam = 8.0
    assert blended.force_at(lam) == pytest.approx(direct.force_at(lam), rel=0.01)
    assert np.abs(blended.lumen_boundary(lam) - direct.lumen_boundary(lam)).max() < 0.5


def test_compliant_vessel_loses_at_least_a_quarter_of_its_area_at_the_highest_force():
    """Measured (2 mm production mesh): 31.8 % area loss at s = 0 (8.5 mm pressed), 30.3 % at the
    stiffest position (8.1 mm), 33.5 % at the softest (8.9 mm); the vessel spans 15-22 mm of depth."""
    phantom = compliant_vessel_phantom()
    section = phantom.section_at(0.0)
    assert section.vessel_depth_mm - section.vessel_radius_mm == pytest.approx(15.0)
    assert section.vessel_depth_mm + section.vessel_radius_mm == pytest.approx(22.0)
    stiffest, softest = phantom.length_mm / 4, 3 * phantom.length_mm / 4
    for s_mm in (0.0, stiffest, softest):
        solution = phantom.solution_at(s_mm)
        pressed = float(solution.probe_displacement_at_force(phantom.max_force_n))
        area_loss = 1.0 - solution.lumen_area_mm2(pressed) / solution.lumen_area_mm2(0.0)
        assert 8.0 <= pressed <= 9.0, (s_mm, pressed)
        assert 0.25 <= area_loss <= 0.4, (s_mm, area_loss)


def test_a_vein_beside_an_artery_collapses_far_more_at_the_same_indentation():
    """Measured (artery_vein_phantom, 1.5 mm mesh, bone at 32 mm): at 6 mm pressed (12.6 N) the artery keeps
    80 % of its area and the vein 47 %."""
    phantom = artery_vein_phantom()
    solution = phantom.solution_at(0.0)
    kept = [solution.lumen_area_mm2(6.0, vessel=v) / solution.lumen_area_mm2(0.0, vessel=v) for v in (0, 1)]
    assert 0.7 < kept[0] < 0.9 and 0.35 < kept[1] < 0.6, kept
    assert solution.lumen_area_mm2(0.0, vessel=1) == pytest.approx(np.pi * 2.9**2, rel=0.02)


def test_each_lumen_of_a_section_is_meshed_with_its_own_stiffness():
    spec = artery_vein_phantom().base_section
    mesh, in_lumen, _ = section_mesh(spec)
    centroids = mesh.p[:, mesh.t].mean(axis=1).T
    lumen = spec.lumen_index(centroids)
    assert np.array_equal(in_lumen, lumen >= 0)
    assert set(np.unique(lumen)) == {-1, 0, 1}
    factor = spec.lumen_modulus_factor(centroids)
    assert np.allclose(factor[lumen == 0], 0.3) and np.allclose(factor[lumen == 1], 0.03)
    assert np.allclose(factor[lumen < 0], 1.0)


def test_section_rejects_lumens_that_touch_or_leave_it():
    with pytest.raises(InputError, match="apart"):
        SectionSpec(vessel_center_x_mm=0.0, extra_vessels=(Vessel(9.0, 20.0, 3.0),))
    with pytest.raises(InputError, match="extra_vessels\\[0\\]"):
        SectionSpec(extra_vessels=(Vessel(20.0, 59.0, 3.0),))
    with pytest.raises(InputError, match="extra_vessels\\[0\\]"):
        SectionSpec(extra_vessels=(Vessel(20.0, 20.0, 3.0, 0.0),))


def test_a_branch_leaves_the_artery_along_the_sweep():
    phantom = branching_phantom()
    start, end = phantom.section_at(0.0).lumens, phantom.section_at(phantom.length_mm).lumens
    gap_start = start[1, 0] - start[1, 2] - (start[0, 0] + start[0, 2])
    gap_end = end[1, 0] - end[1, 2] - (end[0, 0] + end[0, 2])
    assert gap_start == pytest.approx(3.0) and gap_end == pytest.approx(8.0)
    assert (start[1, 2], end[1, 2]) == pytest.approx((1.5, 2.6))
    with pytest.raises(InputError, match="extra_vessels_end"):
        dataclasses.replace(phantom, extra_vessels_end=phantom.extra_vessels_end * 2)  # one end per extra vessel
