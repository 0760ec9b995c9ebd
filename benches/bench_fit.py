"""Fit benchmark: how long ``usdeform fit`` takes on 4 palpations, tracking against fitting.

Usage: ``python benches/bench_fit.py [--before-rev main] [--cache PATH] [--profile] [--repeats N]``

Four simulated 50-frame 256 x 256 palpations of the compliant vessel phantom (seeds 0-3, four
positions along the sweep, up to 17 N) are measured as ``usdeform fit`` measures them
(:func:`usdeform.fitting.measure_positions`: stiffness, tracks, vessel wall), then fitted with each
named method of :data:`usdeform.fitting.FIT_METHODS` by this tree's ``usdeform.regression`` ("after") and by
the one at ``--before-rev`` ("before", read with git), in the same process. Reported per step: the
best wall time of ``--repeats`` runs and the peak of memory newly allocated by Python and NumPy
(tracemalloc), and the fit command's total against its tracking. ``--profile`` prints where this
tree's fits spend their time (cProfile, cumulative). Before and after are compared in image
coordinates (``anchor="image"``); a vessel-anchored method's own fit time is given after the row
and counted in the fit command's total. The fit without a design matrix landed after
6d73e92: ``--before-rev 6d73e92`` compares with the sparse-design fit it replaced. The simulated
recordings and their measurements are pickled to ``--cache`` so reruns skip the simulation; tracking
is timed again on every run.
"""

from __future__ import annotations

import argparse
import copyreg
import cProfile
import dataclasses
import pickle
import pstats
import time
import tracemalloc
import types
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from landed import landed_module
from usdeform.fitting import FIT_METHODS, FitMethod, SampledPosition, fit_measured, measure_positions
from usdeform.recording import Recording
from usdeform.sim import compliant_vessel_phantom, simulate_palpation


# Tracks keep their rejection counts in a read-only mapping, which pickle cannot store: as a dict.
def _read_only(mapping: dict) -> types.MappingProxyType:
    return types.MappingProxyType(mapping)


copyreg.pickle(types.MappingProxyType, lambda proxy: (_read_only, (dict(proxy),)))

POSITIONS_MM = (10.0, 25.0, 40.0, 55.0)  # one palpation each, seeds 0-3
MAX_FORCE_N = 17.0
FLEXIBLE_LAYER_MM = compliant_vessel_phantom().base_section.depth_mm  # as usdeform.experiments.paper_2d


def palpations(cache: Path) -> list[Recording]:
    """The four simulated palpations (pickled to ``cache``)."""
    if cache.exists():
        with cache.open("rb") as file:
            return pickle.load(file)
    phantom = compliant_vessel_phantom()
    recordings = [
        simulate_palpation(phantom, s_mm, MAX_FORCE_N, n_frames=50, seed=seed, rows=256, cols=256)[0]
        for seed, s_mm in enumerate(POSITIONS_MM)
    ]
    with cache.open("wb") as file:
        pickle.dump(recordings, file)
    return recordings


def measured(recordings: list[Recording], cache: Path) -> list[SampledPosition]:
    """The palpations measured as ``usdeform fit`` measures them (pickled to ``cache``)."""
    if cache.exists():
        with cache.open("rb") as file:
            return pickle.load(file)
    result = measure_positions(recordings, FLEXIBLE_LAYER_MM, wall="auto")[0]
    with cache.open("wb") as file:
        pickle.dump(result, file)
    return result


def timed(run: Callable[[], Any], repeats: int) -> tuple[float, float, Any]:
    """Best wall time (s) of ``repeats`` runs, peak traced memory (MB) of one run, and its result."""
    best = np.inf
    result = None
    for _ in range(repeats):
        start = time.perf_counter()
        result = run()
        best = min(best, time.perf_counter() - start)
    tracemalloc.start()
    run()
    peak = tracemalloc.get_traced_memory()[1] / 1e6
    tracemalloc.stop()
    return best, peak, result


