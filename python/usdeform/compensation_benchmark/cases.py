"""The compensation benchmark's cases: what each simulates, the conditions it corrects under and their scores
(see :mod:`usdeform.compensation_benchmark`)."""

from __future__ import annotations

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

from ..compensation import (
    MIN_AREA_COST_PCT,
    MIN_DICE_COST,
    Compensation,
    apply_compensation,
    compensation_option,
    forced_compensation,
)
from ..correction import correct_recording, stiffness_source_for, sweep_profiles
from ..correction._frames import correct_like
from ..errors import InputError, UsdeformError
from ..fitting import fit_palpations
from ..gap import diagnose
from ..gap.benchmark import draw_effect
from ..gap.follow_up import PALPATION_KINDS
from ..gap.follow_up_sim import FollowUpSettings, record_follow_up
from ..metrics import area_mm2, centroid_mm, dice, pixel_size_mm
from ..recording import Recording
from ..sim import (
    Effects,
    ForceController,
    GroundTruth,
    ImagingSettings,
    Phantom,
    coarse_phantom,
    simulate_palpation,
    simulate_sweep,
)
from ..sim.effects import Effect
from ..validation import ForceClampWarning, forces_in_range

__all__ = ["CONDITIONS", "EFFECT_TYPES", "BenchmarkSettings", "run_case", "true_compensation"]

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


#: The integer settings' ranges (inclusive), which the command line's options share.
SETTING_RANGES = (
    ("frame_size", 64, 1024),
    ("palpation_frames", 20, 2000),
    ("sweep_frames", 4, 5000),
    ("workers", 1, 64),
    ("sweep_frame_step", 1, 50),
)


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
    follow_up: bool = True

    def check(self) -> None:
        """InputError naming the first setting out of range."""
        for name, low, high in SETTING_RANGES:
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int) or not low <= value <= high:
                raise InputError(f"{name}: expected an integer from {low} to {high}, got {value!r}")


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


def _diagnosis(recordings: Sequence[Recording | Path], case: _Case, workers: int) -> tuple[dict[str, Any], list[Any]]:
    """The diagnosis.json of ``recordings`` and its follow-up protocol; a failed diagnosis is refused, as its file
    would be."""
    try:
        diagnosis = diagnose(recordings, seed=case.diagnosis_seed, progress=False, workers=workers)
    except UsdeformError as error:
        return {"verdict": f"error: {error}", "named": [], "effects": [], "measures": []}, []
    return diagnosis.to_json(), list(getattr(diagnosis, "follow_up", []))


def _follow_up(
    case: _Case, entries: list[Any], settings: BenchmarkSettings, directory: Path
) -> tuple[list[Path], dict[str, Any]]:
    """What round 0's record_next.json asks for, recorded on the case's phantom with its effect into
    ``directory`` (a known weight needs its file's per-frame KnownLoad), and what was added (kinds asked for,
    recordings, palpations, seconds, kinds the simulator could not record)."""
    duration_s = 2 * settings.palpation_force_n / 5.0 + settings.hold_s  # the palpations' 5 N/s ramp
    follow_up_settings = FollowUpSettings(
        frames_per_s=settings.palpation_frames / duration_s,
        rows=settings.frame_size,
        cols=settings.frame_size,
        seed=case.seeds[0],
    )
    recorded = record_follow_up(entries, directory, _phantom(), Effects.of(case.effects), follow_up_settings)
    kept = [(item, path) for item, path in recorded if path is not None]
    return [path for _, path in kept], {
        "asked": [entry.kind for entry in entries],
        "recordings": len(kept),
        "palpations": sum(item.entry.kind in PALPATION_KINDS for item, _ in kept),
        "seconds": sum(item.duration_s for item, _ in kept),
        "not_recorded": [item.entry.kind for item, path in recorded if path is None],
    }


def _diagnosed(
    case: _Case, palpations: list[Recording], directory: Path, settings: BenchmarkSettings
) -> tuple[Any, Any, str, str, dict[str, Any]]:
    """The diagnosis (blind, on the palpations; then, where it asks for more and ``settings.follow_up``, on them and
    the follow-up recordings) written to ``directory/diagnosis.json`` (round 0: ``diagnosis_round0.json``); the
    compensation ``--compensate`` reads from the last (None when refused), the one ``--force-compensation`` reads
    (None where even forcing applies nothing), its verdict, the refusal (or "") and the loop's record (with
    ``estimate``: the last diagnosis's own per-recording scores of what compensating gives back)."""
    result, entries = _diagnosis(palpations, case, settings.workers)
    loop: dict[str, Any] = {"verdict_round0": str(result.get("verdict")), "named_round0": result.get("named", [])}
    if entries and settings.follow_up:
        (directory / "diagnosis_round0.json").write_text(json.dumps(result, indent=1), encoding="utf-8")
        recordings, loop["follow_up"] = _follow_up(case, entries, settings, directory / "follow_up")
        if recordings:
            result, _ = _diagnosis([*palpations, *recordings], case, settings.workers)
    path = directory / "diagnosis.json"
    path.write_text(json.dumps(result, indent=1), encoding="utf-8")
    loop["estimate"] = (result.get("compensation") or {}).get("recordings", [])
    verdict = str(result.get("verdict"))
    forced = forced_compensation(result, str(path))
    try:
        return compensation_option(path, False), forced, verdict, "", loop
    except InputError as error:
        return None, forced, verdict, str(error), loop


def _identical(x: np.ndarray | None, y: np.ndarray | None) -> bool:
    """Both None, or equal arrays of one dtype and shape, bit for bit."""
    if x is None or y is None:
        return x is y
    return x.dtype == y.dtype and x.shape == y.shape and x.tobytes() == y.tobytes()


def run_case(case: _Case, settings: BenchmarkSettings, directory: Path) -> dict[str, Any]:
    """One case's four conditions, scores and null check (a JSON row)."""
    start = time.perf_counter()
    directory.mkdir(parents=True, exist_ok=True)
    flexible_layer_mm = _phantom().base_section.depth_mm
    scores: dict[str, dict[str, Any]] = {}
    arrays: dict[str, tuple[np.ndarray | None, ...]] = {}
    diagnosed, forced, verdict, refusal, diagnosis_s = None, None, "-", "", 0.0
    loop: dict[str, Any] = {}
    try:
        palpations, sweep, truth = _simulate(case, settings, with_effect=True)
        clean = (palpations, sweep, truth) if case.effect is None else _simulate(case, settings, with_effect=False)
    except UsdeformError as error:  # e.g. a probe pressed past the phantom's solved range: reported, not scored
        failed = {**dict.fromkeys(METRICS, math.nan), "frames": 0, "error": f"simulation: {error}"}
        scores = dict.fromkeys(CONDITIONS, failed)
    else:
        true_pixel = _true_pixel_mm(case, clean[1])
        diagnosis_start = time.perf_counter()
        diagnosed, forced, verdict, refusal, loop = _diagnosed(case, palpations, directory, settings)
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
        **loop,
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
