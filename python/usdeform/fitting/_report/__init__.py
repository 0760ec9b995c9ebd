"""What to read before trusting a displacement model fitted on one's own palpations (``usdeform fit --report DIR``).

:func:`assess_fit` measures a fit (:func:`usdeform.fitting.fit_palpations`) against its own palpations,
without writing anything:

- **tracks per depth band**: how many optical-flow tracks each band of depth (mm below the probe face)
  kept to the highest force and how many it dropped, by the check that dropped them
  (:data:`usdeform.optical_flow.REJECTION_REASONS`, from ``TrackedDisplacements.dropped_reason``);
- **the field at the highest force**: the tracked displacements against the fitted model's at the same
  points (the residual, px and mm);
- **the palpations' phases**: which frames were approach, loading, hold and unloading, and which
  (the loading ramp from contact) were fitted (:mod:`usdeform.fitting`);
- **the stiffness fits**: R^2 of the polynomial orders :func:`usdeform.fitting.fit_stiffness` reports;
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

The parts: :mod:`._report` (the thresholds and what a report holds, with its JSON), :mod:`._assess`
(:func:`assess_fit`), :mod:`._figures` (the report's figures) and :mod:`._html` (:func:`write_fit_report`).
"""

from __future__ import annotations

from . import _report
from ._assess import assess_fit
from ._html import write_fit_report
from ._report import LATERAL_REGIONS as LATERAL_REGIONS
from ._report import MAX_BANDS as MAX_BANDS
from ._report import UNRECORDED as UNRECORDED
from ._report import DepthBand, FitReport, PalpationReport, RegionResidual

# The thresholds, restated here with their doc comments: the API documentation reads a constant's doc
# comment from the module it documents.
#: Depth band width, mm (widened where the frame would have more than :data:`MAX_BANDS` bands).
DEFAULT_BAND_MM = _report.DEFAULT_BAND_MM
#: A depth band where at least this fraction of the tracks was dropped is warned about.
DROPPED_WARNING_FRACTION = _report.DROPPED_WARNING_FRACTION
#: A stiffness fit of the order the model uses (2, the paper's eq. 4) with a lower R^2 is warned about.
R_SQUARED_WARNING = _report.R_SQUARED_WARNING
#: A region whose held-out residual (RMS of the error's length over its samples) exceeds this is warned
#: about, pixels: several times the tracks' own error (0.1-0.3 px on simulated palpations).
HELD_OUT_WARNING_PX = _report.HELD_OUT_WARNING_PX

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
