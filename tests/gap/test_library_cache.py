"""The FEM library's disk cache: an entry is computed once, read back unchanged, keyed by every input, written
atomically, rewritten when corrupt, and switched off on request."""

import dataclasses
import multiprocessing

import numpy as np
import pytest

from usdeform.gap import library_cache, library_entries
from usdeform.sim import SectionSpec

SPEC = SectionSpec(vessel_depth_mm=18.0, vessel_radius_mm=6.0, shear_modulus_kpa=20.0, mesh_size_mm=3.0)
STEPS = np.linspace(0.0, 6.0, 4)
GRID_X, GRID_Z = np.arange(-12.0, 12.1, 3.0), np.arange(0.0, 24.1, 3.0)


@pytest.fixture
def cache(tmp_path, monkeypatch):
    """A fresh cache directory; returns its library folder."""
    monkeypatch.setenv("USDEFORM_CACHE_DIR", str(tmp_path))
    monkeypatch.delenv(library_cache.CACHE_SWITCH, raising=False)
    return tmp_path / "library"


@pytest.fixture
def counted(monkeypatch):
    """Counts the entries computed (not read from the cache)."""
    calls = []
    compute = library_entries.library_entry

    def entry(*args):
        calls.append(args)
        return compute(*args)

    monkeypatch.setattr(library_cache, "library_entry", entry)
    return calls


def _same(first, second):
    for name in ("field", "lumen_area_mm2", "force_n"):
        np.testing.assert_array_equal(getattr(first, name), getattr(second, name))
    assert first.resolved == second.resolved


def test_an_entry_is_computed_once_and_read_back_unchanged(cache, counted):
    assert not library_cache.entry_is_cached(SPEC, STEPS, GRID_X, GRID_Z)
    first = library_cache.cached_library_entry(SPEC, STEPS, GRID_X, GRID_Z)
    assert library_cache.entry_is_cached(SPEC, STEPS, GRID_X, GRID_Z)
    second = library_cache.cached_library_entry(SPEC, STEPS, GRID_X, GRID_Z)
    assert len(counted) == 1
    _same(first, second)
    _same(first, library_entries.library_entry(SPEC, STEPS, GRID_X, GRID_Z))
    assert [path.suffix for path in cache.iterdir()] == [".npz"]  # no temporary file left


def test_the_key_changes_with_every_input():
    keys = {
        library_cache.entry_key(SPEC, STEPS, GRID_X, GRID_Z),
        library_cache.entry_key(dataclasses.replace(SPEC, mesh_size_mm=2.5), STEPS, GRID_X, GRID_Z),
        library_cache.entry_key(dataclasses.replace(SPEC, poisson_ratio=0.42), STEPS, GRID_X, GRID_Z),
        library_cache.entry_key(dataclasses.replace(SPEC, contact="slide"), STEPS, GRID_X, GRID_Z),
        library_cache.entry_key(SPEC, np.linspace(0.0, 6.5, 4), GRID_X, GRID_Z),
        library_cache.entry_key(SPEC, STEPS, GRID_X + 0.5, GRID_Z),
        library_cache.entry_key(SPEC, STEPS, GRID_X, GRID_Z[:-1]),
    }
    assert len(keys) == 7
    assert library_cache.entry_key(SPEC, STEPS, GRID_X, GRID_Z) == library_cache.entry_key(
        dataclasses.replace(SPEC), STEPS.copy(), GRID_X.copy(), GRID_Z.copy()
    )


def test_a_corrupt_entry_is_ignored_and_rewritten(cache, counted):
    first = library_cache.cached_library_entry(SPEC, STEPS, GRID_X, GRID_Z)
    (path,) = cache.iterdir()
    path.write_bytes(path.read_bytes()[:200])  # truncated, as by a full disk
    second = library_cache.cached_library_entry(SPEC, STEPS, GRID_X, GRID_Z)
    assert len(counted) == 2
    _same(first, second)
    library_cache.cached_library_entry(SPEC, STEPS, GRID_X, GRID_Z)
    assert len(counted) == 2  # rewritten whole


def test_an_entry_stored_under_another_key_is_not_read(cache, counted):
    library_cache.cached_library_entry(SPEC, STEPS, GRID_X, GRID_Z)
    (path,) = cache.iterdir()
    other = dataclasses.replace(SPEC, poisson_ratio=0.42)
    path.rename(cache / f"{library_cache.entry_key(other, STEPS, GRID_X, GRID_Z)}.npz")
    entry = library_cache.cached_library_entry(other, STEPS, GRID_X, GRID_Z)
    assert len(counted) == 2
    _same(entry, library_entries.library_entry(other, STEPS, GRID_X, GRID_Z))


