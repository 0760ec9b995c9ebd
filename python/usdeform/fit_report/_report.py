"""The fit report (see :mod:`usdeform.fit_report`)."""

from __future__ import annotations

import dataclasses
import html
import json
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from matplotlib.figure import Figure
from scipy.ndimage import map_coordinates

from .._arrays import finite_or_none
from .._html_report import page, section, stiffness_figure, table
from ..errors import FitError, InputError
from ..fitting import FittedPalpations, fit_measured
from ..io._common import atomic_output, outputs_together
from ..metrics import pixel_size_mm
from ..optical_flow import REJECTION_REASONS
from ..regression import DeformationModel, Observations
from ..sampling import SampledPosition

__all__ = [
    "DEFAULT_BAND_MM",
    "DROPPED_WARNING_FRACTION",
    "HELD_OUT_WARNING_PX",
    "R_SQUARED_WARNING",
    "DepthBand",
    "FitReport",
    "PalpationReport",
    "RegionResidual",
    "assess_fit",
    "write_fit_report",
]

#: Depth band width, mm (widened where the frame would have more than :data:`MAX_BANDS` bands).
DEFAULT_BAND_MM = 3.0
#: Most depth bands of the default width: deeper frames get wider bands (whole mm).
MAX_BANDS = 16
#: A depth band where at least this fraction of the tracks was dropped is warned about.
DROPPED_WARNING_FRACTION = 0.5
#: A stiffness fit of the order the model uses (2, the paper's eq. 4) with a lower R^2 is warned about.
R_SQUARED_WARNING = 0.95
#: A region whose held-out residual (RMS of the error's length over its samples) exceeds this is warned
#: about, pixels: several times the tracks' own error (0.1-0.3 px on simulated palpations).
HELD_OUT_WARNING_PX = 1.0
#: The lateral regions of the cross-validation: thirds of the frame's width.
LATERAL_REGIONS = ("left", "middle", "right")
#: Key of the tracks not kept to the last frame whose tracker recorded no reason.
UNRECORDED = "unrecorded"

# The fit's provenance entries that report.json repeats.
_SETTINGS = ("method", "basis", "coupling", "integration", "wall", "anchor", "wall_weight", "flexible_layer_mm")

_REASON_TEXT = {
    "left_frame": "left the frame",
    "texture": "too little texture",
    "lucas_kanade_status": "lost by Lucas-Kanade",
    "block_matching": "disagreed with block matching",
    "forward_backward": "forward-backward error",
    "lucas_kanade_error": "Lucas-Kanade error",
    "correlation": "speckle decorrelated",
    "neighbours": "disagreed with neighbours",
    UNRECORDED: "no reason recorded",
}


@dataclass(frozen=True)
class DepthBand:
    """Tracks whose reference position lies ``depth_mm`` = (from, to) below the probe face: how many
    were tracked, kept to the last frame, and dropped by each check (every reason of
    :data:`~usdeform.optical_flow.REJECTION_REASONS`, zero included)."""

    depth_mm: tuple[float, float]
    tracks: int
    kept: int
    dropped: dict[str, int]

    @property
    def n_dropped(self) -> int:
        """Tracks dropped for any reason."""
        return self.tracks - self.kept

    @property
    def dropped_fraction(self) -> float:
        """Fraction of the band's tracks dropped (0 where it has none)."""
        return self.n_dropped / self.tracks if self.tracks else 0.0

    def to_json(self) -> dict[str, Any]:
        """The band as JSON-able values."""
        return {
            "depth_mm": list(self.depth_mm),
            "tracks": self.tracks,
            "kept": self.kept,
            "dropped": self.n_dropped,
            "dropped_fraction": self.dropped_fraction,
            "reasons": dict(self.dropped),
        }


@dataclass(frozen=True)
class RegionResidual:
    """The displacement residual in one region (a depth band x a lateral third): the RMS over its
    samples (tracks x frames) of the length of (tracked - predicted), pixels and mm, with the model
    refitted without the region's fold (``held_out_*``) and as fitted on everything (``fitted_*``);
    NaN where the region has no samples (or its fold could not be refitted)."""

    depth_mm: tuple[float, float]
    lateral: str
    lateral_mm: tuple[float, float]
    points: int
    samples: int
    held_out_px: float
    held_out_mm: float
    fitted_px: float
    fitted_mm: float

    def to_json(self) -> dict[str, Any]:
        """The region as JSON-able values (None for NaN)."""
        return {
            name: finite_or_none(value) if isinstance(value, float) else value
            for name, value in (
                ("depth_mm", list(self.depth_mm)),
                ("lateral", self.lateral),
                ("lateral_mm", list(self.lateral_mm)),
                ("points", self.points),
                ("samples", self.samples),
                ("held_out_rms_px", self.held_out_px),
                ("held_out_rms_mm", self.held_out_mm),
                ("fitted_rms_px", self.fitted_px),
                ("fitted_rms_mm", self.fitted_mm),
            )
        }


