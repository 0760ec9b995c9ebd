"""A library section that the FEM cannot solve never ends a diagnosis: it is solved again with finer load steps, or
only to the recorded indentation, or left out with the effect it models."""

import dataclasses

import numpy as np
import pytest

from usdeform.errors import InputError
from usdeform.gap import calibration, library_entries
from usdeform.gap.models import variant_weights
from usdeform.gap.observations import observe
from usdeform.sim import SectionSpec, solve_section
from usdeform.sim.mechanics import MechanicsConvergenceError

SPEC = SectionSpec(vessel_depth_mm=18.0, vessel_radius_mm=6.0, shear_modulus_kpa=20.0, mesh_size_mm=3.0)
STEPS = np.linspace(0.0, 9.0, 7)  # the library's steps: a recorded indentation of (9 - 0.5) / 1.15 = 7.4 mm
GRID_X, GRID_Z = np.arange(-15.0, 15.1, 3.0), np.arange(0.0, 30.1, 3.0)


def _failing(monkeypatch, fails):
    """solve_section that raises as Newton does wherever ``fails(steps)``."""

    def solve(spec, steps, **kwargs):
        if fails(np.asarray(steps)):
            raise MechanicsConvergenceError("Newton failed at load step 5: inverted element (J <= 0)")
        return solve_section(spec, steps, **kwargs)

    monkeypatch.setattr(library_entries, "solve_section", solve)


def test_a_section_failing_at_the_library_steps_is_solved_with_finer_ones(monkeypatch):
    _failing(monkeypatch, lambda steps: len(steps) == len(STEPS))
    entry = library_entries.library_entry(SPEC, STEPS, GRID_X, GRID_Z)
    assert entry.resolved == "finer steps"
    direct = solve_section(SPEC, np.linspace(0.0, 9.0, 25))
    np.testing.assert_allclose(entry.force_n, direct.force_at(STEPS))
    assert entry.field.shape == (2, len(STEPS), len(GRID_Z), len(GRID_X))
    assert np.isfinite(entry.field[:, -1, 3:, :]).all()


def test_a_section_failing_beyond_the_recorded_indentation_is_solved_to_it_and_extrapolated(monkeypatch):
    _failing(monkeypatch, lambda steps: steps[-1] > 8.7)  # beyond the recorded 7.4 mm and one step
    entry = library_entries.library_entry(SPEC, STEPS, GRID_X, GRID_Z)
    assert entry.resolved == "to the recorded indentation"
    monkeypatch.undo()
    full = library_entries.library_entry(SPEC, STEPS, GRID_X, GRID_Z)  # what it stands for
    assert full.resolved == ""
    inside = STEPS <= 8.7
    assert inside.sum() == len(STEPS) - 1
    np.testing.assert_allclose(entry.force_n[inside], full.force_n[inside], rtol=1e-3)
    # the step beyond is extrapolated linearly: near the solved one, within the curvature of 1.5 mm of loading
    assert entry.force_n[-1] == pytest.approx(full.force_n[-1], rel=0.05)


def test_a_section_that_cannot_be_solved_returns_why(monkeypatch):
    _failing(monkeypatch, lambda steps: True)
    assert "inverted element" in library_entries.library_entry(SPEC, STEPS, GRID_X, GRID_Z)


@pytest.mark.slow
def test_the_library_leaves_out_an_unsolvable_variant_with_its_effect(palpation, monkeypatch):
    observation = observe(palpation(), "palpation")
    all_variants = calibration.variant_specs

    def few(spec, parameters, has_vessel):
        variants = all_variants(spec, parameters, has_vessel)
        return {name: variants[name] for name in ("ideal", "slide", "layer_4_0.2", "layer_10_0.5")}

    monkeypatch.setattr(calibration, "variant_specs", few)
    solve = library_entries.library_entry

    def entry(variant, steps, grid_x, grid_z):
        if variant.layers and variant.layers[0].thickness_mm == 10.0:
            return "Newton failed at load step 16: inverted element (J <= 0)"
        return solve(variant, steps, grid_x, grid_z)

    monkeypatch.setattr(calibration, "cached_library_entry", entry)
    section = calibration.calibrate([observation], depths_mm=[60.0])[0]
    assert set(section.fields) == {"ideal", "slide"}
    assert section.left_out_effects == {"layered_tissue"}
    assert {(item.section, item.effect) for item in section.unsolved} == {
        ("layer_10_0.5", "layered_tissue"),
        ("layer_4_0.2", "layered_tissue"),
    }
    assert "inverted element" in next(item.error for item in section.unsolved if item.section == "layer_10_0.5")
    layer = {"layered_tissue": {"thickness_mm": 5.0, "modulus_ratio": 0.3}}
    assert variant_weights(layer, section) == {}
    assert variant_weights({"sliding_contact": {"slip_fraction": 0.5}}, section) == {"slide": 0.5}

    def no_ideal(variant, steps, grid_x, grid_z):
        return "Newton failed at load step 3" if not variant.layers and variant.contact != "slide" else "x"

    monkeypatch.setattr(calibration, "cached_library_entry", no_ideal)
    with pytest.raises(InputError, match="palpation: the calibrated FEM section cannot be solved"):
        calibration.calibrate([observation], depths_mm=[60.0])


def test_every_variant_names_its_effect():
    spec = dataclasses.replace(SPEC, width_mm=200.0)
    parameters = calibration.section_parameters(37.5)
    effects = {library_entries.effect_of_variant(name) for name in calibration.variant_specs(spec, parameters, True)}
    assert effects == {"", "sliding_contact", "layered_tissue", "probe_tilt", "lumen_pressure"}


def test_a_thinner_variant_the_vessel_does_not_fit_in_is_left_out_not_raised():
    """A deep, wide vessel (27 mm deep, 6 mm radius) in the library solved at 40 mm: the 35 mm depth variant cannot
    hold it (3 mm to spare) and is left out; the 45 mm one is kept."""
    parameters = calibration.section_parameters(40.0, 40.0)
    library = {parameter.name: parameter.library for parameter in parameters}
    spec = SectionSpec(width_mm=160.0, vessel_depth_mm=27.0, vessel_radius_mm=6.0, mesh_size_mm=2.5, **library)
    depth = next(parameter for parameter in parameters if parameter.name == "depth_mm")
    assert depth.variants == (35.0, 45.0)
    names = set(calibration.variant_specs(spec, parameters, True))
    assert depth.variant_name(45.0) in names and depth.variant_name(35.0) not in names
