"""``usdeform compensation-benchmark``: what a recording-level effect costs the corrected volume, and how much
``--compensate`` gives back (issue 42).

Each case simulates two load-hold-unload palpations (at two positions along the phantom) and a force-controlled sweep
between them (its force wandering about the target as a robot's does) with its ground truth
(:class:`BenchmarkSettings`), with a withheld effect drawn as the gap benchmark draws it
(:func:`usdeform.gap.benchmark.draw_effect`: image latency, force-sensor bias, drift and weight, viscoelasticity or
sound-speed mismatch), or none (null cases). The model is fitted and the sweep corrected as
``usdeform fit`` and ``usdeform correct`` do (:func:`~usdeform.fitting.fit_palpations`,
:func:`~usdeform.reconstruction.correct_recording`), under four conditions:

* ``a`` the effect, no compensation;
* ``b`` compensated with the diagnosis's own fitted effect: :func:`usdeform.gap.diagnose` runs blind on the two
  palpations, its ``diagnosis.json`` is read with :func:`~usdeform.compensation.compensation_option` and applied
  with :func:`~usdeform.compensation.apply_compensation`, as ``--compensate`` does; a refused compensation is
  reported and scores as ``a``;
* ``c`` compensated with the true parameters (a :class:`~usdeform.compensation.Compensation` of the drawn effect);
* ``d`` the same case without the effect (same seeds);
* ``e`` compensated with the diagnosis's own fitted effect whatever its verdict, as ``--force-compensation`` does
  (:func:`~usdeform.compensation.forced_compensation`: both effects of an ambiguous verdict, the best-fitting one
  where none is named; ``b`` where ``b`` was applied; ``a`` where even forcing applies nothing, an effect of the
  tissue): what the diagnosis's fitted sizes give back, apart from its gate.

The sweep's true lumen masks are warped as its frames are corrected (:func:`~usdeform.correction.correct_like`) and
scored against the zero-force lumen, frame by frame where the lumen is in view: Dice (pixels), area error (% of
the true area) and centre-line depth error (mm, the lumen centroid's depth). Areas and depths of the truth use the
true pixel size (:func:`_true_pixel_mm`); those of a corrected sweep its own ``image_to_probe``, so an uncompensated
sound-speed mismatch shows in mm. Frames a latency compensation drops are left out of its scores.

Scoring (:func:`case_scores`, :func:`summarise`): a metric's goodness is Dice, minus the area error, minus the
depth error; the cost of the effect is goodness(d) - goodness(a) and the recovered share
(goodness(b) - goodness(a)) / cost (``c``: the same with the true parameters; ``e``: forced). A case is costly when
the effect costs at least :data:`MIN_DICE_COST` Dice or :data:`MIN_AREA_COST_PCT` % area; the share of a metric
is the median over the costly cases whose cost in that metric reaches its own threshold (:data:`SHARE_THRESHOLDS`).
Null cases must come out bit for bit unchanged when compensated (corrected frames, validity and poses).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import time
import warnings
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from tqdm import tqdm

from ._files import check_output_folder
from .compensation import (
    MIN_AREA_COST_PCT,
    MIN_DICE_COST,
    Compensation,
    apply_compensation,
    compensation_option,
    forced_compensation,
)
from .correction import correct_like
from .errors import InputError, UsdeformError
from .fitting import fit_palpations
from .gap import diagnose
from .gap.benchmark import draw_effect
from .gap.diagnosis import check_seed
from .gap.report import write_text
from .metrics import area_mm2, centroid_mm, dice, pixel_size_mm
from .reconstruction import correct_recording, stiffness_source_for, sweep_profiles
from .recording import Recording
from .sim import (
    ForceController,
    GroundTruth,
    ImagingSettings,
    Phantom,
    coarse_phantom,
    simulate_palpation,
    simulate_sweep,
)
from .sim.effects import Effect
from .validation import ForceClampWarning, forces_in_range

__all__ = [
    "CONDITIONS",
    "EFFECT_TYPES",
    "BenchmarkSettings",
    "add_compensation_benchmark_command",
    "case_scores",
    "markdown_report",
    "run_compensation_benchmark",
    "summarise",
    "true_compensation",
]

#: The withheld effects, in the order the cases cycle through them (then a null case).
EFFECT_TYPES = ("image_latency", "force_sensor_error", "viscoelasticity", "sound_speed_mismatch")
_ROUND: tuple[str | None, ...] = (*EFFECT_TYPES, None)
#: The conditions: the effect uncompensated, compensated by the diagnosis, by the true parameters, no effect.
CONDITIONS = {"a": "effect", "b": "diagnosed", "c": "true", "d": "no effect", "e": "diagnosed, forced"}
METRICS = ("dice", "area_error_pct", "depth_error_mm")
_SIGN = {"dice": 1.0, "area_error_pct": -1.0, "depth_error_mm": -1.0}  # goodness = sign * value
#: A metric's share counts in a costly case when the effect costs at least this much of it.
SHARE_THRESHOLDS = {"dice": MIN_DICE_COST, "area_error_pct": MIN_AREA_COST_PCT, "depth_error_mm": 0.1}
MAX_WORSENING_DICE = 0.005  # compensation should never make a case worse by more than this
#: The sweep's force loop: a 0.8 N oscillation at 0.3 Hz and 0.25 N rms of 4 Hz ripple about the target.
ROBOT_FORCE_LOOP = ForceController(oscillation_n=0.8, tracking_ripple_n=0.25)


@dataclass(frozen=True)
class BenchmarkSettings:
    """What each case simulates on the coarse phantom (:func:`_phantom`): frame size (pixels),
    frames per palpation and sweep, palpation positions (mm along the phantom; the sweep runs from the first to the
    last), the palpations' highest force and the sweep's force (N), the hold at the top (s), and the diagnosis's
    worker processes. The sweep records every ``sweep_frame_step``-th frame of the 50 fps stream (5: 30 mm in 4 s,
    7.5 mm/s, a robot's sweep speed) under ``sweep_controller``, a force loop that holds its target within about
    +/-1.2 N as robots do (the robot sweeps of :mod:`usdeform.experiments.paper_3d`), so that a frame paired with
    the force of another time shows in the corrected sweep."""

    frame_size: int = 128
    palpation_frames: int = 60
    sweep_frames: int = 40
    positions_mm: tuple[float, float] = (15.0, 45.0)
    palpation_force_n: float = 10.0
    sweep_force_n: float = 5.0
    hold_s: float = 3.0
    workers: int = 1
    sweep_frame_step: int = 5
    sweep_controller: ForceController = ROBOT_FORCE_LOOP

    def check(self) -> None:
        """InputError naming the first setting out of range."""
        for name, low in (
            ("frame_size", 64),
            ("palpation_frames", 20),
            ("sweep_frames", 4),
            ("workers", 1),
            ("sweep_frame_step", 1),
        ):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int) or value < low:
                raise InputError(f"{name}: expected an integer >= {low}, got {value!r}")


def true_compensation(effect: str | None, parameters: dict[str, float]) -> Compensation:
    """The :class:`Compensation` of a drawn effect's true parameters (as :func:`usdeform.gap.benchmark.draw_effect`
    names them); no effect: an empty one, which changes nothing."""
    effects: dict[str, dict[str, float]] = {}
    if effect == "image_latency":
        effects[effect] = {"delay_s": parameters["delay_s"]}
    elif effect == "force_sensor_error":
        offset = parameters["bias_n"] - parameters["uncompensated_weight_n"]
        effects[effect] = {"offset_n": offset, "drift_n_per_s": parameters["drift_n_per_s"]}
    elif effect == "viscoelasticity":
        effects[effect] = {"g": parameters["g"], "tau_s": parameters["tau_s"]}
    elif effect == "sound_speed_mismatch":
        effects[effect] = {"error_m_s": parameters["error_m_s"]}
    elif effect is not None:
        raise InputError(f"effect: expected one of {', '.join(EFFECT_TYPES)} or None, got {effect!r}")
    return Compensation("true parameters", "true", effects, {}, False)


def _phantom() -> Phantom:
    """The coarse phantom (:func:`usdeform.sim.coarse_phantom`), solved to 14 mm of probe displacement instead of 8,
    so that creep under a hold or a sensor error that presses harder stays in range (10 N: up to ~10 mm)."""
    return dataclasses.replace(coarse_phantom(), max_probe_displacement_mm=14.0, n_probe_steps=8)


@dataclass(frozen=True)
class _Case:
    index: int
    effect: str | None
    parameters: dict[str, float]
    effects: tuple[Effect, ...]  # the simulator's effect objects
    seeds: tuple[int, int, int]  # palpation 1, palpation 2, sweep
    diagnosis_seed: int


def _draw_case(
    index: int, effect: str | None, rng: np.random.Generator, diagnosis_seed: int, settings: BenchmarkSettings
) -> _Case:

    phantom = _phantom()
    duration_s = 2 * settings.palpation_force_n / 5.0 + settings.hold_s  # palpation at the default 5 N/s
    effects: tuple[Effect, ...] = ()
    parameters: dict[str, float] = {}
    if effect is not None:
        drawn, parameters, _ = draw_effect(effect, rng, phantom.base_section.shear_modulus_kpa, duration_s)
        effects = (drawn,)
    seeds = tuple(int(s) for s in rng.integers(0, 2**31, 3))
    return _Case(index, effect, parameters, effects, seeds, diagnosis_seed)  # type: ignore[arg-type]


def _simulate(case: _Case, settings: BenchmarkSettings, with_effect: bool) -> tuple[list[Recording], Recording, Any]:
    """The case's two palpations and its sweep with ground truth (``with_effect``: the drawn effect)."""
    phantom, size = _phantom(), settings.frame_size
    effects = list(case.effects) if with_effect else None
    palpations = [
        simulate_palpation(
            phantom,
            position,
            settings.palpation_force_n,
            settings.palpation_frames,
            "up-hold-down",
            seed,
            effects,
            size,
            size,
            hold_s=settings.hold_s,
        )[0]
        for position, seed in zip(settings.positions_mm, case.seeds[:2], strict=True)
    ]
    start, end = settings.positions_mm
    sweep, truth = simulate_sweep(
        phantom,
        start,
        end - start,
        settings.sweep_force_n,
        settings.sweep_frames,
        case.seeds[2],
        effects,
        size,
        size,
        controller=settings.sweep_controller,
        frame_step=settings.sweep_frame_step,
    )
    return palpations, sweep, truth


