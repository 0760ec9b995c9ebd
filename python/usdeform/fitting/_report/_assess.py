"""Measuring a fit against its own palpations (:func:`assess_fit`)."""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from typing import Any

import numpy as np
from scipy.ndimage import map_coordinates

from ...errors import FitError, InputError
from ...metrics import pixel_size_mm
from ...optical_flow import REJECTION_REASONS
from ...regression import DeformationModel, Observations
from .._palpations import FittedPalpations, fit_measured
from .._sampling import SampledPosition
from ._report import (
    _REASON_TEXT,
    DEFAULT_BAND_MM,
    DROPPED_WARNING_FRACTION,
    HELD_OUT_WARNING_PX,
    LATERAL_REGIONS,
    MAX_BANDS,
    R_SQUARED_WARNING,
    UNRECORDED,
    DepthBand,
    FitReport,
    PalpationReport,
    RegionResidual,
    _pooled_rms,
)


def _band_width(depth_mm: float, band_mm: float | None) -> float:
    if band_mm is None:
        return max(DEFAULT_BAND_MM, float(np.ceil(depth_mm / MAX_BANDS)))
    if not (np.isfinite(band_mm) and band_mm > 0):
        raise InputError(f"band_mm: expected a positive width in mm, got {band_mm!r}")
    return float(band_mm)


def _band_edges(band: int, width: float, depth_mm: float) -> tuple[float, float]:
    return (round(band * width, 6), round(min((band + 1) * width, depth_mm), 6))


def _reasons_of(measured: SampledPosition) -> tuple[np.ndarray, list[str]]:
    """(N,) index into the returned reason names of the check that dropped each track (-1: kept to the
    last frame); the names are :data:`REJECTION_REASONS` then :data:`UNRECORDED` (dropped, no reason)."""
    tracked = measured.tracked
    reasons = np.array(tracked.dropped_reason, dtype=np.int64)
    if len(tracked.frame_indices):
        reasons[(reasons < 0) & ~tracked.valid[-1]] = len(REJECTION_REASONS)
    return reasons, [*REJECTION_REASONS, UNRECORDED]


