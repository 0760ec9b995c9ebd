"""The fit stage as a user runs it: palpation recordings -> displacement model.

Each palpation's phases are found first (:func:`usdeform.fitting.detect_phases`: approach,
loading, hold, unloading) and only its loading ramp from contact, with the probe displacement counted
from contact, is measured and fitted; a palpation that is a loading ramp from contact is fitted as
recorded. Each palpation is measured (:func:`usdeform.fitting.measure_positions`: stiffness, tracked pixel
displacements, optionally the vessel wall), then one displacement model is fitted to all of them
(:func:`usdeform.regression.fit_regression`). ``usdeform fit``, the batch runner and the demo all
fit through :func:`fit_palpations`, with a named :class:`FitMethod`:

- ``recommended``: cubic B-splines (8 x 8) with the paper's stiffness coupling (h = F/k), integrated
  over probe displacement, with the vessel wall as observations where a lumen is found, and the
  vessel's collapse anchored to its lumen (a finer B-spline part on a window around the lumen that
  correction moves and scales with each frame's own lumen; in image coordinates alone where no
  palpation shows a lumen), so that the collapse follows a vessel that moves along the sweep or
  differs in size. ``python benches/bench_wall.py`` (grids, wall, anchoring, integration variable)
  and ``usdeform experiment paper-3d`` compare it with the paper's model.
- ``paper``: the paper's model exactly (quadratic basis, eq. 8 integrated over force, no wall), for
  reproduction.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, Literal

from ..correction import SampledProfiles
from ..errors import InputError
from ..io import fit_provenance
from ..options import Anchor, Basis, Coupling, Integration, Solver, WallMode
from ..recording import Recording
from ..regression import BSPLINE_MIN_FUNCTIONS, RegressionFit, fit_regression
from ._phases import PalpationPhases, detect_phases
from ._sampling import SampledPosition, measure_positions

if TYPE_CHECKING:  # its scipy and reconstruction imports only where a compensation is read
    from ..compensation import Compensation

__all__ = [
    "FIT_METHODS",
    "FitMethod",
    "FittedPalpations",
    "MethodName",
    "fit_measured",
    "fit_method",
    "fit_palpations",
    "parse_basis",
]

MethodName = Literal["recommended", "paper"]


@dataclass(frozen=True)
class FitMethod:
    """How a displacement model is fitted: :func:`~usdeform.regression.fit_regression`'s settings,
    whether the vessel wall is measured and used (``wall`` as for
    :func:`~usdeform.fitting.measure_positions`) and what the model is tied to (``anchor``: with
    "vessel", a part of it follows the lumen where the palpations show one, see
    :class:`~usdeform.regression.VesselAnchoredModel`)."""

    basis: Basis | tuple[str, int, int]
    coupling: Coupling
    integration: Integration
    wall: WallMode
    description: str
    anchor: Anchor = "image"


#: The named methods (see the module docstring for why ``recommended`` is what it is).
FIT_METHODS: dict[MethodName, FitMethod] = {
    "recommended": FitMethod(
        ("bspline", 8, 8),
        "stiffness",
        "displacement",
        "auto",
        "cubic B-spline basis 8 x 8, h = F/k, integrated over probe displacement, vessel wall as observations, "
        "the collapse anchored to the vessel's lumen",
        "vessel",
    ),
    "paper": FitMethod("quadratic", "stiffness", "force", "off", "the paper's quadratic model (eq. 8), over force"),
}


def parse_basis(text: str) -> Literal["quadratic"] | tuple[str, int, int]:
    """``quadratic`` or ``bspline:NXxNY`` (cubic B-splines, NX and NY functions along x and y) as
    :func:`~usdeform.regression.fit_regression`'s ``basis``; InputError for anything else."""
    if text == "quadratic":
        return "quadratic"
    name, _, counts = text.partition(":")
    n_x, _, n_y = counts.partition("x")
    if name != "bspline" or not (n_x.isdigit() and n_y.isdigit()) or min(int(n_x), int(n_y)) < BSPLINE_MIN_FUNCTIONS:
        raise InputError(
            f"basis: expected 'quadratic' or 'bspline:NXxNY' with NX, NY >= "
            f"{BSPLINE_MIN_FUNCTIONS} (e.g. bspline:8x6), got {text!r}"
        )
    return ("bspline", int(n_x), int(n_y))


def fit_method(
    name: MethodName,
    *,
    basis: str | None = None,
    coupling: Coupling | None = None,
    integration: Integration | None = None,
    wall: WallMode | None = None,
    anchor: Anchor | None = None,
) -> FitMethod:
    """The named method of :data:`FIT_METHODS` with the settings given here (not None) in place of
    its own; ``basis`` in the notation of :func:`parse_basis`."""
    settings: dict[str, Any] = {"coupling": coupling, "integration": integration, "wall": wall, "anchor": anchor}
    if basis is not None:
        settings["basis"] = parse_basis(basis)
    return dataclasses.replace(
        FIT_METHODS[name], **{key: value for key, value in settings.items() if value is not None}
    )


