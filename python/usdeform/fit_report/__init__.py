"""What to read before trusting a displacement model fitted on one's own palpations (``usdeform fit --report DIR``).

:func:`assess_fit` measures a fit (:func:`usdeform.fitting.fit_palpations`) against its own palpations,
without writing anything:

- **tracks per depth band**: how many optical-flow tracks each band of depth (mm below the probe face)
  kept to the highest force and how many it dropped, by the check that dropped them
  (:data:`usdeform.optical_flow.REJECTION_REASONS`, from ``TrackedDisplacements.dropped_reason``);
- **the field at the highest force**: the tracked displacements against the fitted model's at the same
  points (the residual, px and mm);
- **the palpations' phases**: which frames were approach, loading, hold and unloading, and which
  (the loading ramp from contact) were fitted (:mod:`usdeform.palpation_phases`);
- **the stiffness fits**: R^2 of the polynomial orders :func:`usdeform.stiffness.fit_stiffness` reports;
- **the cross-validated residual by region**: the frame is cut into depth bands x lateral thirds, the
  regions are dealt into ``n_folds`` folds (a fixed shuffle, so the numbers are reproducible), and each
  fold's tracks are predicted by the model refitted without them (same settings and smoothness; the
  exact solver, which the ADAM solver approximates). A region's held-out residual is what the model
  makes of tissue it has not seen there, as correction does between and beyond the tracks;
- **warnings** in plain language, where a user should not trust the model: depth bands where most
  tracks were dropped (:data:`DROPPED_WARNING_FRACTION`: the model is extrapolated or interpolated
  there), a stiffness fit below :data:`R_SQUARED_WARNING`, regions whose held-out residual exceeds
  :data:`HELD_OUT_WARNING_PX`.

:func:`write_fit_report` writes it as ``DIR/report.html`` (self-contained: figures embedded, opens
without a server) and ``DIR/report.json`` (the same numbers, for pipelines), each atomically.

"""

from __future__ import annotations

from ._report import (
    DEFAULT_BAND_MM,
    DROPPED_WARNING_FRACTION,
    HELD_OUT_WARNING_PX,
    R_SQUARED_WARNING,
    DepthBand,
    FitReport,
    PalpationReport,
    RegionResidual,
    assess_fit,
    write_fit_report,
)
from ._report import LATERAL_REGIONS as LATERAL_REGIONS
from ._report import MAX_BANDS as MAX_BANDS
from ._report import UNRECORDED as UNRECORDED

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
