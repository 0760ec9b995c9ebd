"""The coupled quadratic displacement regression (paper eqs. 7-9 and 12).

``d(x, y, h) = K @ M(x, y, h)`` with ``M = [x^2, y^2, h^2, xy, xh, yh, x, y, h, 1]`` on normalised
inputs and ``h = F / k`` (mm). The displacement at force ``F`` is the integral of ``d`` over the
normalised force from 0 to ``F``, with the stiffness ``k`` held constant on each of ``n_intervals``
equal force intervals. Displacements are in pixels, ``(lateral, axial)`` = ``(x, y)``.

The same force terms can multiply another spatial basis: :class:`BSplineDisplacementModel` uses a
tensor-product cubic B-spline in ``(x, y)`` with free ``1``, ``h`` and ``h^2`` coefficients on every
function, for fields the paper's quadratic cannot follow.

Both live in image coordinates, so a vessel's local collapse stays where the vessel was in the fitted
palpations. :class:`VesselAnchoredModel` (``fit_regression(..., anchor="vessel")``) adds a finer
B-spline part on a window around the lumen, in coordinates measured from the lumen's centre in units
of its radius: correction places it on each frame's own lumen, so the collapse follows a vessel that
moves along the sweep or differs in size (another tissue).
"""

from __future__ import annotations

import dataclasses
import warnings
from abc import ABC, abstractmethod
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from functools import partial
from typing import ClassVar, Protocol

import numpy as np
import scipy.linalg
from scipy.interpolate import BSpline
from threadpoolctl import threadpool_limits

from . import _core
from ._arrays import forces_array
from .errors import FitError, InputError
from .options import ANCHORS, COUPLINGS, INTEGRATIONS, SOLVERS, Anchor, Basis, Coupling, Integration, Solver
from .stiffness import StiffnessProfile
from .validation import MAX_INTERVALS, forces_in_range

__all__ = [
    "MAX_MODEL_DISPLACEMENT_PX",
    "M_TERMS",
    "VESSEL_KNOT_SPACING_RADII",
    "VESSEL_WINDOW_RADII",
    "BSplineDisplacementModel",
    "DeformationModel",
    "DisplacementModel",
    "Normalization",
    "Observations",
    "QuadraticDisplacementModel",
    "RegressionFit",
    "VesselAnchor",
    "VesselAnchoredModel",
    "bspline_basis",
    "bspline_vector",
    "check_model",
    "correction_forces",
    "fit_regression",
    "force_terms",
    "regression_vector",
    "vessel_basis",
]

#: Names of the regression terms, in the order of the columns of K.
M_TERMS = ("x^2", "y^2", "h^2", "xy", "xh", "yh", "x", "y", "h", "1")
#: Fewest cubic B-splines per axis of :class:`BSplineDisplacementModel` (one knot span).
BSPLINE_MIN_FUNCTIONS = 4


@dataclass(frozen=True)
class Normalization:
    """Scales between physical values and the regression's normalised [0, 1] inputs.

    ``x_n = x / x_scale`` and ``y_n = y / y_scale`` (pixels), ``F_n = F / force_scale`` (N),
    ``h_n = h / h_scale`` (mm); the model's normalised output is multiplied by ``lateral_scale``
    and ``axial_scale`` to give pixels.

    Parameters
    ----------
    x_scale, y_scale : float
        Pixel coordinate divisors (pixels, > 0).
    force_scale : float
        Force divisor (N, > 0).
    h_scale : float
        ``h`` divisor (mm, > 0).
    lateral_scale, axial_scale : float
        Displacement multipliers (pixels).

    Examples
    --------
    >>> Normalization.for_frames(64, 128, max_force_n=20.0, max_h_mm=5.0).frame_shape
    (64, 128)
    """

    x_scale: float
    y_scale: float
    force_scale: float
    h_scale: float
    lateral_scale: float = 1.0
    axial_scale: float = 1.0

    def __post_init__(self) -> None:
        values = self.as_array()
        if not np.all(np.isfinite(values)):
            raise InputError(f"Normalization: values must be finite, got {values.tolist()}")
        if np.any(values[:4] <= 0):
            raise InputError(
                f"Normalization: x_scale, y_scale, force_scale, h_scale must be positive, got {values[:4].tolist()}"
            )

    @classmethod
    def for_frames(
        cls,
        rows: int,
        cols: int,
        max_force_n: float,
        max_h_mm: float,
        lateral_scale: float = 1.0,
        axial_scale: float = 1.0,
    ) -> Normalization:
        """Pixel coordinates, force and h each mapped onto [0, 1] over a frame of ``rows x cols``.

        Parameters
        ----------
        rows, cols : int
            Frame shape, pixels.
        max_force_n : float
            Largest force, N.
        max_h_mm : float
            Largest ``h``, mm.
        lateral_scale, axial_scale : float
            Displacement multipliers, pixels.

        Returns
        -------
        Normalization
        """
        return cls(
            float(max(cols - 1, 1)),
            float(max(rows - 1, 1)),
            float(max_force_n),
            float(max_h_mm),
            float(lateral_scale),
            float(axial_scale),
        )

    @property
    def frame_shape(self) -> tuple[int, int]:
        """The ``(rows, cols)`` that :meth:`for_frames` normalises over: ``round(scale) + 1`` per axis.

        Models that do not state their frame shape (and model files of version 1) take it from here.
        """
        return round(self.y_scale) + 1, round(self.x_scale) + 1

    def as_array(self) -> np.ndarray:
        """The six scales as a float64 array, in field order."""
        return np.array(
            [self.x_scale, self.y_scale, self.force_scale, self.h_scale, self.lateral_scale, self.axial_scale],
            dtype=np.float64,
        )


def force_terms(
    force_n: float,
    profile: StiffnessProfile,
    normalization: Normalization,
    n_intervals: int,
    integration: Integration = "force",
) -> tuple[float, float, float]:
    """Normalised integrals of ``1``, ``h`` and ``h^2`` from 0 to ``force_n`` (paper eq. 8).

    Parameters
    ----------
    force_n : float
        Upper limit of the integral, N.
    profile : StiffnessProfile
        The tissue's stiffness profile (used as given: no coupling applied).
    normalization : Normalization
        Scales of the normalised inputs.
    n_intervals : int
        Equal force intervals of the integral.
    integration : {"force", "displacement"}
        Integrate over force or over probe displacement (normalised by ``h_scale``).

    Returns
    -------
    tuple of float
        The integrals of ``1``, ``h_n`` and ``h_n^2``.
    """
    return _core.force_integrals(
        float(force_n), profile.as_tuple(), normalization.as_array(), int(n_intervals), integration
    )


#: Largest displacement bound a model may have, pixels (a fitted model moves pixels by a fraction
#: of its frame, at most 65536 pixels; coefficients of 1e300 move them out of any frame).
MAX_MODEL_DISPLACEMENT_PX = 1e6


class DeformationModel(Protocol):
    """What every fitted model offers, whatever it is anchored to: a :class:`DisplacementModel`
    (image coordinates) or a :class:`VesselAnchoredModel` (an image part plus a part that follows the
    vessel's lumen). The correction stage dispatches on the model's type
    (:func:`usdeform.correction.correct_frames`); everything else goes through these members."""

    #: ``"image"``: the model lives in image coordinates alone; ``"vessel"``: a part follows the lumen.
    anchor: ClassVar[Anchor]

    @property
    def image_model(self) -> DisplacementModel:
        """The part in image coordinates (a :class:`DisplacementModel` is its own)."""

    @property
    def frame_shape(self) -> tuple[int, int] | None:
        """``(rows, cols)`` of the frames the model was fitted on (always set on a model)."""

    @property
    def normalization(self) -> Normalization:
        """Scales of the normalised inputs and outputs."""

    @property
    def coupling(self) -> Coupling:
        """The force/stiffness coupling."""

    @property
    def integration(self) -> Integration:
        """What the rate is integrated over."""

    def displacement(self, force_n: float, profile: StiffnessProfile, shape: tuple[int, int]) -> np.ndarray:
        """``D(x, y, F)`` (2, rows, cols), pixels, at ``force_n`` (N); a vessel part on the fitted lumen."""
        ...

    def displacement_with_lumen(
        self, force_n: float, profile: StiffnessProfile, shape: tuple[int, int], lumen: VesselAnchor | None
    ) -> np.ndarray:
        """``D(x, y, F)`` (2, rows, cols), pixels, at ``force_n`` (N) with a vessel part placed on
        ``lumen`` (None: without the vessel part, as the fit treats a palpation that shows no lumen)."""
        ...

    def coefficient_fields(self) -> dict[str, np.ndarray]:
        """The model's coefficient arrays by field name (normalised units)."""
        ...