def _score_masks(
    masks: np.ndarray, references: np.ndarray, pixel: tuple[float, float], true_pixel: tuple[float, float]
) -> dict[str, float]:
    """Mean Dice, area error (% of the true area) and centroid depth error (mm) over the frames whose true lumen
    is in view (an empty corrected lumen: Dice 0, area error 100 %, no depth)."""
    dices, areas, depths = [], [], []
    for mask, reference in zip(masks, references, strict=True):
        if not reference.any():
            continue
        true_area = area_mm2(reference, true_pixel)
        if not mask.any():
            dices.append(0.0)
            areas.append(100.0)
            continue
        dices.append(dice(mask, reference))
        areas.append(100.0 * abs(area_mm2(mask, pixel) - true_area) / true_area)
        depths.append(abs(centroid_mm(mask, pixel)[1] - centroid_mm(reference, true_pixel)[1]))
    mean = lambda values: float(np.mean(values)) if values else math.nan  # noqa: E731
    return {"dice": mean(dices), "area_error_pct": mean(areas), "depth_error_mm": mean(depths), "frames": len(dices)}


def _true_pixel_mm(case: _Case, clean_sweep: Recording) -> tuple[float, float]:
    """(lateral, axial) mm of a pixel of the case's truth masks with the effect: the scanner's calibration, the axial
    size scaled by true / assumed sound speed in a sound-speed case (the simulator displays depths scaled by
    assumed / true speed, the truth masks too)."""
    lateral, axial = pixel_size_mm(clean_sweep.image_to_probe)
    if case.effect == "sound_speed_mismatch":
        assumed = ImagingSettings().assumed_sound_speed_m_s
        axial *= (assumed + case.parameters["error_m_s"]) / assumed
    return lateral, axial


