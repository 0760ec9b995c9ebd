"""The vessel-anchored model: a model in image coordinates plus a part that follows the lumen."""

from __future__ import annotations

import functools
from collections.abc import Sequence
from dataclasses import dataclass
from typing import ClassVar

import numpy as np

from .. import _core
from ..errors import InputError
from ..options import Anchor, Coupling, Integration
from ._basis import VESSEL_WINDOW_RADII, VesselAnchor, _window_coordinates, _window_functions
from ._model import DisplacementModel, Normalization
from ._stiffness_profile import StiffnessProfile


@dataclass(frozen=True, eq=False)
class VesselAnchoredModel:
    """A displacement model in two parts: ``image_model``, tied to the image (the probe's contact),
    plus a cubic B-spline part tied to the vessel, whose window moves and scales with the lumen of
    the frame it corrects (:func:`usdeform.correction._vessel.correct_vessel_anchored` finds it).

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
    other_vessels : tuple of (ndarray, VesselAnchor)
        A part of its own for each further vessel (a vein beside the artery, whose softer lumen collapses
        more): its coefficients (2, 3, n, n) and its palpations' reference lumen, placed on that vessel's
        own lumen in each frame.
    """

    #: A part follows the lumen (see :class:`DeformationModel`).
    anchor: ClassVar[Anchor] = "vessel"

    image_model: DisplacementModel
    vessel_coefficients: np.ndarray
    reference: VesselAnchor
    window_radii: float = VESSEL_WINDOW_RADII
    other_vessels: tuple[tuple[np.ndarray, VesselAnchor], ...] = ()

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
        others = []
        for index, (grid, reference) in enumerate(self.other_vessels):
            array = np.array(grid, dtype=np.float64, order="C")
            if array.shape != coefficients.shape or not np.all(np.isfinite(array)):
                raise InputError(
                    f"other_vessels[{index}]: expected finite coefficients of shape {coefficients.shape}, "
                    f"got {array.shape}"
                )
            if not isinstance(reference, VesselAnchor):
                raise InputError(f"other_vessels[{index}]: expected a VesselAnchor reference")
            array.setflags(write=False)
            others.append((array, reference))
        object.__setattr__(self, "other_vessels", tuple(others))
        object.__setattr__(
            self, "_vessel_kernel", _core.VesselPart(coefficients, self.reference.radius_px, float(self.window_radii))
        )

    @property
    def vessel_kernel(self) -> _core.VesselPart:
        """The compiled vessel part the kernels take (with :attr:`image_model`'s ``kernel``), built once."""
        kernel: _core.VesselPart = self.__dict__["_vessel_kernel"]
        return kernel

    @functools.cached_property
    def vessel_models(self) -> tuple[VesselAnchoredModel, ...]:
        """One model per vessel, each the image part with that vessel's part alone: the main vessel's
        first (this model without its further vessels), then one per further vessel (built once)."""
        if not self.other_vessels:
            return (self,)
        parts = [(self.vessel_coefficients, self.reference), *self.other_vessels]
        return tuple(VesselAnchoredModel(self.image_model, grid, lumen, self.window_radii) for grid, lumen in parts)

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

    def displacement_on(
        self,
        force_n: float,
        profile: StiffnessProfile,
        lumen: VesselAnchor | None,
        window: tuple[slice, slice],
    ) -> np.ndarray:
        """``D(x, y, F)`` on ``window`` (a row and a column slice of the frame, with start and stop),
        the vessel part on ``lumen`` (None: the image part alone): (2, window rows, window columns),
        pixels; compiled (:func:`usdeform.reference.anchored_displacement` is its twin)."""
        rows, cols = window
        return self.vessel_kernel.displacement(
            self.image_model.kernel,
            float(force_n),
            profile.as_tuple(),
            None if lumen is None else (*lumen.centre_px, lumen.radius_px),
            (rows.start, rows.stop),
            (cols.start, cols.stop),
        )

    def displacement(
        self,
        force_n: float,
        profile: StiffnessProfile,
        shape: tuple[int, int],
        anchor: VesselAnchor | None = None,
    ) -> np.ndarray:
        """``D(x, y, F)`` with the lumen at ``anchor`` (None: at :attr:`reference`) and each further vessel's
        part on its reference lumen: (2, rows, cols), pixels."""
        others = [reference for _, reference in self.other_vessels]
        return self.displacement_with_lumen(force_n, profile, shape, anchor or self.reference, others)

    def displacement_with_lumen(
        self,
        force_n: float,
        profile: StiffnessProfile,
        shape: tuple[int, int],
        lumen: VesselAnchor | None,
        other_lumens: Sequence[VesselAnchor | None] = (),
    ) -> np.ndarray:
        """``D(x, y, F)`` with the vessel part on ``lumen`` and each further vessel's part on its entry of
        ``other_lumens``; a part is left out where its lumen is None or not given (as the fit treats a
        palpation that shows no lumen): (2, rows, cols), pixels."""
        field = self.image_model.displacement(force_n, profile, shape)
        lumens = [lumen, *other_lumens][: len(self.vessel_models)]
        for model, placed in zip(self.vessel_models, lumens, strict=False):
            if placed is not None:
                field += model.vessel_displacement(force_n, profile, shape, placed)
        return field

    def coefficient_fields(self) -> dict[str, np.ndarray]:
        """``{"coefficients": ..., "vessel_coefficients": ...}``: the image part's and the vessel part's."""
        return {"coefficients": self.image_model.coefficients, "vessel_coefficients": self.vessel_coefficients}
