import pytest


def pytest_configure(config):
    config.addinivalue_line("markers", "gap_benchmark: the small end-to-end gap benchmark (a few minutes)")


@pytest.fixture(scope="session")
def gap_phantom():
    """A coarse test phantom (two 3 mm-mesh geometry knots) for simulated palpations; FEM cached as usual."""
    from usdeform.sim import Phantom, SectionSpec

    section = SectionSpec(vessel_depth_mm=18.0, vessel_radius_mm=6.0, shear_modulus_kpa=25.0, mesh_size_mm=3.0)
    return Phantom(
        "gap-test",
        section,
        length_mm=40.0,
        stiffness_amplitude=0.05,
        max_probe_displacement_mm=10.0,
        n_probe_steps=11,
        geometry_knots=2,
    )


@pytest.fixture(scope="session")
def palpation(gap_phantom):
    """A function making an 80-frame load-hold-unload palpation of the test phantom to 12 N at s = 10 mm; each
    recording is simulated once per run and shared (tests only read it)."""
    from usdeform.sim import simulate_palpation

    made = {}

    def make(effects=(), seed=3):
        key = (repr(list(effects)), seed)  # the effects are dataclasses: their repr lists every parameter
        if key not in made:
            made[key], _ = simulate_palpation(
                gap_phantom, 10.0, 12.0, n_frames=80, ramp="up-hold-down", hold_s=2.0, seed=seed, effects=list(effects)
            )
        return made[key]

    return make


@pytest.fixture(scope="session")
def latency_diagnosis(palpation):
    from usdeform.gap import diagnose
    from usdeform.sim import ImageLatency

    return diagnose([palpation([ImageLatency(0.1)])], progress=False)