def _run_condition(
    palpations: list[Recording],
    sweep: Recording,
    truth: GroundTruth,
    compensation: Compensation | None,
    true_pixel: tuple[float, float],
    flexible_layer_mm: float,
) -> tuple[dict[str, Any], tuple[np.ndarray | None, ...]]:
    """Fit and correct as ``usdeform fit/correct [--compensate]`` do; the scores (with frames clamped and any
    error) and the corrected sweep's frames, validity and poses (for the bit-for-bit check)."""
    try:
        names = [f"palpation {number + 1}" for number in range(len(palpations))]
        fitted = fit_palpations(palpations, flexible_layer_mm, names=names, compensation=compensation)
        model = fitted.fit.fitted
        recording, _ = apply_compensation(compensation, sweep, "sweep")
        kept = np.searchsorted(sweep.timestamps, recording.timestamps)  # frames a re-pairing kept
        assert recording.force is not None  # a simulated sweep records its force
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", ForceClampWarning)
            corrected = correct_recording(recording, model, fitted.sampled, clamp_force=True)
            forces = forces_in_range(recording.force, model.normalization.force_scale, clamp=True)
        profiles = sweep_profiles(recording, fitted.sampled, stiffness_source=stiffness_source_for(recording))
        lumens = truth.vessel_mask[kept].astype(np.uint8) * 255
        masks = correct_like(lumens, recording.frames, forces, profiles, model) >= 128
    except UsdeformError as error:  # a refused fit or correction is an outcome to report
        return {**dict.fromkeys(METRICS, math.nan), "frames": 0, "error": str(error)}, ()
    scores = _score_masks(
        masks, truth.zero_force_vessel_mask[kept], pixel_size_mm(recording.image_to_probe), true_pixel
    )
    scores["clamped_frames"] = int(np.count_nonzero(forces != recording.force))
    return scores, (corrected.frames, corrected.pixel_valid, corrected.probe_to_base)