@dataclass(frozen=True, eq=False)
class DisplacementModel(ABC):
    """The displacement model shared by every spatial basis.

    The model is converted once into the compiled :class:`usdeform._core.Model` that every kernel
    takes (:attr:`kernel`); the force/stiffness coupling is applied there and nowhere else.

    Parameters
    ----------
    coefficients : ndarray
        The coefficients, shaped by the basis (see the subclasses).
    normalization : Normalization
        Scales of the normalised inputs and outputs.
    n_intervals : int
        Equal force intervals of the integral (paper eq. 8).
    coupling : {"stiffness", "force"}
        ``h = F / k`` (the paper) or ``h = F`` (the force-based baseline of Sun et al. 2010, which
        ignores the stiffness profile it is given).
    integration : {"force", "displacement"}
        The paper's integral over force, or over probe displacement (``dlambda = dF / k``: every
        term then follows a change of stiffness; see :mod:`usdeform.experiments.paper_2d`).
    frame_shape : tuple of int, optional
        ``(rows, cols)`` of the frames the model was fitted on; frames of any other shape are
        refused. None: :attr:`Normalization.frame_shape`.
    """

    #: The basis name of the compiled model.
    basis: ClassVar[Basis]
    #: A model in image coordinates alone (see :class:`DeformationModel`).
    anchor: ClassVar[Anchor] = "image"

    coefficients: np.ndarray
    normalization: Normalization
    n_intervals: int = 64
    coupling: Coupling = "stiffness"
    integration: Integration = "force"
    frame_shape: tuple[int, int] | None = None

    def __post_init__(self) -> None:
        coefficients = np.array(self.coefficients, dtype=np.float64, order="C")
        self._check_shape(coefficients.shape)
        if not np.all(np.isfinite(coefficients)):
            raise InputError("coefficients: contain non-finite values")
        if not 1 <= int(self.n_intervals) <= MAX_INTERVALS:
            raise InputError(f"n_intervals: expected 1 to {MAX_INTERVALS}, got {self.n_intervals}")
        if self.coupling not in COUPLINGS:
            raise InputError(f"coupling: expected one of {COUPLINGS}, got {self.coupling!r}")
        if self.integration not in INTEGRATIONS:
            raise InputError(f"integration: expected one of {INTEGRATIONS}, got {self.integration!r}")
        frame_shape = self.normalization.frame_shape if self.frame_shape is None else self.frame_shape
        if len(frame_shape) != 2 or min(frame_shape) < 1:
            raise InputError(f"frame_shape: expected (rows, cols) of at least one pixel, got {frame_shape!r}")
        coefficients.setflags(write=False)
        object.__setattr__(self, "coefficients", coefficients)
        object.__setattr__(self, "n_intervals", int(self.n_intervals))
        frame_shape = (int(frame_shape[0]), int(frame_shape[1]))
        object.__setattr__(self, "frame_shape", frame_shape)
        kernel = _core.Model(
            self.basis,
            coefficients,
            self.normalization.as_array(),
            n_intervals=self.n_intervals,
            coupling=self.coupling,
            integration=self.integration,
            frame_shape=frame_shape,
        )
        object.__setattr__(self, "_kernel", kernel)

    def __reduce__(self) -> tuple[type[DisplacementModel], tuple[object, ...]]:
        """Pickle the fields; the compiled model is rebuilt on loading."""
        fields = (self.coefficients, self.normalization, self.n_intervals, self.coupling, self.integration)
        return type(self), (*fields, self.frame_shape)

    @property
    def kernel(self) -> _core.Model:
        """The compiled model the kernels take, built once."""
        kernel: _core.Model = self.__dict__["_kernel"]
        return kernel

    @property
    def image_model(self) -> DisplacementModel:
        """The model itself: it lives in image coordinates (see :class:`DeformationModel`)."""
        return self

    def coefficient_fields(self) -> dict[str, np.ndarray]:
        """``{"coefficients": ...}`` (see :class:`DeformationModel`)."""
        return {"coefficients": self.coefficients}

    def displacement_with_lumen(
        self, force_n: float, profile: StiffnessProfile, shape: tuple[int, int], lumen: VesselAnchor | None
    ) -> np.ndarray:
        """:meth:`displacement`: the model has no part that follows the lumen."""
        return self.displacement(force_n, profile, shape)

    @abstractmethod
    def _check_shape(self, shape: tuple[int, ...]) -> None:
        """Raise InputError unless ``shape`` is a coefficient shape of the basis."""

    @abstractmethod
    def spatial_vector(self, x_n: np.ndarray, y_n: np.ndarray, h_terms: tuple[float, float, float]) -> np.ndarray:
        """The model's terms at normalised points, shape (n_terms, *x_n.shape), so that the
        normalised displacement is ``coefficients.reshape(2, -1) @ terms``."""

    def rate(self, h_mm: float, shape: tuple[int, int]) -> np.ndarray:
        """``d(x, y, h)`` on a ``(rows, cols)`` pixel grid.

        Parameters
        ----------
        h_mm : float
            ``h``, mm.
        shape : tuple of int
            ``(rows, cols)`` of the grid.

        Returns
        -------
        ndarray
            (2, rows, cols), pixels per unit normalised force.
        """
        rows, cols = shape
        return self.kernel.rate(float(h_mm), rows, cols)

    def force_integrals(self, force_n: float, profile: StiffnessProfile) -> tuple[float, float, float]:
        """Normalised integrals of ``1``, ``h`` and ``h^2`` from 0 to ``force_n`` (N), with the
        model's coupling applied to ``profile``."""
        return self.kernel.force_integrals(float(force_n), profile.as_tuple())

    def displacement(self, force_n: float, profile: StiffnessProfile, shape: tuple[int, int]) -> np.ndarray:
        """``D(x, y, F)``: where each zero-force pixel sits at ``force_n``.

        Parameters
        ----------
        force_n : float
            Force, N.
        profile : StiffnessProfile
            The tissue's stiffness profile (ignored by force coupling).
        shape : tuple of int
            ``(rows, cols)`` of the grid.

        Returns
        -------
        ndarray
            (2, rows, cols), pixels.
        """
        rows, cols = shape
        return self.kernel.displacement(float(force_n), profile.as_tuple(), rows, cols)


@dataclass(frozen=True, eq=False)
class QuadraticDisplacementModel(DisplacementModel):
    """The paper's model: ``K`` (2 x 10: lateral row, axial row, columns in the order of
    :data:`M_TERMS`); see :class:`DisplacementModel` for the other fields."""

    basis: ClassVar[Basis] = "quadratic"

    def _check_shape(self, shape: tuple[int, ...]) -> None:
        if shape != (2, 10):
            raise InputError(f"coefficients: expected shape (2, 10), got {shape}")

    def spatial_vector(self, x_n: np.ndarray, y_n: np.ndarray, h_terms: tuple[float, float, float]) -> np.ndarray:
        """``M`` of paper eq. 7 (see :func:`regression_vector`)."""
        return regression_vector(x_n, y_n, h_terms)


@dataclass(frozen=True, eq=False)
class BSplineDisplacementModel(DisplacementModel):
    """A tensor-product cubic B-spline model: ``D = sum_ij B_i(y_n) B_j(x_n) (a_ij I1 + b_ij Ih +
    c_ij Ih2)`` per component, with ``I1, Ih, Ih2`` the force integrals of ``1, h, h^2``.

    ``coefficients`` has shape (2, 3, n_y, n_x): component (lateral, axial), force term (``1``,
    ``h``, ``h^2``), ``y`` function, ``x`` function; ``n_y, n_x >= 4`` cubic B-splines on uniform
    clamped knots over the normalised [0, 1] (end pieces extended beyond). Normalised units as for
    the quadratic model; see :class:`DisplacementModel` for the other fields.
    """

    basis: ClassVar[Basis] = "bspline"

    def _check_shape(self, shape: tuple[int, ...]) -> None:
        if len(shape) != 4 or shape[:2] != (2, 3) or min(shape[2:]) < BSPLINE_MIN_FUNCTIONS:
            raise InputError(
                f"coefficients: expected shape (2, 3, n_y, n_x) with n_y, n_x >= {BSPLINE_MIN_FUNCTIONS}, got {shape}"
            )

    @property
    def n_functions(self) -> tuple[int, int]:
        """Basis functions along ``(y, x)``."""
        return self.coefficients.shape[2], self.coefficients.shape[3]

    def spatial_vector(self, x_n: np.ndarray, y_n: np.ndarray, h_terms: tuple[float, float, float]) -> np.ndarray:
        """The B-spline terms (see :func:`bspline_vector`)."""
        return bspline_vector(x_n, y_n, h_terms, self.n_functions)