@dataclass(frozen=True)
class PalpationReport:
    """One palpation: its pixel size (lateral, axial mm), its tracks per depth band, their totals per
    reason (``TrackedDisplacements.rejected`` summed over frames), its stiffness fit (R^2 per order,
    k mean and SD in N/m) and the residual of the fitted field at its highest-force frame (row
    ``highest_force_row`` of the tracks, ``highest_force_n``) over the tracks kept there."""

    name: str
    pixel_size_mm: tuple[float, float]
    bands: tuple[DepthBand, ...]
    rejected: dict[str, int]
    r_squared: dict[int, float]
    stiffness_n_per_m: tuple[float, float]
    highest_force_row: int
    highest_force_n: float
    highest_force_rms_px: float
    highest_force_rms_mm: float

    def to_json(self) -> dict[str, Any]:
        """The palpation as JSON-able values."""
        return {
            "name": self.name,
            "pixel_size_mm": list(self.pixel_size_mm),
            "tracks": sum(band.tracks for band in self.bands),
            "kept": sum(band.kept for band in self.bands),
            "rejected": dict(self.rejected),
            "bands": [band.to_json() for band in self.bands],
            "stiffness": {
                "r_squared": {str(order): value for order, value in self.r_squared.items()},
                "k_mean_n_per_m": self.stiffness_n_per_m[0],
                "k_sd_n_per_m": self.stiffness_n_per_m[1],
            },
            "highest_force": {
                "row": self.highest_force_row,
                "force_n": self.highest_force_n,
                "rms_residual_px": finite_or_none(self.highest_force_rms_px),
                "rms_residual_mm": finite_or_none(self.highest_force_rms_mm),
            },
        }


@dataclass(frozen=True, eq=False)
class FitReport:
    """What :func:`assess_fit` found (see the module docstring); ``warnings`` in plain language.

    ``bands`` pools the palpations' bands (same edges in mm); ``regions`` are the cross-validation's
    (depth band x lateral third, those with tracks). ``fitted`` is what was assessed (the report's
    figures draw it and its palpations' loading ramps)."""

    palpations: tuple[PalpationReport, ...]
    bands: tuple[DepthBand, ...]
    regions: tuple[RegionResidual, ...]
    warnings: tuple[str, ...]
    band_mm: float
    n_folds: int
    fitted: FittedPalpations = field(repr=False)

    def to_json(self) -> dict[str, Any]:
        """The numbers of the report as a JSON-able document (``report.json``)."""
        held_out = [r for r in self.regions if r.samples and np.isfinite(r.held_out_px)]
        fit = self.fitted.fit
        return {
            "format": "usdeform-fit-report",
            "version": 1,
            "band_mm": self.band_mm,
            "rejection_reasons": list(REJECTION_REASONS),
            "warnings": list(self.warnings),
            "fit": {
                **{key: value for key, value in self.fitted.provenance.items() if key in _SETTINGS},
                "description": self.fitted.method.description,
                "solver": fit.solver,
                "loss": fit.loss,
                "n_samples": fit.n_samples,
                "smoothness": fit.smoothness,
            },
            "palpations": [p.to_json() for p in self.palpations],
            "palpation_phases": [found.to_json() for found in self.fitted.phases],
            "depth_bands": [band.to_json() for band in self.bands],
            "cross_validation": {
                "folds": self.n_folds,
                "solver": "exact",
                "held_out_rms_px": finite_or_none(_pooled_rms(held_out, "held_out_px")),
                "held_out_rms_mm": finite_or_none(_pooled_rms(held_out, "held_out_mm")),
                "regions": [region.to_json() for region in self.regions],
            },
        }


def _pooled_rms(regions: Sequence[RegionResidual], name: str) -> float:
    """The RMS over all the regions' samples of the residual ``name``."""
    samples = sum(r.samples for r in regions)
    return float(np.sqrt(sum(r.samples * getattr(r, name) ** 2 for r in regions) / samples)) if samples else np.nan


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
    return model.displacement_with_lumen(force_n, observations.profile, shape, observations.vessel)


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
    warnings = _warnings(palpations, pooled, regions)
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