def _diagnosed(case: _Case, palpations: list[Recording], directory: Path, workers: int) -> tuple[Any, Any, str, str]:
    """The diagnosis (blind, on the palpations) written to ``directory/diagnosis.json``; the compensation
    ``--compensate`` reads from it (None when refused) and the one ``--force-compensation`` reads (None where even
    forcing applies nothing), its verdict and the refusal (or "")."""

    try:
        result = diagnose(palpations, seed=case.diagnosis_seed, progress=False, workers=workers).to_json()
    except UsdeformError as error:  # a failed diagnosis is refused, as its file would be
        result = {"verdict": f"error: {error}", "named": [], "effects": [], "measures": []}
    path = directory / "diagnosis.json"
    path.write_text(json.dumps(result, indent=1), encoding="utf-8")
    verdict = str(result.get("verdict"))
    forced = forced_compensation(result, str(path))
    try:
        return compensation_option(path, False), forced, verdict, ""
    except InputError as error:
        return None, forced, verdict, str(error)


def _identical(x: np.ndarray | None, y: np.ndarray | None) -> bool:
    """Both None, or equal arrays of one dtype and shape, bit for bit."""
    if x is None or y is None:
        return x is y
    return x.dtype == y.dtype and x.shape == y.shape and x.tobytes() == y.tobytes()