def regression_vector(x_n: np.ndarray, y_n: np.ndarray, h_terms: tuple[float, float, float]) -> np.ndarray:
    """``M`` of paper eq. 7 with its ``(1, h, h^2)`` factors replaced by ``h_terms``: shape (10, *x_n.shape).

    ``h_terms = (1, h, h^2)`` gives ``M(x, y, h)``; the force integrals of ``1, h, h^2`` give the
    integral of ``M`` over force (eq. 8), which is how the displacement is linear in ``K``.
    """
    one, h, h2 = h_terms
    return np.stack(
        [
            x_n**2 * one,
            y_n**2 * one,
            np.full_like(x_n, h2),
            x_n * y_n * one,
            x_n * h,
            y_n * h,
            x_n * one,
            y_n * one,
            np.full_like(x_n, h),
            np.full_like(x_n, one),
        ]
    )


def bspline_basis(u: np.ndarray, n_functions: int) -> np.ndarray:
    """The ``n_functions`` cubic B-splines on uniform clamped knots over [0, 1] at normalised ``u``
    (end pieces extended outside): shape (n_functions, *u.shape)."""
    u = np.asarray(u, dtype=np.float64)
    knots = np.concatenate([np.zeros(3), np.linspace(0.0, 1.0, n_functions - 2), np.ones(3)])
    matrix = BSpline.design_matrix(u.ravel(), knots, 3, extrapolate=True).toarray()
    return matrix.T.reshape(n_functions, *u.shape)


def bspline_vector(
    x_n: np.ndarray, y_n: np.ndarray, h_terms: tuple[float, float, float], n_functions: tuple[int, int]
) -> np.ndarray:
    """The B-spline model's terms ``h_term * B_i(y_n) B_j(x_n)`` in the order (term, i, j) of its
    coefficients: shape (3 * n_y * n_x, *x_n.shape)."""
    n_y, n_x = n_functions
    spatial = bspline_basis(y_n, n_y)[:, np.newaxis] * bspline_basis(x_n, n_x)[np.newaxis]
    return np.concatenate([term * spatial.reshape(n_y * n_x, *np.shape(x_n)) for term in h_terms])


#: Half-width of the vessel-anchored basis's square window around the lumen centre, in lumen radii.
#: A lumen perturbs the strain of the tissue around it by about ``(radius / distance)^2`` (Kirsch's
#: solution for a hole in a strained plate): a quarter at two radii, where the smooth field of the
#: probe contact (the image-anchored part) takes over.
VESSEL_WINDOW_RADII = 2.0
#: Knot spacing of the vessel-anchored basis, in lumen radii: the collapse of a round lumen is
#: mostly its oval mode (``cos 2 theta`` around the wall), which half-radius knots resolve.
VESSEL_KNOT_SPACING_RADII = 0.5


@dataclass(frozen=True)
class VesselAnchor:
    """Where a vessel's lumen lies in a frame: its centre ``centre_px`` (x, y) and equivalent radius
    ``radius_px`` (``sqrt(area / pi)``), pixels.

    Examples
    --------
    >>> mask = np.zeros((32, 32), dtype=bool)
    >>> mask[10:20, 4:14] = True
    >>> VesselAnchor.of_mask(mask).centre_px
    (8.5, 14.5)
    """

    centre_px: tuple[float, float]
    radius_px: float

    def __post_init__(self) -> None:
        centre = tuple(float(c) for c in self.centre_px)
        if len(centre) != 2 or not np.all(np.isfinite(centre)):
            raise InputError(f"centre_px: expected a finite (x, y), got {self.centre_px!r}")
        if not (np.isfinite(self.radius_px) and self.radius_px > 0):
            raise InputError(f"radius_px: expected a positive radius in pixels, got {self.radius_px!r}")
        object.__setattr__(self, "centre_px", centre)
        object.__setattr__(self, "radius_px", float(self.radius_px))

    @classmethod
    def of_mask(cls, mask: np.ndarray) -> VesselAnchor:
        """The centroid and equivalent radius of a lumen ``mask`` (rows, cols) of at least one pixel."""
        pixels = np.argwhere(np.asarray(mask, dtype=bool))
        if len(pixels) == 0:
            raise InputError("mask: the lumen mask is empty")
        row, col = pixels.mean(axis=0)
        return cls((float(col), float(row)), float(np.sqrt(len(pixels) / np.pi)))


def _window_coordinates(
    x_px: np.ndarray, y_px: np.ndarray, anchor: VesselAnchor, window_radii: float
) -> tuple[np.ndarray, np.ndarray]:
    """Pixel coordinates as the vessel window's normalised [0, 1] coordinates (lumen centre at 0.5)."""
    width = 2.0 * window_radii * anchor.radius_px
    return (x_px - anchor.centre_px[0]) / width + 0.5, (y_px - anchor.centre_px[1]) / width + 0.5


def _window_functions(u: np.ndarray, n_functions: int) -> np.ndarray:
    """The inner ``n_functions - 4`` cubic B-splines of a clamped basis of ``n_functions`` over the
    window [0, 1], zero outside it: (n_functions - 4, *u.shape). Leaving out the two outer functions
    at each end makes the vessel part vanish with its slope at the window's edge (C1)."""
    inside = (u >= 0.0) & (u <= 1.0)
    functions: np.ndarray = bspline_basis(np.clip(u, 0.0, 1.0), n_functions)[2:-2] * inside
    return functions


def vessel_basis(
    x_px: np.ndarray,
    y_px: np.ndarray,
    anchor: VesselAnchor,
    reference_radius_px: float,
    n_functions: int,
    window_radii: float = VESSEL_WINDOW_RADII,
) -> np.ndarray:
    """The vessel-anchored spatial functions at pixel points: (n_inner^2, *x_px.shape), in the (y, x)
    order of the coefficient grid, with ``n_inner = n_functions - 4``.

    The window follows the lumen: coordinates are measured from ``anchor``'s centre in units of its
    radius, and the functions are scaled by ``radius / reference_radius_px``, so that a lumen twice
    as large gets the same collapse twice as large (the displacement around a hole in a strained
    elastic medium scales with the hole).
    """
    u, v = _window_coordinates(np.asarray(x_px, float), np.asarray(y_px, float), anchor, window_radii)
    along_y, along_x = _window_functions(v, n_functions), _window_functions(u, n_functions)
    spatial = along_y[:, np.newaxis] * along_x[np.newaxis] * (anchor.radius_px / reference_radius_px)
    return spatial.reshape(-1, *np.shape(x_px))