def landed_fit(landed: types.ModuleType, measured_positions: list[SampledPosition], method: FitMethod) -> Any:
    """``fit_measured`` with the landed ``fit_regression``."""
    walls = [m.wall for m in measured_positions if m.wall is not None] if method.wall != "off" else []
    return landed.fit_regression(
        [m.observations for m in measured_positions],
        coupling=method.coupling,
        integration=method.integration,
        basis=method.basis,
        wall_observations=walls,
    )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--before-rev", default="main", help="git revision of the 'before' usdeform.regression")
    parser.add_argument("--cache", type=Path, default=Path("/tmp/usdeform_bench_fit"), help="pickle path prefix")
    parser.add_argument("--repeats", type=int, default=3, help="runs per fit (best time reported)")
    parser.add_argument("--profile", action="store_true", help="profile this tree's fits")
    parser.add_argument("--skip-tracking", action="store_true", help="do not time tracking again")
    args = parser.parse_args()

    recordings = palpations(Path(f"{args.cache}_recordings.pkl"))
    positions = measured(recordings, Path(f"{args.cache}_measured.pkl"))
    n_points = sum(len(m.observations.points_px) for m in positions)
    n_tracked = sum(int(m.observations.valid.sum()) for m in positions)
    n_wall = sum(int(m.wall.valid.sum()) for m in positions if m.wall is not None)
    n_frames = sum(len(r.frames) for r in recordings)
    print(f"4 palpations: {n_frames} frames, {n_points} points, {n_tracked} tracked and {n_wall} wall samples")

    tracking = np.nan
    if not args.skip_tracking:
        tracking, tracking_peak, _ = timed(
            lambda: measure_positions(recordings, FLEXIBLE_LAYER_MM, wall="auto"), repeats=1
        )
        print(f"tracking (measure_positions): {tracking:.2f} s, peak {tracking_peak:.0f} MB")

    landed = landed_module(args.before_rev, "regression")
    print(
        "\n| method | fit before (s) | fit after (s) | speed-up | peak before (MB) | peak after (MB) | fit / tracking |"
    )
    print("|---|---|---|---|---|---|---|")
    fit_times: dict[str, float] = {}
    for name, method in FIT_METHODS.items():
        # Compared in image coordinates (a landed regression may not anchor to the vessel); a
        # vessel-anchored method's own fit is timed after.
        compared = dataclasses.replace(method, anchor="image")
        before, before_peak, old = timed(lambda method=compared: landed_fit(landed, positions, method), args.repeats)
        after, after_peak, new = timed(lambda method=compared: fit_measured(positions, method), args.repeats)
        old_k, new_k = old.model.coefficients, new.model.coefficients
        difference = float(np.abs(old_k - new_k).max() / np.abs(old_k).max())
        anchored, fit_times[name] = "", after
        if method.anchor == "vessel":
            fit_times[name] = timed(lambda method=method: fit_measured(positions, method), args.repeats)[0]
            anchored = f"; anchored to the vessel: {fit_times[name]:.3f} s"
        print(
            f"| {name} | {before:.3f} | {after:.3f} | {before / after:.1f}x | {before_peak:.0f} | {after_peak:.0f} "
            f"| {after / tracking:.3f} |  (image coordinates: coefficients differ by {difference:.1e} relative, "
            f"smoothness {old.smoothness:.3g} -> {new.smoothness:.3g}{anchored})"
        )
    if np.isfinite(tracking):
        for name, after in fit_times.items():
            print(f"fit command with '{name}' (tracking + fit) / tracking: {(tracking + after) / tracking:.3f}")
    if args.profile:
        for name, method in FIT_METHODS.items():
            profiler = cProfile.Profile()
            profiler.enable()
            fit_measured(positions, method)
            profiler.disable()
            print(f"\nprofile of this tree's '{name}' fit (cumulative time):")
            pstats.Stats(profiler).sort_stats("cumulative").print_stats(18)


if __name__ == "__main__":
    main()