def _run_case(case: _Case, settings: BenchmarkSettings, directory: Path) -> dict[str, Any]:
    """One case's four conditions, scores and null check (a JSON row)."""
    start = time.perf_counter()
    directory.mkdir(parents=True, exist_ok=True)
    flexible_layer_mm = _phantom().base_section.depth_mm
    scores: dict[str, dict[str, Any]] = {}
    arrays: dict[str, tuple[np.ndarray | None, ...]] = {}
    diagnosed, forced, verdict, refusal, diagnosis_s = None, None, "-", "", 0.0
    try:
        palpations, sweep, truth = _simulate(case, settings, with_effect=True)
        clean = (palpations, sweep, truth) if case.effect is None else _simulate(case, settings, with_effect=False)
    except UsdeformError as error:  # e.g. a probe pressed past the phantom's solved range: reported, not scored
        failed = {**dict.fromkeys(METRICS, math.nan), "frames": 0, "error": f"simulation: {error}"}
        scores = dict.fromkeys(CONDITIONS, failed)
    else:
        true_pixel = _true_pixel_mm(case, clean[1])
        diagnosis_start = time.perf_counter()
        diagnosed, forced, verdict, refusal = _diagnosed(case, palpations, directory, settings.workers)
        diagnosis_s = time.perf_counter() - diagnosis_start
        scores["a"], arrays["a"] = _run_condition(palpations, sweep, truth, None, true_pixel, flexible_layer_mm)
        if diagnosed is None:
            scores["b"], arrays["b"] = scores["a"], arrays["a"]
        else:
            scores["b"], arrays["b"] = _run_condition(
                palpations, sweep, truth, diagnosed, true_pixel, flexible_layer_mm
            )
        if forced is None:
            scores["e"] = scores["a"]
        elif diagnosed is not None:  # applied under (b) already: the same compensation
            scores["e"] = scores["b"]
        else:
            scores["e"], _ = _run_condition(palpations, sweep, truth, forced, true_pixel, flexible_layer_mm)
        truly = true_compensation(case.effect, case.parameters)
        scores["c"], arrays["c"] = _run_condition(palpations, sweep, truth, truly, true_pixel, flexible_layer_mm)
        clean_pixel = pixel_size_mm(clean[1].image_to_probe)  # without the effect, the truth is imaged as displayed
        scores["d"], _ = _run_condition(*clean, None, clean_pixel, flexible_layer_mm)
    row: dict[str, Any] = {
        "case": case.index,
        "effect": case.effect or "none",
        "parameters": case.parameters,
        "verdict": verdict,
        "named": [] if diagnosed is None else sorted(diagnosed.effects),
        "diagnosed_parameters": None if forced is None else forced.effects,
        "compensation": "applied" if diagnosed is not None else "refused" if verdict != "-" else "not run",
        "refusal": refusal,
        "scores": scores,
        **case_scores(scores),
    }
    if case.effect is None:  # compensated null cases must come out bit for bit unchanged
        row["unchanged"] = {
            condition: bool(arrays.get("a"))
            and len(arrays[condition]) == len(arrays["a"])
            and all(_identical(x, y) for x, y in zip(arrays[condition], arrays["a"], strict=True))
            for condition in ("b", "c")
        }
    row["diagnosis_s"] = diagnosis_s
    row["total_s"] = time.perf_counter() - start
    return row