@dataclass(frozen=True, eq=False)
class VesselAnchoredModel:
    """A displacement model in two parts: ``image_model``, tied to the image (the probe's contact),
    plus a cubic B-spline part tied to the vessel, whose window moves and scales with the lumen of
    the frame it corrects (:func:`usdeform.vessel_correction.correct_vessel_anchored` finds it).

    A model in image coordinates carries the local collapse it learnt to where the vessel was in
    the fitted palpations; where the vessel lies elsewhere along the sweep (or in another tissue)
    this model carries it with the vessel.

    Parameters
    ----------
    image_model : DisplacementModel
        The part in image coordinates (its normalisation, force terms and coupling serve both parts).
    vessel_coefficients : ndarray
        (2, 3, n, n): component, force term (``1``, ``h``, ``h^2``), the inner functions of a
        clamped basis of ``n + 4`` over the window (see :func:`vessel_basis`), normalised units.
    reference : VesselAnchor
        The fitted palpations' lumen (mean centre and radius): the radius the vessel part is scaled
        from, and where it is applied when a frame's lumen is not found.
    window_radii : float
        Half-width of the window, lumen radii.
    """

    #: A part follows the lumen (see :class:`DeformationModel`).
    anchor: ClassVar[Anchor] = "vessel"

    image_model: DisplacementModel
    vessel_coefficients: np.ndarray
    reference: VesselAnchor
    window_radii: float = VESSEL_WINDOW_RADII

    def __post_init__(self) -> None:
        coefficients = np.array(self.vessel_coefficients, dtype=np.float64, order="C")
        if coefficients.ndim != 4 or coefficients.shape[:2] != (2, 3) or coefficients.shape[2] != coefficients.shape[3]:
            raise InputError(f"vessel_coefficients: expected shape (2, 3, n, n), got {coefficients.shape}")
        if not np.all(np.isfinite(coefficients)):
            raise InputError("vessel_coefficients: contain non-finite values")
        if not (np.isfinite(self.window_radii) and self.window_radii > 0):
            raise InputError(f"window_radii: expected a positive number of radii, got {self.window_radii!r}")
        coefficients.setflags(write=False)
        object.__setattr__(self, "vessel_coefficients", coefficients)

    @property
    def frame_shape(self) -> tuple[int, int]:
        """``(rows, cols)`` of the frames the model was fitted on."""
        assert self.image_model.frame_shape is not None  # set by DisplacementModel.__post_init__
        return self.image_model.frame_shape

    @property
    def normalization(self) -> Normalization:
        """The scales of both parts."""
        return self.image_model.normalization

    @property
    def coupling(self) -> Coupling:
        """The force/stiffness coupling of both parts."""
        return self.image_model.coupling

    @property
    def integration(self) -> Integration:
        """What both parts are integrated over."""
        return self.image_model.integration

    @property
    def n_functions(self) -> int:
        """Functions per axis of the clamped window basis (the inner ones carry coefficients)."""
        return self.vessel_coefficients.shape[2] + 4

    def vessel_displacement(
        self,
        force_n: float,
        profile: StiffnessProfile,
        shape: tuple[int, int],
        anchor: VesselAnchor,
        *,
        window: tuple[slice, slice] | None = None,
    ) -> np.ndarray:
        """The vessel part of ``D(x, y, F)`` with the lumen at ``anchor``: (2, rows, cols), pixels; with
        ``window`` (a row and a column slice of the frame), on those pixels only."""
        rows, cols = shape
        row_slice, column_slice = window or (slice(None), slice(None))
        integrals = np.array(self.image_model.force_integrals(force_n, profile))
        x, y = np.arange(cols, dtype=np.float64)[column_slice], np.arange(rows, dtype=np.float64)[row_slice]
        u, v = _window_coordinates(x, y, anchor, self.window_radii)
        along_y, along_x = _window_functions(v, self.n_functions), _window_functions(u, self.n_functions)
        grid = np.tensordot(integrals, self.vessel_coefficients, axes=([0], [1]))  # (2, n, n)
        field = along_y.T @ grid @ along_x * (anchor.radius_px / self.reference.radius_px)  # (2, rows, cols)
        field[0] *= self.normalization.lateral_scale
        field[1] *= self.normalization.axial_scale
        return field

    def displacement(
        self,
        force_n: float,
        profile: StiffnessProfile,
        shape: tuple[int, int],
        anchor: VesselAnchor | None = None,
    ) -> np.ndarray:
        """``D(x, y, F)`` with the lumen at ``anchor`` (None: at :attr:`reference`): (2, rows, cols), pixels."""
        image_part = self.image_model.displacement(force_n, profile, shape)
        return image_part + self.vessel_displacement(force_n, profile, shape, anchor or self.reference)

    def displacement_with_lumen(
        self, force_n: float, profile: StiffnessProfile, shape: tuple[int, int], lumen: VesselAnchor | None
    ) -> np.ndarray:
        """``D(x, y, F)`` with the vessel part on ``lumen``; the image part alone where ``lumen`` is None
        (as the fit treats a palpation that shows no lumen): (2, rows, cols), pixels."""
        if lumen is None:
            return self.image_model.displacement(force_n, profile, shape)
        return self.displacement(force_n, profile, shape, lumen)

    def coefficient_fields(self) -> dict[str, np.ndarray]:
        """``{"coefficients": ..., "vessel_coefficients": ...}``: the image part's and the vessel part's."""
        return {"coefficients": self.image_model.coefficients, "vessel_coefficients": self.vessel_coefficients}


def check_model(model: DeformationModel, name: str = "model") -> None:
    """Raise InputError when ``model`` could displace pixels by more than
    :data:`MAX_MODEL_DISPLACEMENT_PX` over its fitted range (a bound from its coefficients: each
    basis function is about 1 at most there); a vessel-anchored model's two parts each, the vessel
    part at the reference lumen's radius."""
    normalization = model.normalization
    scales = np.abs([normalization.lateral_scale, normalization.axial_scale])
    for field, coefficients in model.coefficient_fields().items():
        bound = float(np.max(np.abs(coefficients).reshape(2, -1).sum(axis=1) * scales))
        if not bound <= MAX_MODEL_DISPLACEMENT_PX:
            raise InputError(
                f"{name}: {field}: displacements up to {bound:.3g} pixels (more than "
                f"{MAX_MODEL_DISPLACEMENT_PX:g}); not a fitted model"
            )


def correction_forces(
    forces: np.ndarray | Sequence[float] | float,
    n_frames: int,
    model: DeformationModel,
    *,
    clamp: bool = False,
    name: str = "forces",
) -> np.ndarray:
    """Per-frame forces (N) for correcting ``n_frames`` frames with ``model``: one per frame (a
    scalar is repeated), finite and in the model's fitted range (see
    :func:`~usdeform.validation.forces_in_range`); the model is checked by
    :func:`check_model`."""
    check_model(model)
    return forces_in_range(forces_array(forces, n_frames), model.normalization.force_scale, clamp=clamp, name=name)


@dataclass(frozen=True, eq=False)
class Observations:
    """Measured displacements of one palpation, from its reference (lowest-force) frame.

    ``points_px`` (N, 2) are the tracked points' (x, y) in the reference frame; ``displacements_px``
    (M, N, 2) their (lateral, axial) displacement to each of M frames, trusted where ``valid`` (M, N);
    ``forces_n`` (M,) the frames' forces and ``reference_force_n`` the reference frame's (N);
    ``profile`` the palpation's stiffness profile; ``frame_shape`` ``(rows, cols)`` of the frames the
    points were tracked on (None: not known; :func:`fit_regression` then needs it); ``vessel`` the
    lumen in the reference frame (None: none seen), which a vessel-anchored fit places its window on.
    """

    points_px: np.ndarray
    displacements_px: np.ndarray
    valid: np.ndarray
    forces_n: np.ndarray
    reference_force_n: float
    profile: StiffnessProfile
    frame_shape: tuple[int, int] | None = None
    vessel: VesselAnchor | None = None

    def __post_init__(self) -> None:
        points = np.asarray(self.points_px, dtype=np.float64)
        displacements = np.asarray(self.displacements_px, dtype=np.float64)
        valid = np.asarray(self.valid, dtype=bool)
        forces = np.asarray(self.forces_n, dtype=np.float64)
        if points.ndim != 2 or points.shape[1] != 2:
            raise InputError(f"points_px: expected shape (n_points, 2), got {points.shape}")
        expected = (forces.shape[0], points.shape[0], 2) if forces.ndim == 1 else None
        if expected is None or displacements.shape != expected or valid.shape != expected[:2]:
            raise InputError(
                f"displacements_px, valid, forces_n: expected shapes (M, N, 2), (M, N), (M,) with "
                f"N = {points.shape[0]} points, got {displacements.shape}, {valid.shape}, {forces.shape}"
            )
        if not np.all(np.isfinite(displacements[valid])) or not np.all(np.isfinite(forces)):
            raise InputError("displacements_px, forces_n: non-finite values where valid")
        if not np.isfinite(self.reference_force_n):
            raise InputError(f"reference_force_n: expected a finite force, got {self.reference_force_n}")
        if self.frame_shape is not None:
            if len(self.frame_shape) != 2 or min(self.frame_shape) < 1:
                raise InputError(f"frame_shape: expected (rows, cols) of at least one pixel, got {self.frame_shape!r}")
            object.__setattr__(self, "frame_shape", (int(self.frame_shape[0]), int(self.frame_shape[1])))
        for name, value in (
            ("points_px", points),
            ("displacements_px", displacements),
            ("valid", valid),
            ("forces_n", forces),
        ):
            object.__setattr__(self, name, value)
        object.__setattr__(self, "reference_force_n", float(self.reference_force_n))


