import os
import signal
import sys
from pathlib import Path

import pytest

# Make the shared random-input helpers importable from every test module.
sys.path.insert(0, str(Path(__file__).parent))

# A run started in the background by a non-interactive shell inherits SIGINT ignored, and passes that on to the
# commands the tests start; the tests of Ctrl-C need it delivered, as it is in a terminal.
if signal.getsignal(signal.SIGINT) == signal.SIG_IGN:
    signal.signal(signal.SIGINT, signal.default_int_handler)

SHARED_DATA_VARIABLE = "USDEFORM_SHARED_DATA"
"""Environment variable naming the folder of real data (``plus/``, ``deepuse-rf/``); default ``../shared/data``
beside the clone."""


def _real_data(name: str) -> Path:
    """The folder ``name`` of the real data (public data sets kept outside the repository), or skip the test."""
    root = Path(os.environ.get(SHARED_DATA_VARIABLE) or Path(__file__).resolve().parents[2] / "shared" / "data")
    folder = root / name
    if not folder.is_dir():
        pytest.skip(
            f"real data {folder} not found: it is not part of the repository; "
            f"set {SHARED_DATA_VARIABLE} to the folder holding {name}/ to run this test"
        )
    return folder


@pytest.fixture(scope="session")
def plus_data() -> Path:
    """The PLUS toolkit's spine-phantom sweep, its configurations and reference volumes (BSD-3), or skip."""
    return _real_data("plus")


@pytest.fixture(scope="session")
def deepuse_rf_data() -> Path:
    """The DeepUSE in-vivo RF sequences under freehand compression (MIT; layout in its README), or skip."""
    return _real_data("deepuse-rf")


@pytest.fixture(scope="session", autouse=True)
def run_mechanics_cache(tmp_path_factory):
    """``USDEFORM_CACHE_DIR``: a folder of this run's own, shared by its tests, so that a section is solved once per
    run and never read from an earlier run's (or the user's ``~/.cache``) solutions. Fixtures that need an empty
    cache set their own."""
    path = tmp_path_factory.mktemp("usdeform-run-cache")
    with pytest.MonkeyPatch.context() as patch:
        patch.setenv("USDEFORM_CACHE_DIR", str(path))
        yield path


@pytest.fixture(scope="session")
def small_palpation():
    """A finite-element palpation of a coarse test phantom: 8 frames of 128 x 128 up to 8 N,
    as (Recording, GroundTruth)."""
    from usdeform.sim.phantoms import coarse_phantom
    from usdeform.sim.recordings import simulate_palpation

    return simulate_palpation(coarse_phantom(), 20.0, 8.0, n_frames=8, seed=11, rows=128, cols=128)


@pytest.fixture(scope="session")
def quick_demo(tmp_path_factory):
    """``usdeform demo --quick`` run once for the session through the command line:
    (DemoResult, output folder with report.html, what the command printed)."""
    import contextlib
    import io

    from usdeform.cli import main
    from usdeform.demo import pipeline

    output = tmp_path_factory.mktemp("demo")
    results, printed = [], io.StringIO()

    def keep_result(*args, **kwargs):
        results.append(run_demo(*args, **kwargs))
        return results[-1]

    run_demo = pipeline.run_demo
    with pytest.MonkeyPatch.context() as patch, contextlib.redirect_stdout(printed):
        patch.setattr(pipeline, "run_demo", keep_result)
        assert main(["demo", "--quick", "--output", str(output)]) == 0
    return results[0], output, printed.getvalue()


@pytest.fixture(scope="session")
def quick_experiment(tmp_path_factory):
    """A function running ``usdeform experiment NAME --quick`` with an empty solution cache and
    returning its output folder."""
    from usdeform.cli import main

    def run(name: str) -> Path:
        output = tmp_path_factory.mktemp(name)
        with pytest.MonkeyPatch.context() as patch:
            patch.setenv("USDEFORM_CACHE_DIR", str(tmp_path_factory.mktemp("cache")))
            assert main(["experiment", name, "--quick", "--output", str(output)]) == 0
        return output

    return run