def case_scores(scores: dict[str, dict[str, Any]]) -> dict[str, Any]:
    """A case's cost of the effect per metric (goodness(d) - goodness(a), module docstring), the shares the
    diagnosed (``recovered``), true (``recovered_true``) and forced diagnosed (``recovered_forced``) compensations
    recover (None where the metric costs nothing), whether it is costly, and whether the diagnosed compensation
    (``worse``) or the forced one (``worse_forced``) made Dice worse by more than :data:`MAX_WORSENING_DICE`."""
    good = {c: {m: _SIGN[m] * scores[c][m] for m in METRICS} for c in CONDITIONS}
    cost = {m: good["d"][m] - good["a"][m] for m in METRICS}

    def share(condition: str) -> dict[str, float | None]:
        return {
            m: (good[condition][m] - good["a"][m]) / cost[m] if math.isfinite(cost[m]) and cost[m] != 0 else None
            for m in METRICS
        }

    return {
        "cost": cost,
        "recovered": share("b"),
        "recovered_true": share("c"),
        "recovered_forced": share("e"),
        "costly": bool(cost["dice"] >= MIN_DICE_COST or cost["area_error_pct"] >= MIN_AREA_COST_PCT),
        "worse": bool(scores["b"]["dice"] < scores["a"]["dice"] - MAX_WORSENING_DICE),
        "worse_forced": bool(scores["e"]["dice"] < scores["a"]["dice"] - MAX_WORSENING_DICE),
    }


def _median(values: list[float]) -> float | None:
    finite = [v for v in values if v is not None and math.isfinite(v)]
    return float(np.median(finite)) if finite else None


def summarise(rows: list[dict[str, Any]]) -> dict[str, Any]:
    """Per effect type (and ``none``): cases, costly cases, the median cost per metric over all its cases, the
    median recovered shares (diagnosed and true) over the costly cases (module docstring), refusals and cases made
    worse; for null cases, how many came out unchanged bit for bit."""
    summary: dict[str, Any] = {"cases": len(rows), "effects": {}}
    for effect in (*EFFECT_TYPES, "none"):
        chosen = [row for row in rows if row["effect"] == effect]
        if not chosen:
            continue
        costly = [row for row in chosen if row["costly"]]
        entry: dict[str, Any] = {
            "cases": len(chosen),
            "costly": len(costly),
            "cost": {m: _median([row["cost"][m] for row in chosen]) for m in METRICS},
            "refused": sum(row["compensation"] == "refused" for row in chosen),
            "worse": sum(row["worse"] for row in chosen),
            "worse_forced": sum(row["worse_forced"] for row in chosen),
        }
        for key in ("recovered", "recovered_true", "recovered_forced"):
            entry[key] = {
                m: _median([row[key][m] for row in costly if row["cost"][m] >= SHARE_THRESHOLDS[m]]) for m in METRICS
            }
        if effect == "none":
            entry["unchanged"] = {c: sum(row.get("unchanged", {}).get(c, False) for row in chosen) for c in ("b", "c")}
        summary["effects"][effect] = entry
    return summary


def _number(value: float | None, digits: int = 3) -> str:
    return "-" if value is None or not math.isfinite(value) else f"{value:.{digits}f}"


def _share(value: float | None) -> str:
    return "-" if value is None else f"{100 * value:.0f} %"