@dataclass(frozen=True, eq=False)
class RegressionFit:
    """A fitted model, its loss (eq. 11, in normalised units: the mean over the tracked samples of the
    squared error summed over both components, plus ``wall_weight`` times that mean over the wall
    samples, without the smoothness penalty), the solver and its iterations (0 for the exact solver),
    the samples (tracked and wall) and the smoothness weight used (0 where nothing is penalised: the
    quadratic basis without a vessel part).

    ``fitted`` is the model as fitted; :attr:`model` the same where it lives in image coordinates
    alone (what the kernels and code written for :class:`DisplacementModel` take), an error for a
    :class:`VesselAnchoredModel`."""

    fitted: DeformationModel
    loss: float
    solver: Solver
    iterations: int
    n_samples: int
    smoothness: float = 0.0

    @property
    def model(self) -> DisplacementModel:
        """The fitted model in image coordinates; FitError for a vessel-anchored fit (see :attr:`fitted`)."""
        if self.fitted.anchor != "image":
            raise FitError(
                "model: this fit is vessel-anchored (anchor='vessel'); take fit.fitted (a VesselAnchoredModel, "
                "which correct_frames, correct_recording, correct_and_compound and save_model take)"
            )
        return self.fitted.image_model


def _normalization_for(
    observations: Sequence[Observations], frame_shape: tuple[int, int], coupling: Coupling, integration: Integration
) -> Normalization:
    """Scales mapping the data onto [0, 1]: pixel coordinates, force, h (and lambda when integrating
    over it) and each displacement component."""
    max_force = max(float(np.max(np.abs(o.forces_n))) for o in observations)
    max_h = 0.0
    for o in observations:
        profile = o.profile if coupling == "stiffness" else StiffnessProfile.UNIT
        lam = profile.lambda_at(o.forces_n)
        max_h = max(max_h, float(np.max(np.abs(o.forces_n) / profile.stiffness_at(lam))))
        if integration == "displacement":
            max_h = max(max_h, float(np.max(np.abs(lam - profile.lambda_at(0.0)))))
    measured = np.concatenate([o.displacements_px[o.valid] for o in observations])
    lateral, axial = (float(np.max(np.abs(measured[:, c]))) if measured.size else 1.0 for c in (0, 1))
    rows, cols = frame_shape
    return Normalization.for_frames(rows, cols, max_force or 1.0, max_h or 1.0, lateral or 1.0, axial or 1.0)


SpatialVector = Callable[[np.ndarray, np.ndarray, tuple[float, float, float]], np.ndarray]


@dataclass(frozen=True)
class _Palpation:
    """One palpation's samples, kept per tracked point and per frame (the design matrix is never
    held: a sample's row has ``integrals[f, t] * spatial[t][p]`` in the columns ``columns[t]``,
    summed over the force terms t).

    ``spatial`` (3 arrays, (n_points, len(columns[t]))): each point's terms for the force integrals
    (1, 0, 0), (0, 1, 0), (0, 0, 1) in the ``columns`` of the ``n_terms`` each term touches (a
    third of them for the B-spline basis); ``integrals`` (n_frames, 3) each frame's force integrals
    from the reference force; ``targets`` (n_frames, n_points, 2) the normalised displacements (0
    where not valid); ``valid`` (n_frames, n_points); ``positions`` (n_points, 2) the points'
    normalised reference positions. Each row and target is weighted by ``row_scale / row_divisor``
    (the palpation's weight in the loss is its square); the two are kept apart so that a dense
    design is rounded exactly as when it was built row by row (ADAM's iterates amplify rounding)."""

    spatial: tuple[np.ndarray, ...]
    columns: tuple[np.ndarray, ...]
    n_terms: int
    integrals: np.ndarray
    targets: np.ndarray
    valid: np.ndarray
    positions: np.ndarray
    row_scale: float = 1.0
    row_divisor: float = 1.0

    @property
    def weight(self) -> float:
        """The weight of this palpation's squared errors in the loss."""
        return (self.row_scale / self.row_divisor) ** 2

    def design(self) -> tuple[np.ndarray, np.ndarray]:
        """The dense weighted design rows and targets of the valid samples (frame by frame):
        (n_samples, n_terms) and (n_samples, 2)."""
        frames, points = np.nonzero(self.valid)
        design = np.zeros((len(frames), self.n_terms))
        for t in range(3):
            design[:, self.columns[t]] += self.integrals[frames, t, None] * self.spatial[t][points]
        # Rounded as the sparse rows were scaled (by the reciprocal) and the targets (divided).
        factor = self.row_scale / self.row_divisor
        return design * factor, self.targets[self.valid] * self.row_scale / self.row_divisor

    def normal_equations(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray, float]:
        """``A^T A``, ``A^T b`` and ``b^T b`` of the samples of ``points`` (a boolean mask), from each
        point's sums over its frames: a row is a point's spatial terms weighted by the frame's force
        integrals, so ``A^T A = sum_p sum_tu S_tu[p] spatial[t][p]^T spatial[u][p]`` with
        ``S_tu[p]`` the sum over the point's valid frames of ``integrals[f, t] integrals[f, u]``:
        O(points x terms^2) instead of O(samples x terms^2) and no design matrix."""
        valid = self.valid[:, points].astype(np.float64)
        targets = self.targets[:, points]
        products = valid.T @ (self.integrals[:, :, None] * self.integrals[:, None, :]).reshape(-1, 9)
        moments = np.einsum("ft,fpc->ptc", self.integrals, targets)
        gram, moment = np.zeros((self.n_terms, self.n_terms)), np.zeros((self.n_terms, 2))
        spatial = [terms[points] for terms in self.spatial]
        for t in range(3):
            moment[self.columns[t]] += spatial[t].T @ moments[:, t]
            for u in range(t, 3):
                block = spatial[t].T @ (products[:, 3 * t + u, None] * spatial[u])
                gram[np.ix_(self.columns[t], self.columns[u])] += block
                if u != t:
                    gram[np.ix_(self.columns[u], self.columns[t])] += block.T
        return gram * self.weight, moment * self.weight, float(np.sum(targets**2)) * self.weight

    def squared_error(self, coefficients: np.ndarray) -> float:
        """The weighted ``sum((A K^T - b)^2)`` over the valid samples, from each point's prediction
        per force term."""
        predicted = sum(
            self.integrals[:, t, None, None] * (self.spatial[t] @ coefficients[:, self.columns[t]].T) for t in range(3)
        )
        return float(np.sum(((predicted - self.targets) * self.valid[:, :, None]) ** 2)) * self.weight


@dataclass(frozen=True)
class _Samples:
    """The weighted samples of a fit: its palpations (tracks and wall), with the samples counted."""

    palpations: tuple[_Palpation, ...]
    n_samples: int

    @classmethod
    def weighted(cls, tracked: Sequence[_Palpation], wall: Sequence[_Palpation], wall_weight: float) -> _Samples:
        """Tracked and wall samples weighted so that the squared error sums to the tracks' mean plus
        ``wall_weight`` times the wall's mean."""
        n_tracked, n_wall = (sum(int(p.valid.sum()) for p in group) for group in (tracked, wall))
        return cls(
            tuple(dataclasses.replace(p, row_divisor=np.sqrt(max(n_tracked, 1))) for p in tracked)
            + (tuple(dataclasses.replace(p, row_scale=np.sqrt(wall_weight / n_wall)) for p in wall) if n_wall else ()),
            n_tracked + n_wall,
        )

    @property
    def sampled_points(self) -> list[np.ndarray]:
        """Per palpation, which points have at least one valid sample."""
        return [np.any(p.valid, axis=0) for p in self.palpations]

    def design(self) -> tuple[np.ndarray, np.ndarray]:
        """The dense weighted design matrix and targets (rows frame by frame, palpation by palpation)."""
        parts = [p.design() for p in self.palpations]
        return np.concatenate([design for design, _ in parts]), np.concatenate([targets for _, targets in parts])

    def normal_equations(self, points: Sequence[np.ndarray] | None = None) -> tuple[np.ndarray, np.ndarray, float]:
        """``A^T A``, ``A^T b``, ``b^T b`` of the weighted samples (of ``points``, one mask per palpation)."""
        points = self.sampled_points if points is None else points
        n_terms = self.palpations[0].n_terms
        gram, moment, energy = np.zeros((n_terms, n_terms)), np.zeros((n_terms, 2)), 0.0
        for palpation, mask in zip(self.palpations, points, strict=True):
            part = palpation.normal_equations(mask)
            gram, moment, energy = gram + part[0], moment + part[1], energy + part[2]
        return gram, moment, energy

    def squared_error(self, coefficients: np.ndarray) -> float:
        """The weighted squared error ``sum((A K^T - b)^2)`` of ``coefficients`` (2, n_terms)."""
        return sum(p.squared_error(coefficients) for p in self.palpations)


