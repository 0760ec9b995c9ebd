"""The diagnosis's worker pool (usdeform.gap.processes): calls run in order, in the pool or here, and the attribution's
fits in worker processes equal those made in this process."""

import warnings
from concurrent.futures import Future
from concurrent.futures.process import BrokenProcessPool

import numpy as np
import pytest

from usdeform.gap import attribution, processes
from usdeform.gap.calibration import calibrate
from usdeform.gap.models import EFFECT_BY_ID, surveyed_depth_mm, without_points_near_base
from usdeform.gap.observations import observe
from usdeform.sim import ImageLatency


def test_run_all_keeps_the_order_and_counts_each_call():
    class Bar:
        count = 0

        def update(self, n):
            self.count += n

    bar = Bar()
    with processes.worker_pool(2) as pool:
        assert processes.run_all(pool, divmod, [(7, 2), (9, 4), (5, 5)], bar) == [(3, 1), (2, 1), (1, 0)]
    assert processes.run_all(None, divmod, [(7, 2)], bar) == [(3, 1)]
    assert processes.run_all(None, divmod, []) == []
    assert bar.count == 4


def test_calls_a_stopped_pool_did_not_run_run_here():
    class HalfBrokenPool:  # the first call ran, then the workers stopped
        calls = 0

        def submit(self, function, *args):
            future = Future()
            if self.calls == 0:
                future.set_result(function(*args))
            else:
                future.set_exception(BrokenProcessPool("a worker stopped"))
            self.calls += 1
            return future

    with pytest.warns(RuntimeWarning, match="running the rest in this process"):
        assert processes.run_all(HalfBrokenPool(), divmod, [(7, 2), (9, 4), (5, 5)]) == [(3, 1), (2, 1), (1, 0)]


def test_a_pool_of_one_is_this_process_and_fewer_are_refused():
    with processes.worker_pool(1) as pool:
        assert pool is None
    with pytest.raises(ValueError, match="workers: expected at least 1, got 0"):
        with processes.worker_pool(0):
            pass


@pytest.mark.slow
def test_attribution_fits_in_worker_processes_equal_those_made_here(palpation, monkeypatch):
    # three library effects (two of them fitted as a pair from the singles' fits) keep the test short
    monkeypatch.setattr(
        attribution, "EFFECTS", tuple(EFFECT_BY_ID[e] for e in ("image_latency", "force_latency", "probe_tilt"))
    )
    observation = observe(palpation([ImageLatency(0.1)]), "latency")
    (survey,) = calibrate([observation], survey=True)
    (section,) = calibrate([observation], depths_mm=[surveyed_depth_mm(observation, survey)])
    observation = without_points_near_base(observation, section)
    results = {}
    for workers in (1, 2):
        with processes.worker_pool(workers) as pool, warnings.catch_warnings():
            warnings.simplefilter("error", RuntimeWarning)  # no fall-back to this process
            results[workers] = attribution.attribute([observation], [section], pool=pool)
    here, pooled = results[1], results[2]
    assert here.verdict == pooled.verdict and here.named == pooled.named
    assert [c.effect for c in here.candidates] == [c.effect for c in pooled.candidates]
    assert len(here.candidates) == 6  # three singles and three pairs
    for ours, theirs in zip(here.candidates, pooled.candidates, strict=True):
        assert ours.parameters == theirs.parameters
        assert ours.gap_after == theirs.gap_after and ours.significant == theirs.significant
    assert np.array_equal(
        [m.value_after for m in here.measures], [m.value_after for m in pooled.measures], equal_nan=True
    )
