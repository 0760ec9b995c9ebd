"""Vessel-wall benchmark: how well each fit undoes the vessel's collapse at the highest force.

Usage: ``python benches/bench_wall.py [--before-rev main] [--output results.json] [--cache DIR] [--only M ...]``

Per phantom (the compliant vessel, which loses about a third of its lumen area at 17 N; the stiff
and the soft presets) the model is fitted on two simulated 50-frame 256 x 256 palpations at the
fitting position and corrects, at the highest force, a third palpation there ("fitted") and
palpations at two other positions with only their own stiffness ("other"). "soft (propagation)"
corrects the soft phantom at 8 N with the stiff phantom's models (the paper's unseen-tissue case).
Dice and area error compare the vessel segmented in the corrected frame with the vessel segmented
in the simulator's zero-force frame (``usdeform.experiments.paper_2d``'s evaluation).

Methods: "paper" and "spline 8x8" are today's fits, fitted by ``usdeform.regression`` at ``--before-rev``
(read with git) in the same process; the others are this tree's options: "+ wall" adds the vessel
wall's displacements (``usdeform.fitting``) as constraints of weight 1, "lambda" integrates over
probe displacement (``integration="displacement"``) instead of force, "vessel-anchored" adds the
part that follows the lumen (``anchor="vessel"``: corrected on the lumen found in each frame), and
the B-spline smoothness is chosen by the spatial-region cross-validation. FEM solutions are cached in ~/.cache/usdeform;
``--cache`` keeps the simulated, tracked palpations for reruns (the wall is measured again each run).
Each vessel-anchored model's correction is timed per frame on a whole palpation after the table.
"""

from __future__ import annotations

import argparse
import copyreg
import json
import pickle
import sys
import time
import types
from collections.abc import Callable
from dataclasses import replace
from pathlib import Path
from types import ModuleType
from typing import Any

import numpy as np

from landed import landed_module
from usdeform.correction import correct_frames
from usdeform.experiments.paper_2d import Palpated, Paper2dConfig, evaluate, palpate
from usdeform.fitting import measure_wall
from usdeform.metrics import area_mm2, pixel_size_mm
from usdeform.regression import fit_regression
from usdeform.sim import Phantom, compliant_vessel_phantom, soft_phantom, stiff_phantom


# Tracks keep their rejection counts in a read-only mapping, which pickle cannot store: as a dict.
def _read_only(mapping: dict) -> types.MappingProxyType:
    return types.MappingProxyType(mapping)


copyreg.pickle(types.MappingProxyType, lambda proxy: (_read_only, (dict(proxy),)))

CONFIG = Paper2dConfig()  # 256 x 256 frames, 50-frame palpations
#: phantom, maximum palpation force (N), fitting position and two other positions (mm)
PHANTOMS: tuple[tuple[str, Callable[[], Phantom], float, float, tuple[float, float]], ...] = (
    ("compliant", compliant_vessel_phantom, 17.0, 10.0, (35.0, 60.0)),
    ("stiff", stiff_phantom, 30.0, 10.0, (40.0, 70.0)),
    ("soft", soft_phantom, 16.0, 10.0, (35.0, 60.0)),
)
PROPAGATION_FORCE_N = 8.0  # the soft phantom corrected by the stiff phantom's models (paper experiment 3)