_KEPT_COLOUR = "tab:green"


def _bands_figure(report: FitReport) -> Figure:
    """Per palpation, kept and dropped tracks per depth band, stacked by reason."""
    figure = Figure(figsize=(4.6 * len(report.palpations), 0.28 * len(report.bands) + 2.2))
    axes = np.atleast_1d(figure.subplots(1, len(report.palpations), sharey=True))
    names = [name for name in (*REJECTION_REASONS, UNRECORDED) if any(b.dropped.get(name) for b in report.bands)]
    colours = {name: f"C{index % 10}" for index, name in enumerate(n for n in (*REJECTION_REASONS, UNRECORDED))}
    colours = {name: ("tab:gray" if c == "C2" else c) for name, c in colours.items()}  # C2 is the kept green
    for axis, palpation in zip(axes, report.palpations, strict=True):
        centres = [np.mean(band.depth_mm) for band in palpation.bands]
        heights = [0.9 * (band.depth_mm[1] - band.depth_mm[0]) for band in palpation.bands]
        left = np.array([band.kept for band in palpation.bands], dtype=float)
        axis.barh(centres, left, height=heights, color=_KEPT_COLOUR, label="kept")
        for name in names:
            counts = np.array([band.dropped.get(name, 0) for band in palpation.bands], dtype=float)
            axis.barh(
                centres, counts, height=heights, left=left, color=colours[name], label=_REASON_TEXT.get(name, name)
            )
            left += counts
        axis.set(title=Path(palpation.name).name, xlabel="tracks", ylabel="depth below the probe (mm)")
        axis.title.set_fontsize(9)
        axis.grid(axis="x", alpha=0.3)
    axes[0].invert_yaxis()
    axes[-1].legend(fontsize=7, loc="lower right")
    figure.tight_layout()
    return figure


def _arrow_gain(moves_mm: np.ndarray, width_mm: float) -> float:
    """How many times longer than true to draw displacement arrows so that the longest (95th
    percentile) spans at most 8 % of the frame's width: 1, 2, 5, 10, 20 or 50."""
    length = float(np.percentile(np.linalg.norm(moves_mm, axis=-1), 95)) if len(moves_mm) else 0.0
    fitting = [gain for gain in (1.0, 2.0, 5.0, 10.0, 20.0, 50.0) if gain * length <= 0.08 * width_mm]
    return fitting[-1] if fitting else 1.0


def _field_figure(report: FitReport) -> Figure:
    """Per palpation at its highest force: tracked and fitted arrows on the frame, and the residual map."""
    fitted = report.fitted
    figure = Figure(figsize=(11, 4.6 * len(report.palpations)))
    axes = np.atleast_2d(figure.subplots(len(report.palpations), 2))
    for (arrows, residuals), palpation, measured, recording in zip(
        axes, report.palpations, fitted.measured, fitted.loading_recordings, strict=True
    ):
        tracked, row = measured.tracked, palpation.highest_force_row
        lateral, axial = palpation.pixel_size_mm
        rows, cols = recording.shape
        extent = (0.0, cols * lateral, rows * axial, 0.0)
        kept = tracked.valid[row] if len(tracked.frame_indices) else np.zeros(len(tracked.points_px), bool)
        points = np.flatnonzero(kept)
        model = _predicted(fitted.fit.fitted, measured.observations, points)[row]
        measured_px = tracked.displacements_px[row, points]
        x_mm, y_mm = tracked.points_px[points, 0] * lateral, tracked.points_px[points, 1] * axial
        frame = recording.frames[int(tracked.frame_indices[row])] if len(tracked.frame_indices) else recording.frames[0]
        arrows.imshow(frame, cmap="gray", extent=extent)
        gain = _arrow_gain(measured_px * [lateral, axial], extent[1])
        # The fitted arrows thinner, on top of the tracked ones: both show where they agree.
        for values, colour, width, label in (
            (measured_px, "yellow", 0.007, "tracked"),
            (model, "cyan", 0.003, "fitted"),
        ):
            arrows.quiver(
                x_mm, y_mm, values[:, 0] * lateral, values[:, 1] * axial, color=colour, angles="xy",
                scale_units="xy", scale=1 / gain, width=width, label=label,
            )  # fmt: skip
        arrows.legend(fontsize=7, loc="lower right")
        arrows.set(
            title=f"{Path(palpation.name).name}: {palpation.highest_force_n:.1f} N, {len(points)} of {len(kept)} "
            "tracks kept" + (f" (arrows x{gain:g})" if gain > 1 else ""),
            xlabel="lateral (mm)",
            ylabel="depth (mm)",
        )
        residuals.imshow(frame, cmap="gray", extent=extent, alpha=0.35)
        error = np.linalg.norm(measured_px - model, axis=-1)
        limit = max(float(np.percentile(error, 98)) if error.size else 0.0, 0.5)
        dots = residuals.scatter(x_mm, y_mm, c=error, cmap="magma_r", vmin=0, vmax=limit, s=22, edgecolors="0.3")
        dropped = np.flatnonzero(~kept)
        residuals.scatter(
            tracked.points_px[dropped, 0] * lateral, tracked.points_px[dropped, 1] * axial, marker="x",
            color="red", s=14, linewidths=0.8, label="dropped",
        )  # fmt: skip
        if len(dropped):
            residuals.legend(fontsize=7, loc="lower right")
        residuals.set(
            title=f"|tracked - fitted|: RMS {palpation.highest_force_rms_px:.2f} px "
            f"({palpation.highest_force_rms_mm:.3f} mm)",
            xlabel="lateral (mm)",
            ylabel="depth (mm)",
            xlim=extent[:2],
            ylim=extent[2:],
        )
        figure.colorbar(dots, ax=residuals, fraction=0.046, label="px")
        for axis in (arrows, residuals):
            axis.title.set_fontsize(9)
    figure.tight_layout()
    return figure