@dataclass(frozen=True)
class _VesselPart:
    """The vessel-anchored terms of a fit: windows of ``n_functions`` clamped cubic B-splines per axis
    (the inner ones free) on each palpation's lumen, scaled from ``reference``'s radius."""

    reference: VesselAnchor
    n_functions: int
    window_radii: float = VESSEL_WINDOW_RADII

    @property
    def n_inner(self) -> int:
        """Free functions per axis."""
        return self.n_functions - 4

    def terms(self, observations: Observations) -> np.ndarray:
        """(n_points, n_inner^2) spatial terms at the observations' points; zero without a lumen."""
        if observations.vessel is None:
            return np.zeros((len(observations.points_px), self.n_inner**2))
        x, y = observations.points_px[:, 0], observations.points_px[:, 1]
        spatial = vessel_basis(x, y, observations.vessel, self.reference.radius_px, self.n_functions, self.window_radii)
        return spatial.T

    def roughness(self) -> np.ndarray:
        """``R^T R`` of the second differences of each force term's window grid, its outer two rings
        held at zero (the part vanishes at the window's edge), over the inner coefficients."""
        inner = np.arange(2, self.n_functions - 2)
        kept = (inner[:, None] * self.n_functions + inner[None, :]).ravel()
        penalty = _second_differences((self.n_functions, self.n_functions))
        columns = np.concatenate([term * self.n_functions**2 + kept for term in range(3)])
        restricted = penalty[:, columns]
        return restricted.T @ restricted

    @classmethod
    def for_lumens(cls, lumens: Sequence[VesselAnchor]) -> _VesselPart:
        """The part for the palpations' lumens: their mean as reference; knots
        :data:`VESSEL_KNOT_SPACING_RADII` apart over a window of :data:`VESSEL_WINDOW_RADII`."""
        centres = np.array([lumen.centre_px for lumen in lumens])
        reference = VesselAnchor(tuple(centres.mean(axis=0)), float(np.mean([lumen.radius_px for lumen in lumens])))
        return cls(reference, round(2 * VESSEL_WINDOW_RADII / VESSEL_KNOT_SPACING_RADII) + 3)


def _samples(
    observations: Sequence[Observations],
    normalization: Normalization,
    n_intervals: int,
    coupling: Coupling,
    integration: Integration,
    spatial_vector: SpatialVector,
    n_terms: int,
    vessel: _VesselPart | None = None,
) -> list[_Palpation]:
    """Each palpation's samples (unweighted), so that the loss of K (2, n_terms) is the mean over the
    valid samples of ``sum((A @ K.T - b)^2)`` with a sample's row A the integrated
    ``spatial_vector`` at the frame's force minus that at the reference force (displacements are
    measured from the reference frame) and b its normalised displacement. With ``vessel`` the row
    goes on with the vessel-anchored terms at the palpation's own lumen (zero without one)."""
    palpations = []
    for o in observations:
        profile = o.profile if coupling == "stiffness" else StiffnessProfile.UNIT
        x_n = o.points_px[:, 0] / normalization.x_scale
        y_n = o.points_px[:, 1] / normalization.y_scale
        # The terms are linear in the force integrals (1, h, h^2): evaluate the basis once per term.
        units = ((1.0, 0.0, 0.0), (0.0, 1.0, 0.0), (0.0, 0.0, 1.0))
        terms = [spatial_vector(x_n, y_n, unit).T for unit in units]
        if vessel is not None:
            local = vessel.terms(o)
            terms = [np.hstack([term, np.kron(unit, local)]) for term, unit in zip(terms, units, strict=True)]
        columns = tuple(np.flatnonzero(np.any(term != 0, axis=0)) for term in terms)
        spatial = tuple(term[:, used] for term, used in zip(terms, columns, strict=True))
        reference = np.array(force_terms(o.reference_force_n, profile, normalization, n_intervals, integration))
        integrals = np.array(
            [force_terms(force, profile, normalization, n_intervals, integration) for force in o.forces_n]
        ).reshape(-1, 3)
        scales = [normalization.lateral_scale, normalization.axial_scale]
        targets = np.where(o.valid[:, :, None], o.displacements_px / scales, 0.0)
        palpations.append(
            _Palpation(
                spatial, columns, n_terms, integrals - reference, targets, o.valid.copy(), np.column_stack([x_n, y_n])
            )
        )
    return palpations


def _second_differences(n_functions: tuple[int, int]) -> np.ndarray:
    """``R`` with ``|R c|^2`` the summed squared second differences along x and along y of each
    force term's coefficient grid, for ``c`` in the (term, y, x) order: (n_differences, 3 n_y n_x)."""
    n_y, n_x = n_functions
    along_x = np.kron(np.eye(n_y), np.diff(np.eye(n_x), 2, axis=0))
    along_y = np.kron(np.diff(np.eye(n_y), 2, axis=0), np.eye(n_x))
    return np.kron(np.eye(3), np.vstack([along_x, along_y]))


def _roughness(n_functions: tuple[int, int]) -> np.ndarray:
    """``R^T R`` of :func:`_second_differences`: the smoothness penalty's quadratic form."""
    penalty = _second_differences(n_functions)
    return penalty.T @ penalty


def _solve_normal_equations(system: np.ndarray, moment: np.ndarray) -> np.ndarray:
    """``system^-1 moment`` for a symmetric positive semi-definite ``system`` (Cholesky; least squares
    where it is singular)."""
    try:
        return scipy.linalg.solve(system, moment, assume_a="pos")
    except (np.linalg.LinAlgError, scipy.linalg.LinAlgError):
        return np.linalg.lstsq(system, moment, rcond=None)[0]


def _penalised_solve(
    samples: _Samples, gram: np.ndarray, moment: np.ndarray, roughness: np.ndarray, smoothness: float
) -> np.ndarray:
    """K (2, n_terms) minimising ``sum((A K^T - b)^2) + smoothness * sum(|R K^T|^2)`` for the
    weighted samples with normal equations ``gram``, ``moment`` and ``roughness = R^T R``: from the
    normal equations when penalised, else as the least-squares solution of ``A K^T = b`` (no squared
    condition number where nothing regularises)."""
    if smoothness > 0:
        return _solve_normal_equations(gram + smoothness * roughness, moment).T
    design, targets = samples.design()
    return np.linalg.lstsq(design, targets, rcond=None)[0].T


def _penalised_solver(gram: np.ndarray, moment: np.ndarray, roughness: np.ndarray) -> Callable[[float], np.ndarray]:
    """A function of the smoothness weight s giving ``(gram + s roughness)^-1 moment``.

    Many weights are tried on one fold, so the pair is diagonalised once: the generalised
    eigenvectors V of ``roughness V = (gram + roughness) V diag(mu)`` (V^T (gram + roughness) V = I)
    give ``gram + s roughness = V^-T diag(1 - mu + s mu) V^-1``, and each weight then costs a
    matrix product instead of a factorisation. Where ``gram + roughness`` is singular, each weight
    is solved directly."""
    try:
        mu, vectors = scipy.linalg.eigh(roughness, gram + roughness)
    except (np.linalg.LinAlgError, scipy.linalg.LinAlgError):
        return lambda smoothness: _solve_normal_equations(gram + smoothness * roughness, moment)
    projected = vectors.T @ moment
    return lambda smoothness: vectors @ (projected / (np.maximum(1.0 - mu, 0.0) + smoothness * mu)[:, None])


#: Smoothness weights of the cross-validation's coarse search, one per decade. Where the best of them
#: is an end of the grid the search widens by decades past it (see :func:`_cross_validated_smoothness`),
#: then refines the best weight by half and quarter decades.
SMOOTHNESS_GRID = tuple(10.0 ** np.arange(-10, 5))
#: Decades the search may widen past each end of :data:`SMOOTHNESS_GRID`.
SMOOTHNESS_WIDENING_DECADES = 8
#: Below this weight relative to the Gram matrix's scale the penalty no longer changes the solution
#: (double precision): a search that ends there has found that the data need no smoothing.
NEGLIGIBLE_RELATIVE_SMOOTHNESS = 1e-12
#: Side, in blocks, of the square grid of spatial regions the cross-validation holds out.
CV_REGIONS_PER_SIDE = 4