def methods(landed: ModuleType) -> dict[str, Callable[[list[Palpated]], Any]]:
    """Name -> fit of a list of palpations, returning a RegressionFit."""

    def tracks(palpations: list[Palpated]) -> list:
        return [p.sampled.observations for p in palpations]

    def walls(palpations: list[Palpated]) -> list:
        return [p.sampled.wall for p in palpations if p.sampled.wall is not None]

    def ours(*, wall: bool = False, **options: Any) -> Callable[[list[Palpated]], Any]:
        def fit(palpations: list[Palpated]) -> Any:
            return fit_regression(tracks(palpations), wall_observations=walls(palpations) if wall else None, **options)

        return fit

    return {
        "paper": lambda palpations: landed.fit_regression(tracks(palpations)),
        "spline 8x8": lambda palpations: landed.fit_regression(tracks(palpations), basis=("bspline", 8, 8)),
        "paper + wall": ours(wall=True),
        "spline 8x8 + wall": ours(basis=("bspline", 8, 8), wall=True),
        "spline 16x16": ours(basis=("bspline", 16, 16)),
        "spline 12x12 + wall": ours(basis=("bspline", 12, 12), wall=True),
        "spline 16x16 + wall": ours(basis=("bspline", 16, 16), wall=True),
        "spline 8x8 + wall, lambda": ours(basis=("bspline", 8, 8), wall=True, integration="displacement"),
        "spline 12x12 + wall, lambda": ours(basis=("bspline", 12, 12), wall=True, integration="displacement"),
        "spline 16x16 + wall, lambda": ours(basis=("bspline", 16, 16), wall=True, integration="displacement"),
        "spline 8x8 + wall, lambda, vessel-anchored": ours(
            basis=("bspline", 8, 8), wall=True, integration="displacement", anchor="vessel"
        ),
        "spline 6x6 + wall, lambda, vessel-anchored": ours(
            basis=("bspline", 6, 6), wall=True, integration="displacement", anchor="vessel"
        ),
        "spline 12x12 + wall, lambda, vessel-anchored": ours(
            basis=("bspline", 12, 12), wall=True, integration="displacement", anchor="vessel"
        ),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--before-rev", default="main", help="git revision of today's usdeform.regression")
    parser.add_argument("--output", type=Path, help="write the rows as JSON here")
    parser.add_argument("--only", nargs="*", help="run only these methods")
    parser.add_argument("--cache", type=Path, help="keep the simulated, tracked palpations here (pickle) for reruns")
    args = parser.parse_args()
    fits = methods(landed_module(args.before_rev, "regression"))
    if args.only:
        fits = {name: fit for name, fit in fits.items() if name in args.only}
    rows: list[dict[str, Any]] = []
    models_by_phantom: dict[str, dict[str, Any]] = {}
    palpations_by_phantom: dict[str, list[tuple[str, float, Palpated]]] = {}
    for name, preset, max_force, fit_position, others in PHANTOMS:
        phantom = preset()
        start = time.perf_counter()
        cached = args.cache / f"{name}.pickle" if args.cache else None
        if cached is not None and cached.exists():
            # Simulated and tracked before: the wall is measured again, by this tree's tracker.
            fitted, evaluated = pickle.loads(cached.read_bytes())
            fitted = [_with_wall_measured(p) for p in fitted]
            evaluated = [(case, position, _with_wall_measured(p)) for case, position, p in evaluated]
            evaluated[0] = ("fitted", fit_position, fitted[2])
        else:
            fitted = [palpate(phantom, fit_position, max_force, CONFIG.seed + i, CONFIG) for i in range(3)]
            evaluated = [("fitted", fit_position, fitted[2])] + [
                ("other", position, palpate(phantom, position, max_force, CONFIG.seed + 10 + n, CONFIG))
                for n, position in enumerate(others)
            ]
            if cached is not None:
                cached.parent.mkdir(parents=True, exist_ok=True)
                cached.write_bytes(pickle.dumps((fitted, evaluated)))
        print(f"{name}: simulated and tracked in {time.perf_counter() - start:.0f} s", file=sys.stderr)
        models = {}
        for method, fit in fits.items():
            start = time.perf_counter()
            result = fit(fitted[:2])
            # Today's fits (read from --before-rev) name the model .model; this tree's fits .fitted.
            models[method] = result.fitted if hasattr(result, "fitted") else result.model
            print(
                f"  {method}: fitted in {time.perf_counter() - start:.1f} s, smoothness {result.smoothness:.3g}",
                file=sys.stderr,
            )
            rows.append({"phantom": name, "case": "fit", "method": method, "smoothness": result.smoothness})
        models_by_phantom[name] = models
        palpations_by_phantom[name] = evaluated
        for case, position, palpated in evaluated:
            result_case, _, masks = evaluate(case, name, position, max_force, palpated, models)
            for method in ("deformed", *models):
                rows.append(_row(name, case, position, result_case, method, palpated, masks["reference"]))
    for _case, position, palpated in palpations_by_phantom["soft"]:
        result_case, _, masks = evaluate(
            "propagation", "soft", position, PROPAGATION_FORCE_N, palpated, models_by_phantom["stiff"]
        )
        for method in ("deformed", *models_by_phantom["stiff"]):
            rows.append(
                _row("soft (propagation)", "other", position, result_case, method, palpated, masks["reference"])
            )
    _print_table(rows)
    _print_correction_times(models_by_phantom["compliant"], palpations_by_phantom["compliant"])
    if args.output:
        args.output.write_text(json.dumps(rows, indent=1))


def _print_correction_times(models: dict[str, Any], evaluated: list[tuple[str, float, Palpated]]) -> None:
    """Time per frame of each vessel-anchored model's correction of a whole palpation (its lumen searched
    frame by frame) against the compiled warp of its image part alone: best of three runs."""
    _, _, palpated = evaluated[1]
    frames, forces, profile = palpated.recording.frames, palpated.force, palpated.sampled.observations.profile
    for method, model in models.items():
        if model.anchor != "vessel":
            continue
        times = [
            min(_seconds(lambda m=m: correct_frames(frames, forces, profile, m)) for _ in range(3)) / len(frames)
            for m in (model, model.image_model)
        ]
        print(
            f"{method}: corrected at {1e3 * times[0]:.2f} ms per {frames.shape[1]} x {frames.shape[2]} frame "
            f"({len(frames)} frames of the compliant phantom at another position); its image part alone, "
            f"compiled: {1e3 * times[1]:.2f} ms"
        )


def _seconds(run: Callable[[], object]) -> float:
    start = time.perf_counter()
    run()
    return time.perf_counter() - start


def _with_wall_measured(palpated: Palpated) -> Palpated:
    wall, note = measure_wall(palpated.recording, palpated.sampled.tracked, palpated.sampled.stiffness)
    observations = replace(palpated.sampled.observations, vessel=wall.vessel if wall is not None else None)
    return replace(palpated, sampled=replace(palpated.sampled, observations=observations, wall=wall, wall_note=note))


def _row(
    phantom: str, case: str, position: float, result: Any, method: str, palpated: Palpated, reference: np.ndarray
) -> dict[str, Any]:
    """One evaluated method; the area error relative to the vessel segmented at zero force."""
    reference_area = area_mm2(reference, pixel_size_mm(palpated.recording.image_to_probe))
    return {
        "phantom": phantom,
        "case": case,
        "position_mm": position,
        "force_n": result.force_n,
        "method": method,
        "dice": result.dice[method],
        "area_error_percent": 100 * result.area_error_mm2[method] / reference_area,
    }


def _print_table(rows: list[dict[str, Any]]) -> None:
    """Per phantom, case and method: the worst Dice and the largest |area error| over the positions."""
    evaluated = [row for row in rows if row["case"] != "fit"]
    phantoms = list(dict.fromkeys(row["phantom"] for row in evaluated))
    methods = list(dict.fromkeys(row["method"] for row in evaluated))
    print("| phantom | case | " + " | ".join(methods) + " |")
    print("|---|---|" + "---|" * len(methods))
    for phantom in phantoms:
        for case in ("fitted", "other"):
            cells = []
            for method in methods:
                chosen = [r for r in evaluated if (r["phantom"], r["case"], r["method"]) == (phantom, case, method)]
                if not chosen:
                    cells.append("")
                    continue
                worst_dice = min(r["dice"] for r in chosen)
                worst_area = max((r["area_error_percent"] for r in chosen), key=abs)
                cells.append(f"{worst_dice:.3f} / {worst_area:+.1f} %")
            if any(cells):
                print(f"| {phantom} | {case} | " + " | ".join(cells) + " |")
    print("\nCells: worst Dice / largest area error (corrected minus zero force) over the positions of the case.")
    fits = [row for row in rows if row["case"] == "fit"]
    print("Chosen smoothness: " + "; ".join(f"{r['phantom']} {r['method']}: {r['smoothness']:.3g}" for r in fits))


if __name__ == "__main__":
    main()