def _bands(
    depth_mm: np.ndarray, reasons: np.ndarray, names: list[str], width: float, n_bands: int, depth: float
) -> list[DepthBand]:
    """Per band: (tracks, kept, reason -> dropped) of the tracks at ``depth_mm``."""
    band_of = np.minimum((depth_mm // width).astype(int), n_bands - 1)
    bands = []
    for band in range(n_bands):
        inside = reasons[band_of == band]
        counts = np.bincount(inside[inside >= 0], minlength=len(names))
        dropped = {name: int(count) for name, count in zip(names, counts, strict=True) if name != UNRECORDED or count}
        bands.append(DepthBand(_band_edges(band, width, depth), len(inside), int(np.sum(inside < 0)), dropped))
    return bands


def _field(model: DeformationModel, observations: Observations, force_n: float) -> np.ndarray:
    """The model's D(x, y, F) on the frame, (2, rows, cols) px, with a vessel-anchored part on the
    palpation's own lumen (none where it shows none, as in the fit)."""
    shape = model.image_model.kernel.frame_shape
    return model.displacement_with_lumen(
        force_n, observations.profile, shape, observations.vessel, observations.other_vessels
    )


def _predicted(model: Any, observations: Observations, points: np.ndarray) -> np.ndarray:
    """(M, n, 2) displacements the model predicts for ``points`` (indices into the observations'
    points) from the reference frame to each of the M frames, px (as the fit compares them)."""
    reference = _field(model, observations, observations.reference_force_n)
    x, y = observations.points_px[points, 0], observations.points_px[points, 1]
    predicted = np.empty((len(observations.forces_n), len(points), 2))
    for row, force in enumerate(observations.forces_n):
        difference = _field(model, observations, float(force)) - reference
        for component in range(2):
            predicted[row, :, component] = map_coordinates(difference[component], [y, x], order=1, mode="nearest")
    return predicted


def _errors_mm(errors_px: np.ndarray, size_mm: tuple[float, float]) -> np.ndarray:
    return np.linalg.norm(errors_px * np.asarray(size_mm), axis=-1)


def _rms(values: np.ndarray) -> float:
    return float(np.sqrt(np.mean(values**2))) if values.size else np.nan


def _held_out_predictions(
    fitted: FittedPalpations, folds: list[np.ndarray]
) -> tuple[list[np.ndarray], list[np.ndarray]]:
    """Per palpation, (M, n_tracks, 2) predictions of each track by the model refitted without its fold
    (NaN where that fit failed) and by the model as fitted. ``folds``: per palpation, (n_tracks,) fold
    of each track (-1: in no region, never held out)."""
    fit = fitted.fit
    penalised = fit.fitted.anchor == "vessel" or fit.fitted.image_model.basis == "bspline"
    smoothness = fit.smoothness if penalised else None
    held_out = [
        np.full((len(m.observations.forces_n), len(f), 2), np.nan) for m, f in zip(fitted.measured, folds, strict=True)
    ]
    for fold in np.unique(np.concatenate(folds)):
        if fold < 0:
            continue
        kept_in = []
        for measured, of_track in zip(fitted.measured, folds, strict=True):
            valid = measured.observations.valid.copy()
            valid[:, : len(of_track)] &= of_track != fold
            kept_in.append(
                dataclasses.replace(measured, observations=dataclasses.replace(measured.observations, valid=valid))
            )
        try:
            refit = fit_measured(
                kept_in, fitted.method, solver="exact", smoothness=smoothness, wall_weight=fitted.wall_weight
            )
        except FitError:
            continue  # too few samples without this fold: its regions stay NaN
        for measured, of_track, predictions in zip(fitted.measured, folds, held_out, strict=True):
            points = np.flatnonzero(of_track == fold)
            if len(points):
                predictions[:, points] = _predicted(refit.fitted, measured.observations, points)
    as_fitted = [
        _predicted(fit.fitted, m.observations, np.arange(len(f))) for m, f in zip(fitted.measured, folds, strict=True)
    ]
    return held_out, as_fitted


def assess_fit(
    fitted: FittedPalpations,
    *,
    names: Sequence[str] | None = None,
    band_mm: float | None = None,
    n_folds: int = 5,
) -> FitReport:
    """Measure how far to trust a fitted model: tracks per depth band and why they were dropped, the
    field at the highest force, the stiffness fits, the cross-validated residual by region, warnings.

    Parameters
    ----------
    fitted : FittedPalpations
        What :func:`usdeform.fitting.fit_palpations` returned; its palpations' loading ramps
        (``loading_recordings``, the frames that were fitted) give the pixel sizes and frames.
    names : sequence of str, optional
        One name per palpation (e.g. its file), used in the warnings.
    band_mm : float, optional
        Depth band width, mm; None: :data:`DEFAULT_BAND_MM`, wider on frames deeper than
        :data:`MAX_BANDS` such bands.
    n_folds : int
        Folds of the cross-validation (>= 2).

    Returns
    -------
    FitReport
    """
    recordings = tuple(fitted.loading_recordings)
    names = [f"palpation {index + 1}" for index in range(len(recordings))] if names is None else list(names)
    if len(names) != len(recordings):
        raise InputError(f"names: expected one per fitted palpation ({len(recordings)}), got {len(names)}")
    if int(n_folds) != n_folds or n_folds < 2:
        raise InputError(f"n_folds: expected an integer >= 2, got {n_folds!r}")
    sizes = [pixel_size_mm(recording.image_to_probe) for recording in recordings]
    rows, cols = recordings[0].shape
    depth = max(rows * axial for _, axial in sizes)
    width = _band_width(depth, band_mm)
    n_bands = int(np.ceil(depth / width - 1e-9))
    # Each track's depth band and lateral third; a region is (band, third), pooled over palpations.
    depth_of = [m.tracked.points_px[:, 1] * axial for m, (_, axial) in zip(fitted.measured, sizes, strict=True)]
    band_of = [np.minimum((d // width).astype(int), n_bands - 1) for d in depth_of]
    third_of = [np.minimum((m.tracked.points_px[:, 0] * 3 // cols).astype(int), 2) for m in fitted.measured]
    region_ids = np.unique(np.concatenate([b * 3 + t for b, t in zip(band_of, third_of, strict=True)]))
    fold_of_region = np.random.default_rng(0).permutation(len(region_ids)) % min(int(n_folds), len(region_ids))
    folds = [fold_of_region[np.searchsorted(region_ids, b * 3 + t)] for b, t in zip(band_of, third_of, strict=True)]
    held_out, as_fitted = _held_out_predictions(fitted, folds)

    palpations, per_palpation_bands = [], []
    errors: dict[int, list[tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]]] = {}
    for index, (name, measured, size) in enumerate(zip(names, fitted.measured, sizes, strict=True)):
        tracked, observations = measured.tracked, measured.observations
        reasons, reason_names = _reasons_of(measured)
        bands = _bands(depth_of[index], reasons, reason_names, width, n_bands, depth)
        per_palpation_bands.append(bands)
        n_tracks = len(tracked.points_px)
        measured_px = observations.displacements_px[:, :n_tracks]
        valid = observations.valid[:, :n_tracks]
        fitted_error = np.where(valid[:, :, None], measured_px - as_fitted[index], np.nan)
        held_error = np.where(valid[:, :, None], measured_px - held_out[index], np.nan)
        row = int(np.argmax(observations.forces_n)) if len(observations.forces_n) else 0
        at_top = fitted_error[row][valid[row]] if len(observations.forces_n) else np.zeros((0, 2))
        for point in range(n_tracks):
            region = int(band_of[index][point] * 3 + third_of[index][point])
            samples = valid[:, point]
            errors.setdefault(region, []).append(
                (
                    np.linalg.norm(held_error[samples, point], axis=-1),
                    _errors_mm(held_error[samples, point], size),
                    np.linalg.norm(fitted_error[samples, point], axis=-1),
                    _errors_mm(fitted_error[samples, point], size),
                )
            )
        mean, sd = measured.stiffness.stiffness_mean_sd_n_per_m
        palpations.append(
            PalpationReport(
                name,
                size,
                tuple(bands),
                {
                    reason: int(tracked.rejected[reason].sum()) if reason in tracked.rejected else 0
                    for reason in REJECTION_REASONS
                },
                dict(measured.stiffness.r_squared),
                (float(mean), float(sd)),
                row,
                float(observations.forces_n[row]) if len(observations.forces_n) else np.nan,
                _rms(np.linalg.norm(at_top, axis=-1)),
                _rms(_errors_mm(at_top, size)),
            )
        )
    pooled = tuple(_pool([bands[band] for bands in per_palpation_bands]) for band in range(n_bands))
    regions = []
    for region in region_ids:
        band, third = divmod(int(region), 3)
        parts = errors.get(int(region), [])
        values = [np.concatenate([part[k] for part in parts]) if parts else np.zeros(0) for k in range(4)]
        regions.append(
            RegionResidual(
                _band_edges(band, width, depth),
                LATERAL_REGIONS[third],
                (round(third * cols / 3 * sizes[0][0], 6), round((third + 1) * cols / 3 * sizes[0][0], 6)),
                len(parts),
                len(values[0]),
                *(_rms(v[np.isfinite(v)]) if np.isfinite(v).any() else np.nan for v in values),
            )
        )
    warnings = _warnings(palpations, pooled, regions) + _lumen_warnings(fitted, [p.name for p in palpations])
    return FitReport(tuple(palpations), pooled, tuple(regions), tuple(warnings), width, int(n_folds), fitted)


def _pool(bands: Sequence[DepthBand]) -> DepthBand:
    names = list(dict.fromkeys(name for band in bands for name in band.dropped))
    return DepthBand(
        bands[0].depth_mm,
        sum(band.tracks for band in bands),
        sum(band.kept for band in bands),
        {name: sum(band.dropped.get(name, 0) for band in bands) for name in names},
    )


def _main_reason(band: Sequence[DepthBand]) -> str:
    totals: dict[str, int] = {}
    for b in band:
        for name, count in b.dropped.items():
            totals[name] = totals.get(name, 0) + count
    name = max(totals, key=totals.__getitem__)
    return _REASON_TEXT.get(name, name.replace("_", " "))


def _lumen_warnings(fitted: FittedPalpations, names: Sequence[str]) -> list[str]:
    """A warning where the palpations show different numbers of lumens: a vessel seen at some positions only
    (a branch, a vein beside the artery) has its collapse learnt there, and a sweep elsewhere extrapolates it."""
    counts = [(m.observations.vessel is not None) + len(m.observations.other_vessels) for m in fitted.measured]
    if len(set(counts)) < 2:
        return []
    most = max(counts)
    fewer = [f"{name} ({count})" for name, count in zip(names, counts, strict=True) if count < most]
    return [
        f"the palpations show different numbers of lumens: {', '.join(fewer)} against {most} in the others; "
        "a vessel seen at some positions only is corrected with the collapse learnt there, so a sweep through "
        "the other positions extrapolates it: palpate where each vessel is"
    ]


def _warnings(
    palpations: Sequence[PalpationReport], bands: Sequence[DepthBand], regions: Sequence[RegionResidual]
) -> list[str]:
    """The plain-language warnings (see the module docstring)."""
    warnings = []
    # Runs of consecutive bands (with tracks) where most tracks were dropped; the deepest run may
    # reach the deepest band that has tracks: the model is extrapolated below its top.
    tracked = [band for band in bands if band.tracks]
    runs: list[list[DepthBand]] = []
    previous = -2
    for position, band in enumerate(tracked):
        if band.dropped_fraction >= DROPPED_WARNING_FRACTION:
            if position == previous + 1:
                runs[-1].append(band)
            else:
                runs.append([band])
            previous = position
    for run in runs:
        tracks = sum(band.tracks for band in run)
        share = 100 * sum(band.n_dropped for band in run) / tracks
        top, bottom = run[0].depth_mm[0], run[-1].depth_mm[1]
        if run[-1] is tracked[-1]:
            where, meaning = f"below {top:g} mm", "the model there is extrapolated"
        else:
            where, meaning = f"between {top:g} and {bottom:g} mm deep", "the model there is interpolated across the gap"
        warnings.append(
            f"{where}, {share:.0f} % of tracks were dropped ({tracks - sum(b.kept for b in run)} of {tracks}, "
            f"mostly: {_main_reason(run)}): {meaning}"
        )
    for palpation in palpations:
        r_squared = palpation.r_squared.get(2)
        if r_squared is not None and r_squared < R_SQUARED_WARNING:
            warnings.append(
                f"{palpation.name}: the stiffness fit (quadratic, the profile the model uses) has R^2 {r_squared:.3f} "
                f"(below {R_SQUARED_WARNING:g}): force and probe displacement do not follow one stiffness curve, "
                "so the stiffness there is uncertain"
            )
    large = [r for r in regions if np.isfinite(r.held_out_px) and r.held_out_px > HELD_OUT_WARNING_PX]
    if large:
        worst = max(large, key=lambda r: r.held_out_px)
        measured = [r for r in regions if r.samples and np.isfinite(r.held_out_px)]
        warnings.append(
            f"the model misses held-out tracks by more than {HELD_OUT_WARNING_PX:g} px (RMS) in {len(large)} of "
            f"{len(measured)} regions, worst {worst.held_out_px:.2f} px ({worst.held_out_mm:.2f} mm) at "
            f"{worst.depth_mm[0]:g}-{worst.depth_mm[1]:g} mm deep on the {worst.lateral} third "
            f"(all regions: {_pooled_rms(measured, 'held_out_px'):.2f} px): do not trust the correction there"
        )
    return warnings