def _cross_validated_smoothness(
    samples: _Samples, roughness: np.ndarray, n_folds: int
) -> tuple[float, dict[float, float]]:
    """The smoothness weight with the least held-out weighted squared error over ``n_folds`` folds of
    whole spatial regions, and the held-out error of every log10 weight tried.

    The frame is cut into ``CV_REGIONS_PER_SIDE``^2 blocks by the samples' normalised reference
    positions, and each fold holds out some blocks with all their frames (assigned by a fixed
    shuffle, so the choice is reproducible). Holding out regions tests what the smoothness is for:
    bridging places without observations (a vessel's lumen, a shadow). Holding out whole frames does
    not: the neighbouring forces of the same points predict a frame well at any smoothness, and that
    criterion chose the smallest weight it tried in every fit of the independent data.

    The search tries :data:`SMOOTHNESS_GRID`; while the best weight is an end of the weights tried
    it widens by a decade past that end (at most :data:`SMOOTHNESS_WIDENING_DECADES`; downwards only
    while the penalty still changes the solution, :data:`NEGLIGIBLE_RELATIVE_SMOOTHNESS`), so that
    the optimum lies inside the range searched; it warns where it does not. The best weight is then
    refined by half and quarter decades. Each trial solves the penalised normal equations from
    per-fold Gram matrices, so it costs O(n_terms^3); ``roughness`` is the penalty's ``R^T R``."""
    sampled = samples.sampled_points
    positions = np.concatenate([p.positions[mask] for p, mask in zip(samples.palpations, sampled, strict=True)])
    block = np.clip(np.floor(positions * CV_REGIONS_PER_SIDE), 0, CV_REGIONS_PER_SIDE - 1).astype(int)
    region_ids, region_of_point = np.unique(block[:, 1] * CV_REGIONS_PER_SIDE + block[:, 0], return_inverse=True)
    if len(region_ids) < 2:
        raise FitError(
            "observations: choosing the smoothness by cross-validation needs observations in at least 2 regions "
            "of the frame; pass smoothness"
        )
    fold = (np.random.default_rng(0).permutation(len(region_ids)) % min(n_folds, len(region_ids)))[region_of_point]
    # A point's samples all share its reference position, so each fold holds whole points.
    fold_of_points = np.split(fold, np.cumsum([int(mask.sum()) for mask in sampled])[:-1])
    folds = [
        [_points_in(mask, of_points == k) for mask, of_points in zip(sampled, fold_of_points, strict=True)]
        for k in np.unique(fold)
    ]
    grams, moments, energies = zip(*(samples.normal_equations(points) for points in folds), strict=True)
    gram_all, moment_all = sum(grams), sum(moments)
    negligible = float(np.log10(NEGLIGIBLE_RELATIVE_SMOOTHNESS * np.abs(gram_all).max() / np.abs(roughness).max()))

    solvers = [
        _penalised_solver(gram_all - gram, moment_all - moment, roughness)
        for gram, moment in zip(grams, moments, strict=True)
    ]

    def held_out_error(log_smoothness: float) -> float:
        error = 0.0
        for solve, gram, moment, energy in zip(solvers, grams, moments, energies, strict=True):
            solution = solve(10.0**log_smoothness)
            error += float(np.sum(solution * (gram @ solution)) - 2 * np.sum(solution * moment) + energy)
        return error

    errors = {float(v): held_out_error(float(v)) for v in np.log10(SMOOTHNESS_GRID)}
    lowest, highest = min(errors), max(errors)
    while True:
        best = min(errors, key=errors.__getitem__)
        if best == max(errors) and best < highest + SMOOTHNESS_WIDENING_DECADES:
            errors[best + 1.0] = held_out_error(best + 1.0)
        elif best == min(errors) and best > max(lowest - SMOOTHNESS_WIDENING_DECADES, negligible):
            errors[best - 1.0] = held_out_error(best - 1.0)
        else:
            break
    if best == max(errors) or (best == min(errors) and best > negligible):
        warnings.warn(
            f"smoothness: the cross-validated optimum lies at the end of the searched range "
            f"(10^{best:g}); pass smoothness to choose it yourself",
            stacklevel=3,
        )
    for step in (0.5, 0.25):
        for candidate in (best - step, best + step):
            if min(errors) <= candidate <= max(errors) and candidate not in errors:
                errors[candidate] = held_out_error(candidate)
        best = min(errors, key=errors.__getitem__)
    return float(10.0**best), errors


def _points_in(mask: np.ndarray, chosen: np.ndarray) -> np.ndarray:
    """The mask of all points that are set in ``mask`` and, among those (in order), ``chosen``."""
    points = np.zeros_like(mask)
    points[np.flatnonzero(mask)[chosen]] = True
    return points


def _adam(
    design: np.ndarray, targets: np.ndarray, learning_rate: float, max_iterations: int, tolerance: float
) -> tuple[np.ndarray, int]:
    """Full-batch ADAM (Kingma and Ba 2014, beta1 0.9, beta2 0.999) from K = 0 on the eq. 11 loss of
    the weighted rows (``sum((A K^T - b)^2)``, the mean squared error without wall samples); stops
    when the loss improves by less than ``tolerance`` (relative) over 100 iterations.

    The loss is quadratic, so its gradient ``2 (K A^T A - b^T A)`` needs only the 10 x 10 Gram
    matrix: each iteration costs O(100), not O(samples), with the same iterates.
    """
    gram, moment = design.T @ design, targets.T @ design
    target_energy = float(np.sum(targets**2))

    def loss(coefficients: np.ndarray) -> float:
        return float(np.sum(coefficients @ gram * coefficients) - 2 * np.sum(coefficients * moment) + target_energy)

    coefficients = np.zeros((2, design.shape[1]))
    first, second = np.zeros_like(coefficients), np.zeros_like(coefficients)
    beta1, beta2, epsilon = 0.9, 0.999, 1e-8
    previous = np.inf
    for iteration in range(1, max_iterations + 1):
        gradient = 2.0 * (coefficients @ gram - moment)
        first = beta1 * first + (1 - beta1) * gradient
        second = beta2 * second + (1 - beta2) * gradient**2
        step = (first / (1 - beta1**iteration)) / (np.sqrt(second / (1 - beta2**iteration)) + epsilon)
        coefficients = coefficients - learning_rate * step
        if iteration % 100 == 0:
            current = loss(coefficients)
            if np.isfinite(previous) and previous - current <= tolerance * previous:
                return coefficients, iteration
            previous = current
    return coefficients, max_iterations


def _spatial_basis(basis: Basis | tuple[str, int, int]) -> tuple[SpatialVector, tuple[int, ...]]:
    """The terms function and the coefficient shape of ``basis``: ``"quadratic"`` or
    ``("bspline", n_x, n_y)``."""
    if basis == "quadratic":
        return regression_vector, (2, len(M_TERMS))
    if (
        isinstance(basis, tuple)
        and len(basis) == 3
        and basis[0] == "bspline"
        and all(isinstance(n, (int, np.integer)) and n >= BSPLINE_MIN_FUNCTIONS for n in basis[1:])
    ):
        n_functions = (int(basis[2]), int(basis[1]))
        return partial(bspline_vector, n_functions=n_functions), (2, 3, *n_functions)
    raise InputError(
        f"basis: expected 'quadratic' or ('bspline', n_x, n_y) with n_x, n_y integers >= "
        f"{BSPLINE_MIN_FUNCTIONS}, got {basis!r}"
    )


def _frame_shape_of(observations: Sequence[Observations], frame_shape: tuple[int, int] | None) -> tuple[int, int]:
    """The frame shape the observations were tracked on: ``frame_shape`` if given, else theirs."""
    carried = {o.frame_shape for o in observations if o.frame_shape is not None}
    if frame_shape is not None:
        shape = (int(frame_shape[0]), int(frame_shape[1]))
        if carried - {shape}:
            raise InputError(f"frame_shape: {shape} differs from the observations' frame shape {sorted(carried)}")
        return shape
    if len(carried) != 1:
        found = f"they carry {sorted(carried)}" if carried else "they carry none"
        raise InputError(f"frame_shape: expected the observations to carry one frame shape, {found}; pass frame_shape")
    return carried.pop()


