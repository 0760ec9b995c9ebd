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


@pytest.fixture(scope="session")
def quick_demo(tmp_path_factory):
    """``usdeform demo --quick`` run once for the session: (DemoResult, output folder with report.html)."""
    from usdeform.demo import DemoConfig, run_demo
    from usdeform.demo.report import write_report

    output = tmp_path_factory.mktemp("demo")
    result = run_demo(output, DemoConfig(quick=True), progress=False)
    write_report(result, output / "report.html")
    return result, output
