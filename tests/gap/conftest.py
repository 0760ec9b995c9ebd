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


def _known_weight_signals(weight_n=5.0, gain=0.04, offset=0.8, drift=0.02, seed=0, rate_hz=20.0):
    """Time (s), load and reading (N) of a known weight: 1 s unloaded, put on over 0.3 s, held 3 s, taken off, 1 s
    unloaded; 0.03 N of noise."""
    import numpy as np

    time = np.arange(0.0, 5.6, 1 / rate_hz)
    on = np.clip(time - 1.0, 0, 0.3) / 0.3 - np.clip(time - 4.3, 0, 0.3) / 0.3
    load = weight_n * on
    noise = 0.03 * np.random.default_rng(seed).standard_normal(len(time))
    return time, load, (1 + gain) * load + offset + drift * time + noise


@pytest.fixture
def known_weight_signals():
    """The function giving a known weight's time (s), load and reading (N)."""
    return _known_weight_signals


@pytest.fixture
def write_known_weight():
    """A function writing a known-weight sequence file (blank 8 x 8 frames, ContactForce and per-frame KnownLoad of
    :func:`known_weight_signals`) to ``path``, ``with_load=False`` leaving KnownLoad out; it returns the load (N)."""
    import numpy as np

    from usdeform.io.sequence_file import write_sequence
    from usdeform.recording import Recording

    def write(path, with_load=True, **signals):
        time, load, reading = _known_weight_signals(**signals)
        n = len(time)
        recording = Recording(
            frames=np.zeros((n, 8, 8), np.uint8),
            timestamps=time,
            probe_to_base=np.tile(np.eye(4), (n, 1, 1)),
            pose_valid=np.ones(n, bool),
            image_to_probe=np.diag([0.1, 0.1, 1.0, 1.0]),
            force=reading,
            probe_displacement=np.zeros(n),
        )
        write_sequence(path, recording, compress=False, frame_series={"KnownLoad": load} if with_load else None)
        return load

    return write