def fit_regression(
    observations: Sequence[Observations],
    frame_shape: tuple[int, int] | None = None,
    solver: Solver = "exact",
    *,
    coupling: Coupling = "stiffness",
    n_intervals: int = 64,
    learning_rate: float = 0.01,
    max_iterations: int = 50_000,
    tolerance: float = 1e-7,
    integration: Integration = "force",
    basis: Basis | tuple[str, int, int] = "quadratic",
    smoothness: float | None = None,
    n_folds: int = 5,
    wall_observations: Sequence[Observations] | None = None,
    wall_weight: float = 1.0,
    anchor: Anchor = "image",
) -> RegressionFit:
    """Fit the displacement model to measured displacements (paper eq. 11).

    Inputs are normalised to [0, 1] as the paper says. The loss is the mean squared error over the
    tracked samples plus ``wall_weight`` times the mean squared error over the vessel-wall samples.

    Parameters
    ----------
    observations : sequence of Observations
        One per palpation: the tissue tracks (and boundary rows).
    frame_shape : tuple of int, optional
        ``(rows, cols)`` of the frames; None: the one the observations carry.
    solver : {"exact", "adam"}
        The least-squares solution the loss has (it is quadratic in K), or the paper's ADAM with
        step ``learning_rate``, at most ``max_iterations`` and a relative ``tolerance``.
    coupling : {"stiffness", "force"}
        ``h = F / k`` (the paper) or the force-based baseline ``h = F``.
    n_intervals : int
        Equal force intervals of the integral.
    learning_rate, max_iterations, tolerance
        ADAM's settings.
    integration : {"force", "displacement"}
        Integrate the rate over force or over probe displacement.
    basis : "quadratic" or ("bspline", n_x, n_y)
        The paper's quadratic, or a :class:`BSplineDisplacementModel` (exact solver only) whose
        loss adds ``smoothness`` times the summed squared second differences of each force term's
        coefficient grid (normalised units); without ``smoothness`` the weight is chosen by
        ``n_folds``-fold cross-validation over spatial regions (see :data:`SMOOTHNESS_GRID`). A
        finer grid (12 x 12, 16 x 16 on a 256 x 256 frame: knots 20-30 pixels apart) can follow a
        vessel's local collapse; the cross-validated penalty keeps it smooth where nothing is
        observed (benches/bench_wall.py measures the grids).
    smoothness : float, optional
        The B-spline smoothness weight.
    n_folds : int
        Folds of the cross-validation.
    wall_observations : sequence of Observations, optional
        Displacements of the vessel wall (:func:`usdeform.vessel_wall.track_vessel_wall`), any
        number of palpations, as constraints of their own weight.
    wall_weight : float
        Weight of the wall samples' mean squared error against the tracks' (>= 0).
    anchor : {"image", "vessel"}
        A model in image coordinates, or a :class:`VesselAnchoredModel` (exact solver): the basis
        plus a finer B-spline part on a window around each palpation's lumen
        (``Observations.vessel``, at least one needed), which correction moves and scales with the
        lumen of the frame it corrects. For vessels that move along the sweep or differ in size.

    Returns
    -------
    RegressionFit
        The model (with the frame shape) and the fit's loss and settings.
    """
    if solver not in SOLVERS:
        raise InputError(f"solver: expected one of {SOLVERS}, got {solver!r}")
    if coupling not in COUPLINGS:
        raise InputError(f"coupling: expected one of {COUPLINGS}, got {coupling!r}")
    if integration not in INTEGRATIONS:
        raise InputError(f"integration: expected one of {INTEGRATIONS}, got {integration!r}")
    spatial_vector, coefficient_shape = _spatial_basis(basis)
    is_spline = len(coefficient_shape) == 4
    if anchor not in ANCHORS:
        raise InputError(f"anchor: expected one of {ANCHORS}, got {anchor!r}")
    # B-splines and the vessel part are penalised by their roughness, with the smoothness chosen by
    # cross-validation (the quadratic under a vessel part is not penalised).
    penalised = is_spline or anchor == "vessel"
    if penalised and solver != "exact":
        raise InputError(
            f"solver: the B-spline basis and the vessel-anchored model are fitted by the exact solver only, "
            f"got {solver!r}"
        )
    if smoothness is not None and not (penalised and np.isfinite(smoothness) and smoothness >= 0):
        raise InputError(
            f"smoothness: expected a finite value >= 0 with a B-spline basis or anchor='vessel', got {smoothness!r} "
            f"with basis {basis!r}"
        )
    if int(n_folds) < 2:
        raise InputError(f"n_folds: expected at least 2, got {n_folds}")
    if not (np.isfinite(wall_weight) and wall_weight >= 0):
        raise InputError(f"wall_weight: expected a finite weight >= 0, got {wall_weight!r}")
    observations = list(observations)
    walls = list(wall_observations or [])
    if not observations:
        raise FitError("observations: need at least one palpation")
    frame_shape = _frame_shape_of(observations + walls, frame_shape)
    rows, cols = frame_shape
    for name, group in (("observations", observations), ("wall_observations", walls)):
        for number, o in enumerate(group):
            outside = (o.points_px < 0) | (o.points_px > [cols - 1, rows - 1])
            if np.any(outside):
                raise InputError(
                    f"{name}[{number}].points_px: points outside the {rows} x {cols} frame_shape; "
                    "the frame shape sets the model's normalisation and must be the frames' own"
                )
    normalization = _normalization_for(observations + walls, frame_shape, coupling, integration)
    vessel = None
    if anchor == "vessel":
        lumens = [o.vessel for o in observations + walls if o.vessel is not None]
        if not lumens:
            raise FitError(
                "observations: anchor='vessel' needs the lumen of at least one palpation's lowest-force frame "
                "(Observations.vessel, set where the vessel wall is measured)"
            )
        vessel = _VesselPart.for_lumens(lumens)
    n_image_terms = int(np.prod(coefficient_shape[1:]))
    n_terms = n_image_terms + (3 * vessel.n_inner**2 if vessel is not None else 0)
    problem = partial(
        _samples,
        normalization=normalization,
        n_intervals=n_intervals,
        coupling=coupling,
        integration=integration,
        spatial_vector=spatial_vector,
        n_terms=n_terms,
        vessel=vessel,
    )
    samples = _Samples.weighted(problem(observations), problem(walls) if wall_weight > 0 else [], wall_weight)
    n_samples = samples.n_samples
    # BLAS on one thread: OpenBLAS's threaded routines round differently with the thread count, and
    # the fit must not depend on it (the systems are a few hundred unknowns: one thread is fast).
    with threadpool_limits(limits=1, user_api="blas"):
        if penalised:
            if is_spline:
                roughness = _roughness((coefficient_shape[2], coefficient_shape[3]))
            else:
                roughness = np.zeros((n_image_terms, n_image_terms))
            if vessel is not None:
                roughness = scipy.linalg.block_diag(roughness, vessel.roughness())
            gram, moment, _ = samples.normal_equations()
            rank = np.linalg.matrix_rank(gram + roughness, hermitian=True) if n_samples else 0
            if rank < n_terms:
                raise FitError(
                    f"observations: {n_samples} valid samples with the smoothness penalty reach rank "
                    f"{rank} of the {n_terms} coefficients; track more points over more distinct "
                    "forces, or use fewer basis functions"
                )
            if smoothness is None:
                smoothness, _ = _cross_validated_smoothness(samples, roughness, int(n_folds))
            coefficients = _penalised_solve(samples, gram, moment, roughness, float(smoothness))
            iterations = 0
            image_type = BSplineDisplacementModel if is_spline else QuadraticDisplacementModel
            image_model = image_type(
                coefficients[:, :n_image_terms].reshape(coefficient_shape),
                normalization,
                n_intervals,
                coupling,
                integration,
                frame_shape,
            )
            model: DeformationModel = image_model
            if vessel is not None:
                vessel_coefficients = coefficients[:, n_image_terms:].reshape(2, 3, vessel.n_inner, vessel.n_inner)
                model = VesselAnchoredModel(image_model, vessel_coefficients, vessel.reference, vessel.window_radii)
        else:
            dense, targets = samples.design()
            if dense.shape[0] < n_terms or np.linalg.matrix_rank(dense) < n_terms:
                raise FitError(
                    f"observations: {n_samples} valid samples with design rank "
                    f"{np.linalg.matrix_rank(dense) if dense.shape[0] else 0} cannot determine the 10 terms of K; "
                    "track more points over more distinct forces"
                )
            if solver == "exact":
                coefficients = np.linalg.lstsq(dense, targets, rcond=None)[0].T
                iterations = 0
            else:
                coefficients, iterations = _adam(dense, targets, learning_rate, max_iterations, tolerance)
            model = QuadraticDisplacementModel(
                coefficients, normalization, n_intervals, coupling, integration, frame_shape
            )
        loss = samples.squared_error(coefficients)
    return RegressionFit(model, loss, solver, iterations, n_samples, float(smoothness or 0.0))
