import sys
from pathlib import Path

import pytest

# Make the shared random-input helpers importable from every test module.
sys.path.insert(0, str(Path(__file__).parent))


@pytest.fixture(scope="session")
def small_palpation(tmp_path_factory):
    """A finite-element palpation of a coarse test phantom: 8 frames of 128 x 128 up to 8 N,
    as (Recording, GroundTruth)."""
    from usdeform.sim.mechanics import SectionSpec
    from usdeform.sim.phantoms import Phantom
    from usdeform.sim.recordings import simulate_palpation

    section = SectionSpec(width_mm=115.0, depth_mm=50.0, vessel_depth_mm=18.0, vessel_radius_mm=5.0, mesh_size_mm=3.0)
    phantom = Phantom(
        name="test",
        base_section=section,
        length_mm=60.0,
        stiffness_amplitude=0.2,
        max_force_n=15.0,
        max_probe_displacement_mm=8.0,
        n_probe_steps=5,
        geometry_knots=2,
    )
    with pytest.MonkeyPatch.context() as patch:
        patch.setenv("USDEFORM_CACHE_DIR", str(tmp_path_factory.mktemp("usdeform-cache")))
        return simulate_palpation(phantom, 20.0, 8.0, n_frames=8, seed=11, rows=128, cols=128)