def markdown_report(summary: dict[str, Any], rows: list[dict[str, Any]], command: str, seconds: float) -> str:
    """``benchmark.md``: the table per effect type, the null check and the table per case."""
    lines = [
        "# Compensation benchmark",
        "",
        f"`{command}`: {summary['cases']} cases in {seconds / 60:.1f} min.",
        "",
        "Cost: the effect's median cost (no effect minus effect) in Dice, area error (% points) and centre-line "
        "depth error (mm), over all cases. Recovered: median share ((b) - (a)) / ((d) - (a)) over the cases where "
        f"the effect costs >= {MIN_DICE_COST} Dice or {MIN_AREA_COST_PCT:g} % area (and that metric's own threshold), "
        "with the diagnosis's fitted effect (b), with the true parameters (c) and with the diagnosis's fitted effect "
        "forced whatever its verdict (e).",
        "",
        "| effect | cases | costly | cost Dice | cost area % | cost depth mm | recovered Dice / area / depth (b) "
        f"| with true parameters (c) | forced (e) | refused | worse by > {MAX_WORSENING_DICE} Dice (b / e) |",
        "|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for effect, entry in summary["effects"].items():
        cost = entry["cost"]
        shares = [
            " / ".join(_share(entry[key][m]) for m in METRICS)
            for key in ("recovered", "recovered_true", "recovered_forced")
        ]
        lines.append(
            f"| {effect} | {entry['cases']} | {entry['costly']} | {_number(cost['dice'])} | "
            f"{_number(cost['area_error_pct'], 1)} | {_number(cost['depth_error_mm'], 2)} | {shares[0]} | "
            f"{shares[1]} | {shares[2]} | {entry['refused']} | {entry['worse']} / {entry['worse_forced']} |"
        )
    null = summary["effects"].get("none")
    if null:
        lines += [
            "",
            f"Null cases unchanged bit for bit when compensated: {null['unchanged']['b']} of {null['cases']} with the "
            f"diagnosis (a refused compensation counts as unchanged), {null['unchanged']['c']} of {null['cases']} "
            "with the (empty) true compensation.",
        ]
    lines += [
        "",
        "## Cases",
        "",
        "Dice, area error % and depth error mm under (a) effect / (b) diagnosed / (c) true / (d) no effect / "
        "(e) diagnosed, forced.",
        "",
        "| case | effect | parameters | verdict | compensation | Dice | area % | depth mm | s |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for row in rows:
        parameters = ", ".join(f"{k} {v:.3g}" for k, v in row["parameters"].items()) or "-"
        values = {
            m: " / ".join(_number(row["scores"][c][m], 3 if m == "dice" else 2) for c in CONDITIONS) for m in METRICS
        }
        errors = [f"{c}: {row['scores'][c]['error']}" for c in CONDITIONS if row["scores"][c].get("error")]
        compensation = row["compensation"] + (f" ({', '.join(row['named'])})" if row["named"] else "")
        lines.append(
            f"| {row['case']} | {row['effect']} | {parameters} | {row['verdict']} | {compensation} | "
            f"{values['dice']} | {values['area_error_pct']} | {values['depth_error_mm']} | {row['total_s']:.0f} |"
            + ("" if not errors else " " + "; ".join(errors))
        )
    return "\n".join(lines) + "\n"


def _json(value: Any, indent: int | None = None) -> str:
    """Strict JSON: NumPy scalars as numbers, NaN (a metric of a refused fit) as null."""

    def plain(item: Any) -> Any:
        if isinstance(item, dict):
            return {key: plain(entry) for key, entry in item.items()}
        if isinstance(item, list | tuple):
            return [plain(entry) for entry in item]
        if isinstance(item, np.integer | np.floating):
            item = item.item()
        return None if isinstance(item, float) and not math.isfinite(item) else item

    return json.dumps(plain(value), indent=indent, allow_nan=False)


def run_compensation_benchmark(
    n_cases: int,
    seed: int,
    out: str | Path,
    *,
    settings: BenchmarkSettings = BenchmarkSettings(),
    effects: Sequence[str | None] = _ROUND,
    progress: bool = True,
    command: str = "",
) -> dict[str, Any]:
    """Run ``n_cases`` cases (module docstring) and write ``out/cases.jsonl`` (a line per finished case),
    ``out/benchmark.json`` and ``out/benchmark.md``, each case's ``diagnosis.json`` in ``out/case_NNN``.
    Returns the summary (:func:`summarise`). Case ``i`` withholds ``effects[i % len(effects)]`` (an ID of
    :data:`EFFECT_TYPES` or None; default: each in turn, then none) and depends on ``seed``, ``i`` and that alone.

    Raises InputError before any work for a ``n_cases`` below 1, a negative seed, bad settings, an ``out`` that
    is an existing file or a ``cases.jsonl`` there that already holds cases. Call it under
    ``if __name__ == "__main__":`` in scripts: the diagnosis starts processes."""

    if isinstance(n_cases, bool) or not isinstance(n_cases, int | np.integer) or n_cases < 1:
        raise InputError(f"--cases: expected a positive integer, got {n_cases!r}")
    seed = check_seed(seed, "--seed")
    settings.check()
    unknown = [effect for effect in effects if effect is not None and effect not in EFFECT_TYPES]
    if not effects or unknown:
        raise InputError(f"effects: expected IDs of {', '.join(EFFECT_TYPES)} or None, got {list(effects)!r}")
    out = check_output_folder(out, "--out")
    log = out / "cases.jsonl"
    if log.exists() and log.read_text().strip():
        raise InputError(f"--out: {log} already holds cases; choose another folder")
    out.mkdir(parents=True, exist_ok=True)
    log.write_text("")
    command = command or f"run_compensation_benchmark({n_cases}, {seed}, {str(out)!r})"
    start = time.perf_counter()
    generation, diagnosis = np.random.SeedSequence(seed).spawn(2)
    rngs = [np.random.default_rng(s) for s in generation.spawn(int(n_cases))]
    diagnosis_seeds = [int(s.generate_state(1)[0]) for s in diagnosis.spawn(int(n_cases))]
    rows = []
    for index in tqdm(range(int(n_cases)), desc="compensation benchmark", disable=not progress):
        case = _draw_case(index, effects[index % len(effects)], rngs[index], diagnosis_seeds[index], settings)
        row = {**_run_case(case, settings, out / f"case_{index:03d}"), "seed": seed}
        rows.append(row)
        with log.open("a") as handle:
            handle.write(_json(row) + "\n")
    summary = summarise(rows)
    seconds = time.perf_counter() - start
    document = {"command": command, "seconds": seconds, "settings": dataclasses.asdict(settings), "summary": summary}
    write_text(out / "benchmark.json", _json({**document, "cases": rows}, indent=1))
    write_text(out / "benchmark.md", markdown_report(summary, rows, command, seconds))
    return summary


def _run(args: argparse.Namespace) -> None:
    settings = BenchmarkSettings(args.frame_size, args.palpation_frames, args.sweep_frames, workers=args.workers)
    summary = run_compensation_benchmark(args.cases, args.seed, args.out, settings=settings, command=args.command_line)
    for effect, entry in summary["effects"].items():
        share = entry["recovered"]["dice"]
        print(
            f"{effect}: {entry['cases']} cases, {entry['costly']} costly; cost {_number(entry['cost']['dice'])} Dice; "
            f"recovered {_share(share)} of the Dice"
        )
    print(f"wrote {Path(args.out) / 'benchmark.md'}, benchmark.json and cases.jsonl")


def add_compensation_benchmark_command(commands: argparse._SubParsersAction) -> None:
    """``usdeform compensation-benchmark --cases N --seed S --out DIR``."""
    parser = commands.add_parser(
        "compensation-benchmark",
        help="measure what a recording effect costs the corrected volume and what --compensate gives back",
        description="Simulate palpations and a sweep with a withheld recording effect (image latency, force-sensor "
        "error, viscoelasticity, sound speed; every fifth case none), diagnose the palpations blind, and score the "
        "corrected sweep against the zero-force truth with the effect, compensated by the diagnosis, compensated "
        "with the true parameters and without the effect.",
    )
    parser.add_argument("--cases", type=int, default=5, help="number of cases (default 5)")
    parser.add_argument("--seed", type=int, default=0, help="seed of the cases and the diagnoses (default 0)")
    parser.add_argument("--out", type=Path, required=True, help="output folder (benchmark.md, benchmark.json, ...)")
    parser.add_argument("--frame-size", type=int, default=128, metavar="PX", help="frame rows and columns (128)")
    parser.add_argument("--palpation-frames", type=int, default=60, metavar="N", help="frames per palpation (60)")
    parser.add_argument("--sweep-frames", type=int, default=40, metavar="N", help="frames of the sweep (40)")
    parser.add_argument("--workers", type=int, default=1, help="processes of each diagnosis (default 1)")
    parser.set_defaults(run=_run)
