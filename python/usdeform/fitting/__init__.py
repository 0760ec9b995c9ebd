"""Fitting: a position's palpations measured and a deformation model fitted to them (paper Section III-A).

:func:`fit_palpations` is the door: each palpation's phases (:func:`detect_phases`: the loading ramp
from contact is fitted), its stiffness (:func:`fit_stiffness`, paper eqs. 4-5), its pixel displacements
and vessel wall (:func:`measure_positions`, :func:`track_vessel_wall`), then the regression with the
settings of a fit method (:data:`FIT_METHODS`). :func:`assess_fit` and :func:`write_fit_report` say what
to read before trusting the model (``usdeform fit --report``).

Behind the door: :mod:`._stiffness`, :mod:`._phases`, :mod:`._vessel_wall`, :mod:`._sampling` (one
palpated position), :mod:`._palpations` (the fit methods and the fit) and :mod:`._report` (the fit report).
"""

from __future__ import annotations

from ._palpations import (
    FIT_METHODS,
    FitMethod,
    FittedPalpations,
    MethodName,
    fit_measured,
    fit_method,
    fit_palpations,
    parse_basis,
)
from ._phases import PalpationPhases, detect_phases
from ._report import (
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
    assess_fit,
    write_fit_report,
)
from ._sampling import SampledPosition, measure_palpation, measure_positions, measure_wall
from ._stiffness import StiffnessFit, fit_stiffness  # first: the modules below use it
from ._vessel_wall import track_vessel_wall

__all__ = [
    "DEFAULT_BAND_MM",
    "DROPPED_WARNING_FRACTION",
    "FIT_METHODS",
    "HELD_OUT_WARNING_PX",
    "LATERAL_REGIONS",
    "MAX_BANDS",
    "R_SQUARED_WARNING",
    "UNRECORDED",
    "DepthBand",
    "FitMethod",
    "FitReport",
    "FittedPalpations",
    "MethodName",
    "PalpationPhases",
    "PalpationReport",
    "RegionResidual",
    "SampledPosition",
    "StiffnessFit",
    "assess_fit",
    "detect_phases",
    "fit_measured",
    "fit_method",
    "fit_palpations",
    "fit_stiffness",
    "measure_palpation",
    "measure_positions",
    "measure_wall",
    "parse_basis",
    "track_vessel_wall",
    "write_fit_report",
]
