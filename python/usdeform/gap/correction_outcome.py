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
"""

from __future__ import annotations

import numpy as np

from ..correction import correct_frames
from ..errors import FitError, InputError
from ..metrics import area_mm2, dice, segment_vessel
from ..regression import Observations, fit_regression
from ..stiffness import fit_stiffness
from .attribution import MeasureResult
from .measures import Prediction
from .observations import Observation

__all__ = ["correction_measures"]

_BOOTSTRAP = 10  # each draw refits the correction model three times (the slow part of the measure)
_DICE_FLOOR = 0.01
_AREA_FLOOR_MM2 = 1.0


def _outcome(
    observation: Observation, displacement_px: np.ndarray, points: np.ndarray, reference_mask: np.ndarray
) -> tuple[float, float]:
    """(Dice, area error mm^2) of the peak frame corrected with a model fitted to ``displacement_px`` at ``points``."""
    loading = np.flatnonzero(
        (observation.phase == 0) & (np.arange(observation.n_frames) != observation.reference_index)
    )
    stiffness = fit_stiffness(observation.force_n[loading], observation.probe_displacement_mm[loading])
    displacements = displacement_px[loading][:, points]
    valid = np.isfinite(displacements).all(axis=2)
    samples = Observations(
        observation.points_px[points],
        np.where(valid[..., None], displacements, 0.0),
        valid,
        observation.force_n[loading],
        float(observation.force_n[observation.reference_index]),
        stiffness.profile,
    )
    model = fit_regression([samples], observation.frame_shape).model
    peak = observation.peak_index
    assert observation.peak_frame is not None  # checked by correction_measures
    corrected = correct_frames(
        observation.peak_frame, float(observation.force_n[peak]), stiffness.profile, model, fill=0.0
    )
    mask = segment_vessel(corrected.astype(np.uint8)).mask
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
