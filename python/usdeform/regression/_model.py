"""The displacement models in image coordinates, and the interface every fitted model offers.

:class:`DisplacementModel` (with :class:`QuadraticDisplacementModel`, the paper's, and
:class:`BSplineDisplacementModel`) is converted once into the compiled model every kernel takes.
:class:`DeformationModel` is what every model offers, a vessel-anchored one included;
:func:`check_model` and :func:`correction_forces` check a model and the forces it corrects.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from collections.abc import Sequence
from dataclasses import dataclass
from typing import ClassVar, Protocol

import numpy as np

from .. import _core
from .._arrays import forces_array
from ..errors import InputError
from ..options import COUPLINGS, INTEGRATIONS, Anchor, Basis, Coupling, Integration
from ..validation import MAX_INTERVALS, forces_in_range
from ._basis import BSPLINE_MIN_FUNCTIONS, VesselAnchor, bspline_vector, regression_vector
from ._stiffness_profile import StiffnessProfile

#: ``n_intervals`` of a fitted model (see :class:`DisplacementModel`; the integrals do not depend on it).
N_INTERVALS = 64


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
        A model's ``n_intervals`` (1 to :data:`~usdeform.validation.MAX_INTERVALS`): checked; the
        integrals are exact whatever its value.
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
        self,
        force_n: float,
        profile: StiffnessProfile,
        shape: tuple[int, int],
        lumen: VesselAnchor | None,
        other_lumens: Sequence[VesselAnchor | None] = (),
    ) -> np.ndarray:
        """``D(x, y, F)`` (2, rows, cols), pixels, at ``force_n`` (N) with a vessel part placed on
        ``lumen`` (None: without the vessel part, as the fit treats a palpation that shows no lumen) and
        each further vessel's on its entry of ``other_lumens``."""
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
        Force intervals of the paper's midpoint integral (eq. 8), 1 to
        :data:`~usdeform.validation.MAX_INTERVALS`: kept in the model and its files, and checked; the
        force integrals are exact (closed form), whatever its value.
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
    n_intervals: int = N_INTERVALS
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
        self,
        force_n: float,
        profile: StiffnessProfile,
        shape: tuple[int, int],
        lumen: VesselAnchor | None,
        other_lumens: Sequence[VesselAnchor | None] = (),
    ) -> np.ndarray:
        """:meth:`displacement`: the model has no part that follows a lumen."""
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