def _regions_figure(report: FitReport) -> Figure:
    """The held-out residual per depth band x lateral third, px (and mm) written in each cell."""
    n_bands = len(report.bands)
    grid = np.full((n_bands, 3), np.nan)
    labels: dict[tuple[int, int], str] = {}
    for region in report.regions:
        band = next(i for i, b in enumerate(report.bands) if b.depth_mm == region.depth_mm)
        third = LATERAL_REGIONS.index(region.lateral)
        grid[band, third] = region.held_out_px
        if np.isfinite(region.held_out_px):
            labels[band, third] = f"{region.held_out_px:.2f} px\n{region.held_out_mm:.3f} mm"
    figure = Figure(figsize=(6.4, 0.42 * n_bands + 1.6))
    axis = figure.subplots()
    top = report.bands[-1].depth_mm[1]
    finite = grid[np.isfinite(grid)]
    image = axis.imshow(
        np.ma.masked_invalid(grid),
        cmap="Reds",
        vmin=0,
        vmax=max(float(finite.max()) if finite.size else 0.0, HELD_OUT_WARNING_PX),
        aspect="auto",
        extent=(0, 3, top, 0),
    )
    for (band, third), text in labels.items():
        centre = float(np.mean(report.bands[band].depth_mm))
        axis.text(third + 0.5, centre, text, ha="center", va="center", fontsize=7)
    axis.set_xticks([0.5, 1.5, 2.5], [f"{name} third" for name in LATERAL_REGIONS])
    axis.set(ylabel="depth below the probe (mm)", title="held-out residual (RMS of |tracked - predicted|)")
    axis.title.set_fontsize(9)
    figure.colorbar(image, ax=axis, fraction=0.05, label="px")
    figure.tight_layout()
    return figure


def _band_rows(report: FitReport) -> list[tuple[str, ...]]:
    return [
        (
            f"{band.depth_mm[0]:g}-{band.depth_mm[1]:g}",
            str(band.tracks),
            str(band.kept),
            f"{band.dropped_fraction:.0%}" if band.tracks else "",
            ", ".join(f"{_REASON_TEXT.get(name, name)} {count}" for name, count in band.dropped.items() if count),
        )
        for band in report.bands
    ]


def _summary(report: FitReport) -> str:
    n_tracks = sum(band.tracks for band in report.bands)
    kept = sum(band.kept for band in report.bands)
    document = report.to_json()["cross_validation"]
    held = document["held_out_rms_px"]
    overall = (
        f"; predicted from the other regions, the tracks are off by {held:.2f} px RMS "
        f"({document['held_out_rms_mm']:.3f} mm)"
        if held is not None
        else ""
    )
    head = (
        f"{len(report.palpations)} palpation{'s' if len(report.palpations) > 1 else ''}: {kept} of {n_tracks} tracks "
        f"kept to the highest force{overall}. "
    )
    if not report.warnings:
        return html.escape(head + "No warnings: every depth band kept most of its tracks, the stiffness fits hold "
                           "and the cross-validated residual is small everywhere.")  # fmt: skip
    items = "".join(f"<li>{html.escape(warning)}</li>" for warning in report.warnings)
    return f"{html.escape(head)}Warnings:<ul>{items}</ul>"