def test_a_section_that_cannot_be_solved_is_cached_with_why(cache, monkeypatch):
    monkeypatch.setattr(library_cache, "library_entry", lambda *args: "Newton failed at load step 5")
    assert library_cache.cached_library_entry(SPEC, STEPS, GRID_X, GRID_Z) == "Newton failed at load step 5"
    monkeypatch.setattr(library_cache, "library_entry", lambda *args: pytest.fail("computed again"))
    assert library_cache.cached_library_entry(SPEC, STEPS, GRID_X, GRID_Z) == "Newton failed at load step 5"


def test_the_cache_can_be_switched_off(cache, counted, monkeypatch):
    monkeypatch.setenv(library_cache.CACHE_SWITCH, "off")
    assert library_cache.library_cache_dir() is None
    for _ in range(2):
        library_cache.cached_library_entry(SPEC, STEPS, GRID_X, GRID_Z)
    assert len(counted) == 2
    assert not cache.exists()


def test_the_cache_follows_xdg_without_its_own_variable(tmp_path, monkeypatch):
    monkeypatch.delenv("USDEFORM_CACHE_DIR", raising=False)
    monkeypatch.delenv(library_cache.CACHE_SWITCH, raising=False)
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path))
    assert library_cache.library_cache_dir() == tmp_path / "usdeform" / "library"


def _entry_in_process(arguments):
    return library_cache.cached_library_entry(*arguments).force_n


def test_concurrent_processes_write_one_readable_entry(cache):
    context = multiprocessing.get_context("spawn")
    with context.Pool(2) as pool:
        forces = pool.map(_entry_in_process, [(SPEC, STEPS, GRID_X, GRID_Z)] * 4)
    for force in forces[1:]:
        np.testing.assert_array_equal(force, forces[0])
    assert len(list(cache.iterdir())) == 1
    np.testing.assert_array_equal(library_cache.cached_library_entry(SPEC, STEPS, GRID_X, GRID_Z).force_n, forces[0])


@pytest.mark.slow
def test_a_second_diagnosis_reads_the_library_and_says_the_same(palpation, tmp_path, monkeypatch):
    from usdeform.gap import diagnose
    from usdeform.gap.report import write_report

    monkeypatch.delenv(library_cache.CACHE_SWITCH, raising=False)
    monkeypatch.setattr(library_cache, "library_cache_dir", lambda: tmp_path / "library")  # the FEM solutions stay
    recording = palpation()
    first = write_report(diagnose([recording], progress=False, workers=1), tmp_path / "first")
    assert any((tmp_path / "library").glob("*.npz"))
    monkeypatch.setattr(library_cache, "library_entry", lambda *args: pytest.fail("an entry was computed again"))
    second = write_report(diagnose([recording], progress=False, workers=1), tmp_path / "second")
    assert (second / "diagnosis.json").read_text() == (first / "diagnosis.json").read_text()


def test_recordings_of_nearby_indentations_share_their_library_entries(palpation):
    from usdeform.gap import calibration
    from usdeform.gap.observations import observe

    observation = observe(palpation(), "palpation")
    plan = calibration._LibraryPlan.of(observation, None, survey=False)
    step = calibration._LAMBDA_STEP_MM
    np.testing.assert_array_equal(plan.steps, np.arange(len(plan.steps)) * step)  # a lattice from 0
    top = calibration._top_lambda_mm(observation)
    assert plan.steps[-2] < top <= plan.steps[-1]
    deepest = float(np.max(observation.probe_displacement_mm))

    def pressed_to(top_mm):  # the observation with its indentation scaled to reach ``top_mm`` of library
        scale = (top_mm - library_entries.SPARE_MM) / library_entries.SPARE_FACTOR / deepest
        return dataclasses.replace(observation, probe_displacement_mm=observation.probe_displacement_mm * scale)

    shallower = calibration._LibraryPlan.of(pressed_to(plan.steps[-2] + 0.01), None, survey=False)
    assert set(shallower.solves()) == set(plan.solves())  # within one step: the same entries
    deeper = calibration._LibraryPlan.of(pressed_to(plan.steps[-1] + 0.01), None, survey=False)
    assert len(deeper.steps) == len(plan.steps) + 1
    assert not set(deeper.solves()) & set(plan.solves())
