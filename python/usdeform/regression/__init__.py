"""The coupled quadratic displacement regression (paper eqs. 7-9 and 12).

``d(x, y, h) = K @ M(x, y, h)`` with ``M = [x^2, y^2, h^2, xy, xh, yh, x, y, h, 1]`` on normalised
inputs and ``h = F / k`` (mm). The displacement at force ``F`` is the integral of ``d`` over the
normalised force from 0 to ``F``, in closed form for the quadratic stiffness profile (the compiled
core's ``force_integrals``). Displacements are in pixels, ``(lateral, axial)`` = ``(x, y)``.

The same force terms can multiply another spatial basis: :class:`BSplineDisplacementModel` uses a
tensor-product cubic B-spline in ``(x, y)`` with free ``1``, ``h`` and ``h^2`` coefficients on every
function, for fields the paper's quadratic cannot follow.

Both live in image coordinates, so a vessel's local collapse stays where the vessel was in the fitted
palpations. :class:`VesselAnchoredModel` (``fit_regression(..., anchor="vessel")``) adds a finer
B-spline part on a window around the lumen, in coordinates measured from the lumen's centre in units
of its radius: correction places it on each frame's own lumen, so the collapse follows a vessel that
moves along the sweep or differs in size (another tissue).

The parts: :mod:`._basis` (the spatial functions), :mod:`._model` (the models in image coordinates
and the interface every model offers), :mod:`._anchored` (the vessel-anchored model),
:mod:`._observations` (measured displacements and a fit's samples), :mod:`._smoothness` (the
cross-validated smoothness weight) and :mod:`._fit` (:func:`fit_regression`).
"""

from __future__ import annotations

from ..options import COUPLINGS, INTEGRATIONS  # re-exported (batch.manifest takes them from here)
from ._anchored import VesselAnchoredModel
from ._basis import (
    BSPLINE_MIN_FUNCTIONS,
    M_TERMS,
    VESSEL_KNOT_SPACING_RADII,
    VESSEL_WINDOW_RADII,
    LumenTrack,
    VesselAnchor,
    bspline_basis,
    bspline_vector,
    regression_vector,
    vessel_basis,
)
from ._fit import RegressionFit, fit_regression
from ._model import (
    MAX_MODEL_DISPLACEMENT_PX,
    BSplineDisplacementModel,
    DeformationModel,
    DisplacementModel,
    Normalization,
    QuadraticDisplacementModel,
    check_model,
    correction_forces,
    force_terms,
)
from ._observations import Observations, SpatialVector
from ._smoothness import (
    CV_REGIONS_PER_SIDE,
    NEGLIGIBLE_RELATIVE_SMOOTHNESS,
    SMOOTHNESS_GRID,
    SMOOTHNESS_WIDENING_DECADES,
)
from ._stiffness_profile import StiffnessProfile, profiles_array

__all__ = [
    "BSPLINE_MIN_FUNCTIONS",
    "COUPLINGS",
    "CV_REGIONS_PER_SIDE",
    "INTEGRATIONS",
    "MAX_MODEL_DISPLACEMENT_PX",
    "M_TERMS",
    "NEGLIGIBLE_RELATIVE_SMOOTHNESS",
    "SMOOTHNESS_GRID",
    "SMOOTHNESS_WIDENING_DECADES",
    "VESSEL_KNOT_SPACING_RADII",
    "VESSEL_WINDOW_RADII",
    "BSplineDisplacementModel",
    "DeformationModel",
    "DisplacementModel",
    "LumenTrack",
    "Normalization",
    "Observations",
    "QuadraticDisplacementModel",
    "RegressionFit",
    "SpatialVector",
    "StiffnessProfile",
    "VesselAnchor",
    "VesselAnchoredModel",
    "bspline_basis",
    "bspline_vector",
    "check_model",
    "correction_forces",
    "fit_regression",
    "force_terms",
    "profiles_array",
    "regression_vector",
    "vessel_basis",
]
