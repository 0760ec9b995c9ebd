import sys
from pathlib import Path

import pytest

# Make the shared random-input helpers importable from every test module.
sys.path.insert(0, str(Path(__file__).parent))


@pytest.fixture(scope="session")
def small_palpation(tmp_path_factory):
    """A finite-element palpation of a coarse test phantom: 8 frames of 128 x 128 up to 8 N,
    as (Recording, GroundTruth)."""
    from usdeform.sim.phantoms import coarse_phantom
    from usdeform.sim.recordings import simulate_palpation

    phantom = coarse_phantom()
    with pytest.MonkeyPatch.context() as patch:
        patch.setenv("USDEFORM_CACHE_DIR", str(tmp_path_factory.mktemp("usdeform-cache")))
        return simulate_palpation(phantom, 20.0, 8.0, n_frames=8, seed=11, rows=128, cols=128)
