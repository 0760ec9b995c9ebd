"""The correction method's outcome as a gap measure: what a user who calibrates on the simulator gets.

The paper's correction (stiffness profile, quadratic displacement regression, warp) is fitted three
ways for each recording and applied to the recording's highest-force loading frame:

* on the recording's own tracked displacements (the reference outcome);
* on the calibrated ideal simulator's displacements at the same points ("before");
* on the simulator with the best candidate effect added ("after").

Measures: Dice of the corrected lumen against the lumen of the lowest-force frame, and the lumen
area error (mm^2); value = recording-fitted minus simulator-fitted outcome (before), with the
"after" value beside it; uncertainty from 10 bootstrap resamples of the tracked points, plus a
floor of 0.01 Dice / 1 mm^2 (segmentation).

:func:`compensation_outcome` says what the diagnosed effect costs that correction and what compensating it
(``usdeform fit/correct --compensate diagnosis.json``, :mod:`usdeform.compensation`) gives back: the
correction fitted on each recording as recorded and with the effect undone at its fitted size, both applied to the
frame a force-controlled sweep would show (:func:`_sweep_frame`: the robot holds the sensor's reading at the sweep's
target, so a sensor reading 2 N high at 15 N leaves the tissue at 13 N, and the correction sees 15 N) and scored
against the lowest-force frame's lumen.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any

import numpy as np

from ..compensation import (
    MIN_AREA_COST_PCT,
    MIN_DICE_COST,
    Compensation,
    compensation_from_diagnosis,
    forced_compensation,
)
from ..correction import correct_frames
from ..errors import FitError, InputError
from ..fitting import fit_stiffness
from ..metrics import area_mm2, dice, pixel_size_mm, segment_vessel
from ..recording import Recording
from ..regression import Observations, fit_regression
from .attribution import MeasureResult
from .measures import Prediction
from .observations import Observation

__all__ = ["compensation_outcome", "correction_measures"]

_BOOTSTRAP = 10  # each draw refits the correction model three times (the slow part of the measure)
_DICE_FLOOR = 0.01
_AREA_FLOOR_MM2 = 1.0
#: the sweep's target reading over the palpations' highest (``usdeform simulate sweep``'s default: half of it)
SWEEP_FORCE_FRACTION = 0.5


def _corrected_peak_mask(
    observation: Observation,
    displacement_px: np.ndarray,
    points: np.ndarray,
    force_n: np.ndarray,
    probe_displacement_mm: np.ndarray,
    reference_index: int,
    frame: tuple[np.ndarray, int] | None = None,
) -> np.ndarray:
    """Lumen mask of the peak frame (or ``frame``: an image and its index) corrected with a model fitted to
    ``displacement_px`` (from frame ``reference_index``) at ``points`` on the loading frames, with per-frame
    ``force_n`` (N) and ``probe_displacement_mm`` (mm; NaN: a frame left out)."""
    loading = np.flatnonzero(
        (observation.phase == 0) & (np.arange(observation.n_frames) != reference_index) & np.isfinite(force_n)
    )
    stiffness = fit_stiffness(force_n[loading], probe_displacement_mm[loading])
    displacements = displacement_px[loading][:, points]
    valid = np.isfinite(displacements).all(axis=2)
    samples = Observations(
        observation.points_px[points],
        np.where(valid[..., None], displacements, 0.0),
        valid,
        force_n[loading],
        float(force_n[reference_index]),
        stiffness.profile,
    )
    model = fit_regression([samples], observation.frame_shape).model
    if frame is None:
        assert observation.peak_frame is not None  # checked by the callers
        frame = (observation.peak_frame, observation.peak_index)
    corrected = correct_frames(frame[0], float(force_n[frame[1]]), stiffness.profile, model, fill=0.0)
    return segment_vessel(corrected.astype(np.uint8)).mask


def _outcome(
    observation: Observation, displacement_px: np.ndarray, points: np.ndarray, reference_mask: np.ndarray
) -> tuple[float, float]:
    """(Dice, area error mm^2) of the peak frame corrected with a model fitted to ``displacement_px`` at ``points``."""
    mask = _corrected_peak_mask(
        observation,
        displacement_px,
        points,
        observation.force_n,
        observation.probe_displacement_mm,
        observation.reference_index,
    )
    pixel = observation.pixel_size_mm
    return dice(mask, reference_mask), area_mm2(mask, pixel) - area_mm2(reference_mask, pixel)


def correction_measures(
    observation: Observation, before: Prediction, after: Prediction, rng: np.random.Generator, z_crit: float
) -> list[MeasureResult]:
    """Dice and area-error measures of the correction fitted on the recording vs on the simulator.

    Empty when the frames hold no segmentable lumen or a fit fails (the measure does not apply).
    """
    if observation.peak_frame is None or observation.reference_frame is None:
        return []
    try:
        reference_mask = segment_vessel(observation.reference_frame).mask
        n_points = len(observation.points_px)
        draws = [np.arange(n_points)] + [rng.integers(0, n_points, n_points) for _ in range(_BOOTSTRAP)]
        results = np.array(
            [
                [
                    _outcome(observation, field, points, reference_mask)
                    for field in (observation.displacement_px, before.displacement_px, after.displacement_px)
                ]
                for points in draws
            ]
        )  # (draws, 3 fits, 2 metrics)
    except (InputError, FitError):
        return []
    differences_before = results[:, 0] - results[:, 1]
    differences_after = results[:, 0] - results[:, 2]
    spread = differences_before[1:].std(axis=0)
    measures = []
    for metric, (name, floor) in enumerate(
        (("correction_dice", _DICE_FLOOR), ("correction_area_error_mm2", _AREA_FLOOR_MM2))
    ):
        value = float(differences_before[0, metric])
        sigma = float(np.hypot(spread[metric], floor))
        measures.append(
            MeasureResult(
                name=name,
                recording=observation.name,
                group="correction",
                region="vessel lumen, highest-force loading frame",
                force_range_n=(
                    float(observation.force_n[observation.reference_index]),
                    float(observation.force_n[observation.peak_index]),
                ),
                phase="loading",
                value=value,
                uncertainty=sigma,
                significant=bool(abs(value) > z_crit * sigma),
                value_after=float(differences_after[0, metric]),
            )
        )
        measures.append(
            MeasureResult(
                name=f"{name}_recording_fit",
                recording=observation.name,
                group="correction",
                region="vessel lumen, highest-force loading frame",
                force_range_n=None,
                phase="loading",
                value=float(results[0, 0, metric]),
                uncertainty=float(np.hypot(results[1:, 0, metric].std(), floor)),
                significant=False,
                value_after=None,
            )
        )
    return measures


def _compensated_scores(
    observation: Observation, recording: Recording, compensation: Compensation
) -> dict[str, float | str]:
    """One recording's peak frame corrected as recorded and compensated: Dice against the lowest-force frame's
    lumen, and area error (% of that lumen's area in the compensated calibration), each way."""
    scores: dict[str, float | str] = {"recording": observation.name}
    try:
        compensated, _ = compensation.apply(recording, observation.name)
        reference_mask = (
            None if observation.reference_frame is None else segment_vessel(observation.reference_frame).mask
        )
    except InputError as error:  # a re-pairing that keeps too few frames, or no lumen in the lowest-force frame
        scores["error"] = str(error)
        return scores
    kept = np.searchsorted(recording.timestamps, compensated.timestamps)
    force = np.full(observation.n_frames, math.nan)
    probe_displacement = np.full(observation.n_frames, math.nan)
    force[kept] = np.asarray(compensated.force, dtype=float)
    probe_displacement[kept] = np.asarray(compensated.probe_displacement, dtype=float)
    if observation.peak_frame is None or reference_mask is None or not np.isfinite(force[observation.peak_index]):
        return scores  # no lumen frames, or the re-pairing dropped the peak frame
    # a re-pairing may drop the reference frame: the tracks are then taken from the kept frame of least lambda
    in_contact = np.flatnonzero(np.isfinite(force) & np.isfinite(observation.displacement_px).any(axis=(1, 2)))
    if not len(in_contact):
        return scores
    reference = int(in_contact[np.argmin(probe_displacement[in_contact])])
    displacement = observation.displacement_px - observation.displacement_px[reference]
    compensated_pixel = pixel_size_mm(compensated.image_to_probe)
    reference_area = area_mm2(reference_mask, compensated_pixel)
    if reference_area <= 0:
        return scores  # no lumen in the lowest-force frame
    points = np.arange(len(observation.points_px))
    sweep_index = _sweep_frame(observation, force)
    if sweep_index is None:
        return scores
    frame = (np.asarray(recording.frames[sweep_index]), sweep_index)
    scores["sweep_force_n"] = float(observation.force_n[sweep_index])
    scores["sweep_force_felt_n"] = float(force[sweep_index])
    for way, (tracks, forces, displacements, reference_index, pixel) in {
        "uncompensated": (
            observation.displacement_px,
            observation.force_n,
            observation.probe_displacement_mm,
            observation.reference_index,
            observation.pixel_size_mm,
        ),
        "compensated": (displacement, force, probe_displacement, reference, compensated_pixel),
    }.items():
        try:
            mask = _corrected_peak_mask(observation, tracks, points, forces, displacements, reference_index, frame)
        except (InputError, FitError) as error:
            scores[f"error_{way}"] = str(error)
            continue
        scores[f"dice_{way}"] = float(dice(mask, reference_mask))
        scores[f"area_error_pct_{way}"] = 100.0 * (area_mm2(mask, pixel) - reference_area) / reference_area
    return scores


def _sweep_frame(observation: Observation, felt_force_n: np.ndarray) -> int | None:
    """The loading frame that shows the tissue as a force-controlled sweep would: the sweep's robot holds the
    sensor's reading at its target (``SWEEP_FORCE_FRACTION`` of the highest reading recorded, as the simulator's
    sweeps), so the tissue feels the target less the sensor's error; the frame whose reading is nearest the
    target shows that tissue (its ``felt_force_n``, the compensated force, is what the tissue felt), and a
    correction sees that reading. None when no loading frame in contact has a felt force."""
    loading = np.flatnonzero((observation.phase == 0) & np.isfinite(felt_force_n))
    loading = loading[loading != observation.reference_index]
    if not len(loading):
        return None
    target = SWEEP_FORCE_FRACTION * float(np.max(observation.force_n))
    return int(loading[np.argmin(np.abs(observation.force_n[loading] - target))])


def compensation_outcome(
    observations: Sequence[Observation], recordings: Sequence[Recording], diagnosis: dict[str, Any]
) -> dict[str, Any]:
    """What the effect ``diagnosis`` (the diagnosis.json contract) names costs the correction and what compensating
    it gives back, on the frame of each recording that a force-controlled sweep would show (module docstring).

    Returns the ``compensation`` entry of diagnosis.json: ``effects`` (what is undone, with the fitted
    parameters), ``supported`` (``--compensate`` accepts it; False: measured as ``--force-compensation`` would
    apply it), ``refusal`` (why ``--compensate`` refuses it, or ""), ``recordings`` (per recording: Dice and area
    error %, uncompensated and compensated) and ``summary``, one line saying it.
    """
    entry: dict[str, Any] = {"effects": {}, "supported": False, "refusal": "", "recordings": []}
    named = list(diagnosis.get("named") or [])
    if not named:
        entry["summary"] = "Compensation: the diagnosis names no effect, so there is nothing to compensate."
        return entry
    compensation: Compensation | None
    try:
        compensation = compensation_from_diagnosis(diagnosis, "the diagnosis")
        entry["supported"] = True
    except InputError as refusal:
        entry["refusal"] = str(refusal).removeprefix("the diagnosis: ")
        compensation = (
            None if diagnosis.get("verdict") == "ambiguous" else forced_compensation(diagnosis, "the diagnosis")
        )
    if compensation is None:
        entry["summary"] = f"Compensation: none; {entry['refusal']}."
        return entry
    entry["effects"] = compensation.effects
    rows = [_compensated_scores(o, r, compensation) for o, r in zip(observations, recordings, strict=True)]
    entry["recordings"] = rows
    keys = ("dice_uncompensated", "dice_compensated", "area_error_pct_uncompensated", "area_error_pct_compensated")
    scored = [row for row in rows if all(key in row for key in keys)]
    effects = " and ".join(compensation.effects)
    if not scored:
        entry["summary"] = (
            f"Compensation of {effects}: not measured (no recording has a lumen to score, or a fit failed)."
        )
        return entry
    dice_before, dice_after, area_before, area_after = (float(np.mean([row[key] for row in scored])) for key in keys)
    how = (
        "--compensate diagnosis.json"
        if entry["supported"]
        else f"--force-compensation, as the diagnosis does not support it: {entry['refusal']}"
    )
    dice_change, area_change = dice_after - dice_before, abs(area_before) - abs(area_after)
    if abs(dice_change) < MIN_DICE_COST and abs(area_change) < MIN_AREA_COST_PCT:
        outcome = (
            f"within {MIN_DICE_COST} Dice and {MIN_AREA_COST_PCT:g} points of area error of each other: at its fitted "
            "size the effect costs this correction less than that, and compensation gives back no more"
        )
    elif dice_change >= 0 and area_change >= 0:
        outcome = (
            f"compensation gives back {dice_change:.3f} Dice and {area_change:.1f} points of area error, what the "
            "effect costs an uncompensated correction in so far as the fitted size is right"
        )
    else:
        outcome = (
            f"compensation changes Dice by {dice_change:+.3f} and the size of the area error by {-area_change:+.1f} "
            "points, worse in at least one: check the fitted size and its uncertainty before compensating"
        )
    entry["summary"] = (
        f"Compensation of {effects} at its fitted size ({how}): a frame as a force-controlled sweep holding the "
        f"reading at {SWEEP_FORCE_FRACTION:g} of the highest would show it, corrected to zero force, "
        f"scores Dice {dice_after:.3f} and area error {area_after:+.1f} % against the lowest-force frame compensated, "
        f"{dice_before:.3f} and {area_before:+.1f} % as recorded (mean of {len(scored)} recording(s)); {outcome}."
    )
    return entry
