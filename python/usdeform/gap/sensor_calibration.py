"""The force sensor's gain, offset and drift from a known-weight recording: the probe in its holder, off the tissue,
loaded by a calibrated weight, with the load truly applied per frame (``Seq_FrameNNNN_KnownLoad``, N) beside the
sensor's reading (``ContactForce``).

No palpation can tell a sensor that reads a fixed fraction too high from a stiffer tissue: both scale every force
alike. A known load can: ``reading = (1 + gain_error) * load + offset + drift * t`` fitted by least squares, the
standard errors from the block bootstrap (time blocks of 0.3 s, whose serial correlation the sensor's noise keeps).
The drift is fitted where the recording identifies it (unloaded stretches before and after the load, or a load held
long enough) and held at zero otherwise, by the same rule as a palpation's (:func:`usdeform.gap.folds.
unidentified_linear`).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from ..errors import InputError
from ..io.sequence_file import read_frame_series, read_sequence
from .folds import unidentified_linear

__all__ = [
    "DRIFT_TOLERANCE_N_PER_S",
    "KNOWN_LOAD_FIELD",
    "OFFSET_TOLERANCE_N",
    "KnownSensor",
    "SensorCalibration",
    "is_known_weight",
    "known_sensor",
    "known_weight_calibration",
    "sensor_calibration",
    "sensor_finding",
]

KNOWN_LOAD_FIELD = "KnownLoad"
_BLOCK_S = 0.3
_BOOTSTRAP = 200
_MIN_FRAMES = 10
_MIN_LOAD_RANGE_N = 0.5
#: A sensor within these sizes of offset (N) and drift (N/s) counts as free of error: a third of the smallest bias
#: the palpations are known to show, and a drift that adds less than that over a 10 s palpation.
OFFSET_TOLERANCE_N = 0.1
DRIFT_TOLERANCE_N_PER_S = 0.01
_Z = 3.0  # standard errors: an offset or drift is shown when beyond this many of them


@dataclass(frozen=True)
class SensorCalibration:
    """The force sensor's error fitted on a known-weight recording: gain error (reading / load - 1), offset (N) and
    drift (N/s), each with its standard error; the drift is None when the recording does not identify it."""

    recording: str
    gain_error: float
    gain_error_uncertainty: float
    offset_n: float
    offset_uncertainty_n: float
    drift_n_per_s: float | None
    drift_uncertainty_n_per_s: float | None
    frames: int

    def to_json(self) -> dict[str, object]:
        return asdict(self)


def is_known_weight(path: str | Path) -> bool:
    """Whether the sequence file at ``path`` is a known-weight recording (it has per-frame KnownLoad)."""
    return read_frame_series(path, KNOWN_LOAD_FIELD) is not None


def _fit(design: np.ndarray, reading: np.ndarray) -> np.ndarray:
    return np.linalg.lstsq(design, reading, rcond=None)[0]


def sensor_calibration(
    reading_n: np.ndarray, known_load_n: np.ndarray, time_s: np.ndarray, name: str, seed: int = 0
) -> SensorCalibration:
    """The sensor's gain error, offset and drift from its ``reading_n`` under ``known_load_n`` (both (n,), N) at
    ``time_s`` (n,), see the module docstring. Raises InputError naming ``name`` for too few frames or a load that
    does not vary."""
    reading, load, time = (np.asarray(a, dtype=float) for a in (reading_n, known_load_n, time_s))
    ok = np.isfinite(reading) & np.isfinite(load) & np.isfinite(time)
    if ok.sum() < _MIN_FRAMES:
        raise InputError(f"{name}: {KNOWN_LOAD_FIELD}: {ok.sum()} frames with a reading and a load, need {_MIN_FRAMES}")
    if np.ptp(load[ok]) < _MIN_LOAD_RANGE_N:
        raise InputError(
            f"{name}: {KNOWN_LOAD_FIELD}: the load varies by {np.ptp(load[ok]):.3g} N; a known weight must be put on "
            f"and taken off (at least {_MIN_LOAD_RANGE_N} N)"
        )
    reading, load, time = reading[ok], load[ok], time[ok] - time[ok][0]
    block = (time / _BLOCK_S).astype(int)
    blocks = np.unique(block)
    rng = np.random.default_rng(seed)

    def estimates(design: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        point = _fit(design, reading)
        rows = []
        for _ in range(_BOOTSTRAP):
            chosen = np.concatenate([np.flatnonzero(block == b) for b in rng.choice(blocks, len(blocks))])
            if np.ptp(load[chosen]) > 0:
                rows.append(_fit(design[chosen], reading[chosen]))
        spread = np.std(np.array(rows), axis=0, ddof=1) if len(rows) > 2 else np.full(design.shape[1], np.inf)
        return point, spread

    with_drift = np.column_stack([load, np.ones_like(load), time])
    point, spread = estimates(with_drift)
    drift: float | None = float(point[2])
    drift_error: float | None = float(spread[2])
    if unidentified_linear([{"drift_n_per_s": float(spread[2])}]):
        point, spread = estimates(with_drift[:, :2])
        drift = drift_error = None
    return SensorCalibration(
        recording=name,
        gain_error=float(point[0] - 1.0),
        gain_error_uncertainty=float(spread[0]),
        offset_n=float(point[1]),
        offset_uncertainty_n=float(spread[1]),
        drift_n_per_s=drift,
        drift_uncertainty_n_per_s=drift_error,
        frames=int(ok.sum()),
    )


def known_weight_calibration(path: str | Path, seed: int = 0) -> SensorCalibration:
    """:func:`sensor_calibration` of the known-weight sequence file at ``path`` (ContactForce against KnownLoad).
    Raises InputError naming the file when it has no KnownLoad or ContactForce."""
    load = read_frame_series(path, KNOWN_LOAD_FIELD)
    if load is None:
        raise InputError(f"{path}: no {KNOWN_LOAD_FIELD} field: a known-weight recording gives the load of every frame")
    recording = read_sequence(path)
    if recording.force is None:
        raise InputError(f"{path}: no ContactForce field: a known-weight recording needs the sensor's reading")
    return sensor_calibration(recording.force, load, recording.timestamps, str(path), seed)


def sensor_finding(calibrations: Sequence[Mapping[str, Any]]) -> str | None:
    """What known weights (:meth:`SensorCalibration.to_json` each) show of the force sensor: "error" when one shows an
    offset or drift beyond :data:`OFFSET_TOLERANCE_N` or :data:`DRIFT_TOLERANCE_N_PER_S` and beyond 3 standard
    errors; "clean" when each shows both within them with 3 standard errors to spare (a drift it cannot identify
    is not shown small); None otherwise, or without a known weight. A gain error is left out: it scales every
    force alike, which a palpation reads as stiffness, so no palpation shows it."""
    if not calibrations:
        return None

    def shown(value: float | None, error: float | None, tolerance: float) -> bool:
        return value is not None and error is not None and abs(value) > max(tolerance, _Z * error)

    def small(value: float | None, error: float | None, tolerance: float) -> bool:
        return value is not None and error is not None and abs(value) + _Z * error < tolerance

    if any(
        shown(c["offset_n"], c["offset_uncertainty_n"], OFFSET_TOLERANCE_N)
        or shown(c["drift_n_per_s"], c["drift_uncertainty_n_per_s"], DRIFT_TOLERANCE_N_PER_S)
        for c in calibrations
    ):
        return "error"
    if all(
        small(c["offset_n"], c["offset_uncertainty_n"], OFFSET_TOLERANCE_N)
        and small(c["drift_n_per_s"], c["drift_uncertainty_n_per_s"], DRIFT_TOLERANCE_N_PER_S)
        for c in calibrations
    ):
        return "clean"
    return None


@dataclass(frozen=True)
class KnownSensor:
    """What known weights show of the force sensor, for the diagnosis: ``finding`` (:func:`sensor_finding`) and
    ``drift_n_per_s``, the drift they identify as (value, standard error) in N/s, or None. A palpation that cannot
    identify its drift holds it at this value instead of zero."""

    finding: str | None = None
    drift_n_per_s: tuple[float, float] | None = field(default=None)


def known_sensor(calibrations: Sequence[Mapping[str, Any]]) -> KnownSensor:
    """:class:`KnownSensor` of known weights (:meth:`SensorCalibration.to_json` each): the drift is the
    inverse-variance mean of those that identify it."""
    drifts = [
        (float(c["drift_n_per_s"]), float(c["drift_uncertainty_n_per_s"]))
        for c in calibrations
        if c["drift_n_per_s"] is not None and c["drift_uncertainty_n_per_s"]
    ]
    drift = None
    if drifts:
        weights = np.array([1 / error**2 for _, error in drifts])
        drift = (float(np.dot(weights, [value for value, _ in drifts]) / weights.sum()), float(weights.sum() ** -0.5))
    return KnownSensor(sensor_finding(calibrations), drift)
