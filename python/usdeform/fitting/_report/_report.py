"""What a fit report holds (:class:`FitReport` and its parts, each with its JSON) and the thresholds of
its warnings."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from ..._arrays import finite_or_none
from ...optical_flow import REJECTION_REASONS
from .._palpations import FittedPalpations

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
            "palpated_lumens": self.palpated_lumens(),
            "depth_bands": [band.to_json() for band in self.bands],
            "cross_validation": {
                "folds": self.n_folds,
                "solver": "exact",
                "held_out_rms_px": finite_or_none(_pooled_rms(held_out, "held_out_px")),
                "held_out_rms_mm": finite_or_none(_pooled_rms(held_out, "held_out_mm")),
                "regions": [region.to_json() for region in self.regions],
            },
        }

    def palpated_lumens(self) -> list[dict[str, Any]]:
        """Each palpation's lumens at contact, vessel by vessel (0: the main one): depth of the centre below the
        image's top row and equivalent radius, mm. A vessel-anchored model learnt each vessel's collapse there;
        ``usdeform correct`` warns for sweep frames whose lumens lie beyond them
        (:func:`usdeform.correction.uncovered_lumens`)."""
        from ...metrics import pixel_size_mm

        rows = []
        for palpation, measured, recording in zip(
            self.palpations, self.fitted.measured, self.fitted.loading_recordings, strict=True
        ):
            width, height = pixel_size_mm(recording.image_to_probe)
            lumens = (measured.observations.vessel, *measured.observations.other_vessels)
            rows += [
                {
                    "palpation": palpation.name,
                    "vessel": vessel,
                    "depth_mm": lumen.centre_px[1] * height,
                    "radius_mm": lumen.radius_px * float(np.sqrt(width * height)),
                }
                for vessel, lumen in enumerate(lumens)
                if lumen is not None
            ]
        return rows


def _pooled_rms(regions: Sequence[RegionResidual], name: str) -> float:
    """The RMS over all the regions' samples of the residual ``name``."""
    samples = sum(r.samples for r in regions)
    return float(np.sqrt(sum(r.samples * getattr(r, name) ** 2 for r in regions) / samples)) if samples else np.nan
