"""The FEM library of a calibrated section: the same whether its solves run in one process or several, or its
worker processes fail; the diagnosis's worker pool (usdeform.gap.processes)."""

import subprocess
import sys
import time
from concurrent.futures import Future
from concurrent.futures.process import BrokenProcessPool

import numpy as np
import pytest

from usdeform.gap import calibration, processes
from usdeform.gap.observations import observe


@pytest.mark.slow
def test_library_solved_in_parallel_processes_equals_the_serial_library(palpation, tmp_path, monkeypatch):
    observation = observe(palpation(), "palpation")
    all_variants = calibration.variant_specs

    def two_variants(spec, parameters, has_vessel):  # keep the test short: the ideal section and one variant
        variants = all_variants(spec, parameters, has_vessel)
        return {name: variants[name] for name in ("ideal", "poisson_ratio=0.49")}

    monkeypatch.setattr(calibration, "variant_specs", two_variants)
    sections = {}
    for workers in (1, 2):
        monkeypatch.setenv("USDEFORM_CACHE_DIR", str(tmp_path / f"cache_{workers}"))  # both solve from scratch
        with processes.worker_pool(workers) as pool:
            sections[workers] = calibration.calibrate([observation], pool=pool)[0]
        assert len(list((tmp_path / f"cache_{workers}" / "mechanics").glob("*.npz"))) == 2

    class BrokenPool:  # as when the workers die: a script without a main guard re-runs itself in each worker
        def __init__(self, *args, **kwargs):
            pass

        def submit(self, *args):
            future = Future()
            future.set_exception(BrokenProcessPool("a worker stopped"))
            return future

        def shutdown(self, wait=True, cancel_futures=False):
            pass

    monkeypatch.setattr(processes, "ProcessPoolExecutor", BrokenPool)
    monkeypatch.setenv("USDEFORM_CACHE_DIR", str(tmp_path / "cache_broken"))
    with pytest.warns(RuntimeWarning, match="if __name__ == '__main__'"), processes.worker_pool(2) as pool:
        sections["broken"] = calibration.calibrate([observation], pool=pool)[0]
    serial, parallel, fallback = sections[1], sections[2], sections["broken"]
    for name in serial.fields:
        np.testing.assert_array_equal(serial.fields[name], fallback.fields[name])
    assert list(serial.fields) == list(parallel.fields) == ["ideal", "poisson_ratio=0.49"]
    for name in serial.fields:
        np.testing.assert_array_equal(serial.fields[name], parallel.fields[name])
        np.testing.assert_array_equal(serial.lumen_area_mm2[name], parallel.lumen_area_mm2[name])
        np.testing.assert_array_equal(serial.force_n[name], parallel.force_n[name])
    assert serial.shear_modulus_kpa == parallel.shear_modulus_kpa


def test_library_workers_end_when_the_process_that_started_them_is_killed(tmp_path):
    script = tmp_path / "parent.py"
    script.write_text(
        "import multiprocessing, os, sys, time\n"
        "from concurrent.futures import ProcessPoolExecutor\n"
        "from usdeform.gap.processes import _exit_with_parent\n"
        "if __name__ == '__main__':\n"
        "    pool = ProcessPoolExecutor(2, mp_context=multiprocessing.get_context('spawn'),\n"
        "                               initializer=_exit_with_parent, initargs=(os.getpid(),))\n"
        "    pids = {pool.submit(os.getpid).result() for _ in range(4)}\n"
        "    pool.submit(time.sleep, 600)\n"
        "    print(' '.join(map(str, pids)), flush=True)\n"
        "    time.sleep(600)\n"
    )
    parent = subprocess.Popen([sys.executable, str(script)], stdout=subprocess.PIPE, text=True)
    try:
        workers = [int(pid) for pid in parent.stdout.readline().split()]
        assert workers and all(_alive(pid) for pid in workers)
    finally:
        parent.kill()  # SIGKILL: no shutdown of the pool
        parent.wait()
    deadline = time.monotonic() + 20
    while any(_alive(pid) for pid in workers) and time.monotonic() < deadline:
        time.sleep(0.2)
    assert not any(_alive(pid) for pid in workers)


def test_an_interrupt_during_the_solves_drops_the_queued_ones(palpation, tmp_path, monkeypatch):
    # Ctrl-C or SIGTERM (usdeform.cli raises it in the main thread) while the library solves: the pool's exit used
    # to wait for every queued solve, minutes, before the command could stop
    observation = observe(palpation(), "palpation")
    monkeypatch.setenv("USDEFORM_CACHE_DIR", str(tmp_path / "cache"))
    pools = []

    class RecordingPool:
        def __init__(self, *args, **kwargs):
            self.shutdowns = []
            pools.append(self)

        def submit(self, *args):
            future = Future()
            future.set_result((np.zeros((2, 1, 1, 1)), np.zeros(1), np.zeros(1)))
            return future

        def shutdown(self, wait=True, cancel_futures=False):
            self.shutdowns.append((wait, cancel_futures))

    class InterruptedBar:
        def update(self, n):
            raise KeyboardInterrupt

    monkeypatch.setattr(processes, "ProcessPoolExecutor", RecordingPool)
    with pytest.raises(KeyboardInterrupt), processes.worker_pool(2) as pool:
        calibration.calibrate([observation], survey=True, progress=InterruptedBar(), pool=pool)
    assert [pool.shutdowns for pool in pools] == [[(False, True)]]


def _alive(pid: int) -> bool:
    """Whether process ``pid`` runs (a zombie, dead but not yet reaped by init, counts as gone)."""
    try:
        with open(f"/proc/{pid}/stat") as handle:
            return handle.read().split(")")[-1].split()[0] != "Z"
    except FileNotFoundError:
        return False