@dataclass(frozen=True)
class FittedPalpations:
    """A model fitted to palpations.

    Attributes
    ----------
    fit : RegressionFit
        The model and how the fit went.
    measured : list of SampledPosition
        Each palpation's stiffness, tracks, observations and wall note.
    sampled : SampledProfiles
        Where each palpation was and its stiffness profile (what correction interpolates).
    provenance : dict
        What a model file records of the fit: method and settings, solver, loss, palpations' walls.
    method : FitMethod
        The settings the model was fitted with.
    wall_weight : float
        The weight of the wall's samples (as for :func:`fit_measured`).
    phases : list of PalpationPhases
        Each palpation's approach, loading, hold and unloading frames.
    loading_recordings : list of Recording
        Each palpation's loading ramp from contact: the frames that were measured and fitted.
    """

    fit: RegressionFit
    measured: list[SampledPosition]
    sampled: SampledProfiles
    provenance: dict[str, Any]
    method: FitMethod
    wall_weight: float
    phases: list[PalpationPhases]
    loading_recordings: list[Recording]


def fit_measured(
    measured: Sequence[SampledPosition],
    method: FitMethod,
    *,
    solver: Solver = "exact",
    smoothness: float | None = None,
    wall_weight: float = 1.0,
) -> RegressionFit:
    """Fit one displacement model to measured palpations with ``method``'s settings; the walls are
    used where they were measured and ``method.wall`` is not "off". A vessel-anchored method anchors
    on the lumens the wall measurement found; where it found none (no palpation shows a lumen, or the
    palpations were measured with the wall "off") there is no vessel to follow, and the model is
    fitted in image coordinates (the fit's provenance says which)."""
    walls = [w for m in measured for w in (m.wall, *m.other_walls) if w is not None] if method.wall != "off" else []
    anchor = method.anchor
    if not any(m.observations.vessel is not None for m in measured):
        anchor = "image"
    return fit_regression(
        [m.observations for m in measured],
        solver=solver,
        coupling=method.coupling,
        integration=method.integration,
        basis=method.basis,
        smoothness=smoothness,
        wall_observations=walls,
        wall_weight=wall_weight,
        anchor=anchor,
    )


def fit_palpations(
    recordings: Sequence[Recording],
    flexible_layer_mm: float,
    *,
    method: MethodName | FitMethod = "recommended",
    names: Sequence[str] | None = None,
    solver: Solver = "exact",
    smoothness: float | None = None,
    wall_weight: float = 1.0,
    compensation: Compensation | None = None,
) -> FittedPalpations:
    """Measure palpations (one per sampling position) on their loading ramps from contact and fit one
    displacement model to them.

    Parameters
    ----------
    recordings : sequence of Recording
        Palpations with ContactForce, ProbeDisplacement and valid probe poses, frames of one size.
    flexible_layer_mm : float
        Thickness of the flexible layer, mm (paper eq. 10).
    method : {"recommended", "paper"} or FitMethod
        A named method of :data:`FIT_METHODS` or one of its variants (``dataclasses.replace``).
    names : sequence of str, optional
        One name per recording (e.g. its file), used in error messages.
    solver, smoothness, wall_weight
        As for :func:`~usdeform.regression.fit_regression`.
    compensation : Compensation, optional
        Diagnosed recording effects undone on every palpation first
        (:func:`usdeform.compensation.read_compensation`); the provenance's ``compensation`` says
        what changed.

    Returns
    -------
    FittedPalpations

    Raises
    ------
    InputError
        A palpation without contact or loading ramp (:func:`~usdeform.fitting.detect_phases`),
        before any palpation is measured.
    """
    settings = FIT_METHODS[method] if isinstance(method, str) else method
    names = [f"palpation {index}" for index in range(len(recordings))] if names is None else list(names)
    if len(names) != len(recordings):
        raise InputError(f"names: expected one per recording ({len(recordings)}), got {len(names)}")
    notes = []
    if compensation is not None:
        compensated = [compensation.apply(recording, name) for recording, name in zip(recordings, names, strict=True)]
        recordings, notes = [recording for recording, _ in compensated], [note for _, note in compensated]
    phases = [detect_phases(recording, name) for recording, name in zip(recordings, names, strict=True)]
    loading = [found.loading_recording(recording) for found, recording in zip(phases, recordings, strict=True)]
    measured, sampled = measure_positions(loading, flexible_layer_mm, names=names, wall=settings.wall)
    fit = fit_measured(measured, settings, solver=solver, smoothness=smoothness, wall_weight=wall_weight)
    basis = settings.basis if isinstance(settings.basis, str) else "{}:{}x{}".format(*settings.basis)
    provenance = {
        **fit_provenance(fit),
        **({"method": method} if isinstance(method, str) else {}),
        **{key: value for key, value in dataclasses.asdict(settings).items() if key != "description"},
        "basis": basis,
        "wall_weight": wall_weight,
        "wall_palpations": sum(m.wall is not None for m in measured) if settings.wall != "off" else 0,
        "anchor": fit.fitted.anchor,
        "flexible_layer_mm": flexible_layer_mm,
        "palpation_phases": [found.to_json() for found in phases],
        **({"compensation": {**compensation.to_json(), "notes": notes}} if compensation is not None else {}),
    }
    return FittedPalpations(fit, list(measured), sampled, provenance, settings, wall_weight, phases, loading)