def write_fit_report(report: FitReport, out_dir: str | Path) -> tuple[Path, Path]:
    """Write ``report`` as ``out_dir/report.html`` (self-contained) and ``out_dir/report.json``; the
    folder is created if missing; both files replace the old ones together, or neither does (they
    join an enclosing :func:`~usdeform.io._common.outputs_together` block). Returns the two paths."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    fit = report.fitted.fit
    stiffness_rows = [
        (
            palpation.name,
            *(f"{palpation.r_squared[order]:.4f}" for order in sorted(palpation.r_squared)),
            "{:.0f} ± {:.0f}".format(*palpation.stiffness_n_per_m),
        )
        for palpation in report.palpations
    ]
    orders = sorted(report.palpations[0].r_squared)
    region_rows = [
        (
            f"{region.depth_mm[0]:g}-{region.depth_mm[1]:g}",
            region.lateral,
            str(region.points),
            str(region.samples),
            *(f"{value:.2f}" if np.isfinite(value) else "" for value in (region.held_out_px, region.fitted_px)),
            *(f"{value:.3f}" if np.isfinite(value) else "" for value in (region.held_out_mm, region.fitted_mm)),
        )
        for region in report.regions
    ]
    body = "".join(
        [
            "<h1>usdeform fit: can this model be trusted?</h1>",
            f'<div id="summary">{_summary(report)}</div>',
            f"<p>Fitted: {html.escape(report.fitted.method.description)}; the model is tied to the "
            f"{html.escape(str(report.fitted.provenance.get('anchor')))}; {fit.n_samples} samples, loss "
            f"{fit.loss:.4g}{f', smoothness {fit.smoothness:.3g}' if fit.smoothness else ''}. The numbers are also in "
            "<code>report.json</code> beside this page.</p>",
            section(
                "Tracks per depth band",
                "Optical-flow tracks by their depth below the probe face in the lowest-force frame "
                f"({report.band_mm:g} mm bands): kept to the highest force, or dropped by the first check they "
                "failed. Where most tracks were dropped the model has no data and extrapolates (or bridges the gap).",
                _bands_figure(report),
                "tracks per depth band",
            ),
            table(("depth (mm)", "tracks", "kept", "dropped", "dropped by"), _band_rows(report)),
            section(
                "Tracked and fitted field at the highest force",
                "Left: the tracked displacements (yellow) and the fitted model's at the same points (cyan) on the "
                "highest-force frame (lengthened where the title says so). Right: the length of their difference "
                "at each kept track; red crosses mark tracks that were dropped.",
                _field_figure(report),
                "tracked against fitted field",
            ),
            section(
                "Stiffness fits",
                "Force against probe displacement with polynomial fits and their R²; the quadratic is the stiffness "
                "profile the model uses.",
                stiffness_figure(
                    [m.stiffness for m in report.fitted.measured], [Path(p.name).name for p in report.palpations]
                ),
                "stiffness fits",
            ),
            table(("palpation", *(f"R² order {order}" for order in orders), "k (N/m)"), stiffness_rows),
            "<h2>Palpation phases</h2><p>Each palpation's frames by phase; the method is fitted on the loading "
            "ramp from contact, with the probe displacement counted from contact.</p>",
            table(("palpation", "phases"), [(p.name, p.summary()) for p in report.fitted.phases]),
            section(
                "Cross-validated residual by region",
                f"The frame cut into depth bands and lateral thirds; the regions dealt into {report.n_folds} folds, "
                "and each fold's tracks predicted by the model refitted without them (same settings and smoothness). "
                "Held out: how far the model is from tissue it was not fitted to there; fitted: from the tracks it "
                "was fitted to. RMS over the region's tracks and frames.",
                _regions_figure(report),
                "cross-validated residual by region",
            ),
            table(
                (
                    "depth (mm)",
                    "lateral",
                    "tracks",
                    "samples",
                    "held out (px)",
                    "fitted (px)",
                    "held out (mm)",
                    "fitted (mm)",
                ),
                region_rows,
            ),
        ]
    )
    html_path, json_path = out / "report.html", out / "report.json"
    with outputs_together():
        with atomic_output(html_path) as handle:
            handle.write(page("usdeform fit report", body).encode("utf-8"))
        with atomic_output(json_path) as handle:
            handle.write((json.dumps(report.to_json(), indent=1, allow_nan=False) + "\n").encode("utf-8"))
    return html_path, json_path
