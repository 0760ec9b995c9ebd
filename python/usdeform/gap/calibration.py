"""Real-to-sim calibration: the ideal simulator fitted to a recording, with cached mechanical variants.

What makes it fast (stated, since FEM is slow):

* **Geometry on a grid.** The vessel's lateral position, depth and radius come from the lumen
  segmented in the lowest-lambda frame, snapped to a 1 mm / 0.5 mm / 0.5 mm grid so that
  recordings of one phantom share cached solves (``usdeform.sim.solve_section`` caches on disk).
* **Modulus scaling.** Every solve is made at one shear modulus (``LIBRARY_SHEAR_MODULUS_KPA``); the
  field does not depend on it and the force scales with it, so the tissue modulus is a one-number
  least-squares fit of the scaled FEM force to the recorded force.
* **A small library of mechanical variants** of the calibrated section (sliding contact, also at the wider
  probe face since slip depends on the face's width, a soft top layer on a 2 x 2 grid of thickness and
  modulus ratio, lumen pressure at two levels, the face tilted either way so that it meets the surface
  progressively, a flat face pressed off the surface normal), solved once
  and gridded; intermediate parameters interpolate the field *differences* from the ideal section
  linearly (a reduced model: exact at the grid points, linear between them).
* **Free parameters of the ideal section** (``SECTION_PARAMETERS``), calibrated with every candidate
  like the modulus: how nearly incompressible the tissue is (Poisson's ratio 0.40-0.499: it sets how far
  the tissue bulges sideways under the probe, and differs between tissues, phantom materials and FEM
  engines), how thick it is above a rigid base (30-90 mm: the depth of bone or of the phantom block,
  which sets how fast the indentation decays with depth; a three-dimensional footprint, a few centimetres
  long in elevation, decays it faster than any plane-strain section of that depth, and the thin end takes
  that up too), how much it stiffens with strain (Yeoh's C20/C10 from -0.3 to 6, neo-Hookean at 0, soft
  tissue about 3: the paper's Table 1; stiffening spreads the indentation deeper and wider, a depth profile
  that a soft top layer would otherwise take up), how compliant the lumen is (its modulus
  0.005-0.3 times the tissue's, from an empty or fluid-filled lumen to a wall-supported one) and how wide
  the flat probe face is (from the image's width, which the transducer array spans, to 20 mm more: the
  housing around the array presses too, and its size is nowhere in a recording). The library
  solves the section at each parameter's library value and at the ends of its range; the field is taken
  as linear between them in a coordinate it varies nearly linearly in (Poisson's ratio, the Yeoh ratio and the
  face width themselves, the reciprocal thickness, the log lumen modulus) and :func:`usdeform.gap.models.predict` fits
  the weights.
* **Depth first.** Tissue depth is the one parameter whose variants differ in where the field exists at all
  (a thinner section is rigid below its base): blending a 60 mm section with a 35 mm one misplaces the
  displacement over the 25 mm between them, and on a 50 mm phantom that misfit was taken up by a spurious
  -100 m/s speed-of-sound error on every recording. So a survey (the ideal section at 60 mm and its 35 and
  90 mm variants only) fits the depth first, and the full library is then solved at the ``DEPTH_LADDER_MM``
  rung nearest it, with the neighbouring rungs (5-10 mm away) as the depth variants
  (:func:`usdeform.gap.models.surveyed_depth_mm`).
* **Solves in parallel.** The uncached sections of every recording's library are solved together in the
  diagnosis's worker processes, one per core (:mod:`usdeform.gap.processes`; each solve is independent and
  deterministic, so the result does not depend on the number of processes). Solved and gridded sections are
  cached on disk for later diagnoses (:mod:`usdeform.gap.library_cache`).
* **No rendering for the mechanical measures.** The simulated displacement of a tracked point is
  the FEM field at the point's material position; frames are rendered only for image measures.
* The elastic force curve of the ideal simulator is a cubic in lambda through the origin, fitted
  to the recording: its shape absorbs the unknown material law (a nuisance, not an effect). What a
  variant adds to the force at first contact (a pressurised lumen pushing the surface against the
  probe) is kept: a cubic through the origin cannot take it up.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Sequence
from concurrent.futures import Executor
from dataclasses import dataclass
from typing import Any

import numpy as np

from ..errors import InputError
from ..sim import Layer, SectionSpec
from ..sim.mechanics import MAX_INDENTATION_FRACTION
from .library_cache import cached_library_entry, entry_is_cached
from .library_entries import SPARE_FACTOR, SPARE_MM, LibraryEntry, UnsolvedSection, effect_of_variant
from .observations import Observation
from .processes import run_all

__all__ = [
    "DEPTH_LADDER_MM",
    "LAYER_MODULUS_RATIOS",
    "LAYER_THICKNESSES_MM",
    "LIBRARY_SHEAR_MODULUS_KPA",
    "PRESSURE_RATIOS",
    "SECTION_PARAMETERS",
    "TILT_VARIANT_DEG",
    "TRAVEL_VARIANT",
    "CalibratedSection",
    "SectionParameter",
    "calibrate",
    "depth_parameter",
    "ideal_section",
    "library_solves",
    "library_variants",
    "section_parameters",
    "tilt_variant_name",
    "variant_specs",
]

LIBRARY_SHEAR_MODULUS_KPA = 20.0
LIBRARY_MESH_MM = 2.5
LAYER_THICKNESSES_MM = (4.0, 10.0)
LAYER_MODULUS_RATIOS = (0.2, 0.5)
PRESSURE_RATIOS = (0.05, 0.2)  # lumen pressure / tissue shear modulus
TILT_VARIANT_DEG = 8.0  # the probe tilt (either sign) whose progressive contact the library solves
TRAVEL_VARIANT = "travel_8"  # a flat face pressed TILT_VARIANT_DEG off the surface normal towards +x
_GRID_SPACING_MM = 0.75
_LAMBDA_STEP_MM = 0.75
_LUMEN_CLEARANCE_MM = 3.0  # tissue a section keeps below its lumen
_PROBE_WIDER_MM = (12.5, 20.0)  # the face-width variant and the widest fitted face, beyond the image's width
DEPTH_LADDER_MM = (30.0, 35.0, 40.0, 45.0, 50.0, 55.0, 60.0, 70.0, 80.0, 90.0)
"""Tissue depths (mm) the full library is solved at, once the survey has fitted the depth: 5 mm apart where a
section's thickness matters most (the thin end), 10 mm beyond 60 mm; the depth parameter's bounds are its ends."""
_PLACEHOLDER_VESSEL = (50.0, 25.0, 3.0)  # x, depth, radius (mm): far from the probe when no lumen is seen (and
# shallow enough for the thinnest depth variant)


_COORDINATES: dict[str, tuple[Callable[[float], float], Callable[[float], float]]] = {
    "linear": (lambda value: value, lambda at: at),
    "reciprocal": (lambda value: 1.0 / value, lambda at: 1.0 / at),
    "log": (lambda value: float(np.log(value)), lambda at: float(np.exp(at))),
}
"""A section parameter's interpolation coordinate: (value -> coordinate, coordinate -> value)."""


@dataclass(frozen=True)
class SectionParameter:
    """A free parameter of the ideal section (a :class:`~usdeform.sim.SectionSpec` field): its library value,
    the values of the variants solved beside it, and the range it is fitted in.

    ``coordinate`` is what the field is interpolated (and extrapolated, within ``bounds``) linearly in:
    ``"linear"`` (the value), ``"reciprocal"`` or ``"log"``. With one variant the weight of its difference
    from the ideal field may be negative (extrapolation to the other side); with two, one variant per side.
    """

    name: str
    library: float
    variants: tuple[float, ...]
    bounds: tuple[float, float]
    coordinate: str

    def _coordinate(self, value: float) -> float:
        return _COORDINATES[self.coordinate][0](value)

    def variant_name(self, value: float) -> str:
        return f"{self.name}={value:g}"

    def weight_bounds(self, variant: float) -> tuple[float, float]:
        """Bounds of the weight of ``variant``'s field difference: its side of the range (both, with one variant)."""
        step = self._coordinate(variant) - self._coordinate(self.library)
        ends = [(self._coordinate(end) - self._coordinate(self.library)) / step for end in self.bounds]
        low, high = min(ends), max(ends)
        return (low, high) if len(self.variants) == 1 else (max(low, 0.0), high)

    def value(self, variant: float, weight: float) -> float:
        """The parameter's value at ``weight`` of ``variant``'s field difference."""
        at = self._coordinate(self.library) + weight * (self._coordinate(variant) - self._coordinate(self.library))
        return _COORDINATES[self.coordinate][1](at)


SECTION_PARAMETERS = (
    SectionParameter("poisson_ratio", 0.45, (0.49,), (0.40, 0.499), "linear"),  # SectionSpec's default is 0.45
    SectionParameter("depth_mm", 60.0, (35.0, 90.0), (30.0, 90.0), "reciprocal"),  # the survey's; strain ~ 1 / depth
    SectionParameter("lumen_stiffness_ratio", 0.05, (0.005, 0.3), (0.005, 0.3), "log"),
    SectionParameter("yeoh_c2", 0.0, (3.0,), (-0.3, 6.0), "linear"),  # strain stiffening, C20/C10
)
"""The free parameters every calibrated section has; :func:`section_parameters` adds the probe face's width."""


def depth_parameter(library_mm: float) -> SectionParameter:
    """The tissue depth's free parameter solved at the ``DEPTH_LADDER_MM`` rung ``library_mm``, with the
    neighbouring rungs as its variants (one at either end of the ladder)."""
    rung = DEPTH_LADDER_MM.index(library_mm)
    neighbours = tuple(DEPTH_LADDER_MM[i] for i in (rung - 1, rung + 1) if 0 <= i < len(DEPTH_LADDER_MM))
    return SectionParameter("depth_mm", library_mm, neighbours, (DEPTH_LADDER_MM[0], DEPTH_LADDER_MM[-1]), "reciprocal")


def section_parameters(image_width_mm: float, depth_mm: float | None = None) -> tuple[SectionParameter, ...]:
    """The free parameters of a section imaged ``image_width_mm`` wide (centred on the probe axis): those of
    ``SECTION_PARAMETERS`` and the probe face's width, whose library value is the image's width (snapped up
    to 0.5 mm so that recordings of one probe share cached solves; the paper's probe: 37.5 mm) and which is
    fitted from 2.5 mm narrower (the array's edge elements may not image) to 20 mm wider. ``depth_mm``: a
    ``DEPTH_LADDER_MM`` rung to solve the depth at (:func:`depth_parameter`) instead of the survey's 60 mm."""
    face = float(np.ceil(2 * image_width_mm - 1e-6) / 2)
    wider, widest = _PROBE_WIDER_MM
    probe = SectionParameter("probe_width_mm", face, (face + wider,), (face - 2.5, face + widest), "linear")
    fixed: tuple[SectionParameter, ...] = SECTION_PARAMETERS
    if depth_mm is not None:
        fixed = tuple(depth_parameter(depth_mm) if p.name == "depth_mm" else p for p in SECTION_PARAMETERS)
    return (*fixed, probe)


@dataclass
class CalibratedSection:
    """The calibrated ideal section and its mechanical variants, gridded for fast evaluation.

    grid_x_mm (nx,), grid_z_mm (nz,): section coordinates of the grid; lambda_mm (ns,): solved steps.
    fields: variant name -> (2, ns, nz, nx) displacement (x, z), mm (NaN outside the section).
    lumen_area_mm2: variant name -> (ns,) lumen area. force_n: variant name -> (ns,) FEM force at
    the library modulus (at lambda = 0 the push of a pressurised lumen on the probe face, else zero).
    spec: the ideal section (library modulus). shear_modulus_kpa: the
    calibrated tissue modulus (modulus scaling of the ideal FEM force to the recorded loading force).
    has_vessel: whether a lumen was seen (otherwise a placeholder vessel far from the probe).
    parameters: the section's free parameters (:func:`section_parameters`). unsolved: the library sections left
    out (:mod:`usdeform.gap.library_entries`), with every variant of the effect each one models; resolved: the
    sections solved with finer load steps or only to the recorded indentation, (name, how).
    """

    spec: SectionSpec
    grid_x_mm: np.ndarray
    grid_z_mm: np.ndarray
    lambda_mm: np.ndarray
    fields: dict[str, np.ndarray]
    lumen_area_mm2: dict[str, np.ndarray]
    force_n: dict[str, np.ndarray]
    shear_modulus_kpa: float
    has_vessel: bool
    parameters: tuple[SectionParameter, ...] = SECTION_PARAMETERS
    # library sections left out because they could not be solved, and those solved in another way (name -> how)
    unsolved: tuple[UnsolvedSection, ...] = ()
    resolved: tuple[tuple[str, str], ...] = ()

    @property
    def left_out_effects(self) -> set[str]:
        """The library effects whose sections could not be solved for this recording (not fitted)."""
        return {entry.effect for entry in self.unsolved if entry.effect}

    def field(self, variant_weights: dict[str, float]) -> np.ndarray:
        """Ideal field plus the weighted differences of the named variants to it, (2, ns, nz, nx)."""
        ideal = self.fields["ideal"]
        result = ideal.copy()
        for name, weight in variant_weights.items():
            if weight:
                result += weight * (self.fields[name] - ideal)
        return result

    def joint_weights(self, weights: dict[str, float]) -> dict[str, float]:
        """``weights`` (variant name -> weight of its difference to the ideal field) with the interaction of an
        effect's variant and a parameter's variant where both were solved together (:func:`joint_name`):
        bilinear in the two weights, f = I + a (A - I) + b (B - I) + a b (AB - A - B + I)."""
        result = dict(weights)
        for effect_variant, a in weights.items():
            for parameter_variant in self.parameter_variants():
                joint = joint_name(effect_variant, parameter_variant)
                b = weights.get(parameter_variant, 0.0)
                if a and b and joint in self.fields:
                    result[joint] = a * b
                    result[effect_variant] -= a * b
                    result[parameter_variant] -= a * b
        return result

    def parameter_change(self, name: str, weights: dict[str, float]) -> dict[str, float]:
        """The field's change per unit weight of the parameter variant ``name`` given the effects' variant
        ``weights``, as coefficients of library fields (so that a caller samples each field at its points once):
        its difference to the ideal, bent by the joint solves (:meth:`joint_weights`)."""
        change = {name: 1.0, "ideal": -1.0}
        for effect_variant, a in weights.items():
            joint = joint_name(effect_variant, name)
            if a and joint in self.fields:
                change[joint] = a
                change[name] -= a
                change[effect_variant] = change.get(effect_variant, 0.0) - a
                change["ideal"] += a
        return change

    def parameter_variants(self) -> list[str]:
        """Names of the solved variants of the section's free parameters, in their order."""
        names = [parameter.variant_name(value) for parameter in self.parameters for value in parameter.variants]
        return [name for name in names if name in self.fields]

    def lumen_area(self, variant_weights: dict[str, float]) -> np.ndarray:
        """(ns,) lumen area with the weighted variant differences, mm^2."""
        ideal = self.lumen_area_mm2["ideal"]
        return ideal + sum(w * (self.lumen_area_mm2[name] - ideal) for name, w in variant_weights.items())

    def contact_reaction_n(self, variant_weights: dict[str, float]) -> float:
        """Force, N, on the probe face at first contact (lambda = 0+) of the weighted variants, at the calibrated
        modulus: a pressurised lumen bulges the surface into the probe (the lumen pressure is a fixed ratio of the
        modulus in the library, so the reaction scales with it)."""
        scale = self.shear_modulus_kpa / LIBRARY_SHEAR_MODULUS_KPA
        ideal = self.force_n["ideal"][0]
        return scale * float(sum(w * (self.force_n[name][0] - ideal) for name, w in variant_weights.items()))

    def displacement(self, field: np.ndarray, points_mm: np.ndarray, lambda_mm: np.ndarray) -> np.ndarray:
        """Displacement (2, k, m), mm, of section points (m, 2) at each of the probe displacements (k,), from a
        gridded field (2, ns, nz, nx).

        Trilinear in (lambda, z, x): exact in lambda between solved steps (the FEM field is linear
        there); bilinear in space on the grid. Points outside the grid get NaN. Written out rather than with
        ``scipy.ndimage.map_coordinates`` for speed (a prediction samples several fields at every frame x point
        pair): the four spatial neighbours are gathered once per point from the flattened grid, then the two
        neighbouring steps once per frame (``map_coordinates`` of the k x m pairs is about ten times slower).
        """
        nx, nz, ns = len(self.grid_x_mm), len(self.grid_z_mm), len(self.lambda_mm)
        ix = (points_mm[:, 0] - self.grid_x_mm[0]) / (self.grid_x_mm[1] - self.grid_x_mm[0])
        iz = (points_mm[:, 1] - self.grid_z_mm[0]) / (self.grid_z_mm[1] - self.grid_z_mm[0])
        inside = (ix >= 0) & (ix <= nx - 1) & (iz >= 0) & (iz <= nz - 1)
        x0 = np.clip(np.floor(np.nan_to_num(ix)), 0, nx - 2).astype(np.intp)
        z0 = np.clip(np.floor(np.nan_to_num(iz)), 0, nz - 2).astype(np.intp)
        fx, fz = np.nan_to_num(ix) - x0, np.nan_to_num(iz) - z0
        corner = z0 * nx + x0
        corners = np.stack([corner, corner + 1, corner + nx, corner + nx + 1])  # (4, m) in the flattened grid
        corner_weights = np.stack([(1 - fz) * (1 - fx), (1 - fz) * fx, fz * (1 - fx), fz * fx])
        gathered = np.take(field.reshape(2 * ns, nz * nx), corners, axis=1)  # (2 ns, 4, m)
        spatial = np.einsum("scm,cm->sm", gathered, corner_weights).reshape(2, ns, -1)
        step = np.interp(np.clip(lambda_mm, 0.0, None), self.lambda_mm, np.arange(ns))
        lower = np.minimum(np.floor(step).astype(np.intp), ns - 2)
        above = (step - lower)[:, None]
        result = spatial[:, lower] * (1 - above) + spatial[:, lower + 1] * above
        result[:, :, ~inside] = np.nan
        return result


def joint_name(effect_variant: str, parameter_variant: str) -> str:
    """Library name of the section with an effect's variant and a free parameter's variant together."""
    return f"{effect_variant},{parameter_variant}"


def tilt_variant_name(tilt_deg: float) -> str:
    """Library name of the section pressed by a face tilted ``tilt_deg`` (the image's tilt, degrees)."""
    return f"tilt_{tilt_deg:g}"


def variant_specs(
    spec: SectionSpec, parameters: tuple[SectionParameter, ...], has_vessel: bool
) -> dict[str, SectionSpec]:
    """The library's sections: ideal, the free parameters' variants, sliding, soft top layers on a grid, the face
    tilted either way, a flat face pressed off the normal, lumen pressures. A thinner tissue that the vessel does
    not fit in (with 3 mm to spare) is left out, and so are the lumen's variants when no lumen was seen
    (``has_vessel``)."""
    variants = {"ideal": spec}
    for parameter in parameters:
        if parameter.name == "lumen_stiffness_ratio" and not has_vessel:
            continue
        for value in parameter.variants:
            changed: dict[str, Any] = {parameter.name: value}
            depth = changed.get("depth_mm", spec.depth_mm)  # checked first: SectionSpec refuses a vessel not fitting
            if spec.vessel_depth_mm + spec.vessel_radius_mm + _LUMEN_CLEARANCE_MM <= depth:
                variants[parameter.variant_name(value)] = dataclasses.replace(spec, **changed)
    variants["slide"] = dataclasses.replace(spec, contact="slide")
    for parameter in parameters:
        if parameter.name == "probe_width_mm":  # how far tissue slips depends on the face's width: solved jointly
            for value in parameter.variants:
                variants[joint_name("slide", parameter.variant_name(value))] = dataclasses.replace(
                    spec, contact="slide", probe_width_mm=value
                )
    for thickness in LAYER_THICKNESSES_MM:
        for ratio in LAYER_MODULUS_RATIOS:
            layer = Layer(thickness_mm=thickness, shear_modulus_kpa=spec.shear_modulus_kpa * ratio)
            variants[f"layer_{thickness:g}_{ratio:g}"] = dataclasses.replace(spec, layers=(layer,))
    for sign in (-1.0, 1.0):  # the image's tilt is the face's, with the opposite sign (SectionSpec.face_tilt_deg)
        variants[tilt_variant_name(sign * TILT_VARIANT_DEG)] = dataclasses.replace(
            spec, face_tilt_deg=-sign * TILT_VARIANT_DEG
        )
    variants[TRAVEL_VARIANT] = dataclasses.replace(spec, face_travel_deg=TILT_VARIANT_DEG)
    if has_vessel:
        for ratio in PRESSURE_RATIOS:
            pressure = spec.shear_modulus_kpa * ratio
            variants[f"pressure_{ratio:g}"] = dataclasses.replace(spec, lumen_pressure_kpa=pressure)
    return variants


def _top_lambda_mm(observation: Observation) -> float:
    """The largest probe displacement the library is solved to, mm: the recording's, with 15 % and 0.5 mm spare."""
    return float(np.max(observation.probe_displacement_mm)) * SPARE_FACTOR + SPARE_MM


def ideal_section(
    observation: Observation, depth_mm: float | None = None
) -> tuple[SectionSpec, tuple[SectionParameter, ...], bool]:
    """The ideal section of an observation, its free parameters and whether a lumen was seen.

    The reference lumen is snapped to the geometry grid; the section is 3 times as wide as the widest probe
    face solved (``section_parameters``), every variant alike. ``depth_mm``: a fitted tissue depth; the section
    is then solved at the ``DEPTH_LADDER_MM`` rung nearest it among those the lumen fits in (3 mm to spare) and
    the indentation is at most ``MAX_INDENTATION_FRACTION`` of it (of the survey's 60 mm when None)."""
    if observation.vessel_center_probe_mm is None or observation.vessel_radius_mm is None:
        x, depth, radius = _PLACEHOLDER_VESSEL
        has_vessel = False
    else:
        reference_lambda = max(float(observation.probe_displacement_mm[observation.reference_index]), 0.0)
        x = float(np.round(observation.vessel_center_probe_mm[0]))
        depth = float(np.round(2 * (observation.vessel_center_probe_mm[1] + reference_lambda)) / 2)
        radius = float(np.clip(np.round(2 * observation.vessel_radius_mm) / 2, 1.5, 12.0))
        depth = float(np.clip(depth, radius + 3.0, 60.0 - radius - _LUMEN_CLEARANCE_MM))
        x = float(np.clip(x, -55.0 + radius, 55.0 - radius))
        has_vessel = True
    columns_mm = observation.image_to_probe[0, 3] + observation.image_to_probe[0, 0] * np.array(
        [0.0, observation.frame_shape[1]]
    )
    rung = None
    if depth_mm is not None:
        thinnest = max(depth + radius + _LUMEN_CLEARANCE_MM, _top_lambda_mm(observation) / MAX_INDENTATION_FRACTION)
        deep_enough = [candidate for candidate in DEPTH_LADDER_MM if candidate >= thinnest] or [DEPTH_LADDER_MM[-1]]
        rung = min(deep_enough, key=lambda candidate: abs(candidate - depth_mm))
    parameters = section_parameters(2 * float(np.max(np.abs(columns_mm))), rung)
    library: dict[str, Any] = {parameter.name: parameter.library for parameter in parameters}
    probe = next(parameter for parameter in parameters if parameter.name == "probe_width_mm")
    spec = SectionSpec(
        width_mm=max(SectionSpec.width_mm, 3 * max(probe.variants)),
        vessel_center_x_mm=x,
        vessel_depth_mm=depth,
        vessel_radius_mm=radius,
        shear_modulus_kpa=LIBRARY_SHEAR_MODULUS_KPA,
        mesh_size_mm=min(LIBRARY_MESH_MM, radius),
        **library,
    )
    return spec, parameters, has_vessel


def library_variants(
    observation: Observation,
    spec: SectionSpec,
    parameters: tuple[SectionParameter, ...],
    has_vessel: bool,
    *,
    survey: bool = False,
) -> dict[str, SectionSpec]:
    """The sections :func:`calibrate` solves for ``observation`` around its ideal section (:func:`ideal_section`):
    :func:`variant_specs` less a thinner variant that cannot take the recorded indentation; with ``survey``
    only the ideal section and its depth variants."""
    top = _top_lambda_mm(observation)
    variants = {
        name: variant
        for name, variant in variant_specs(spec, parameters, has_vessel).items()
        if top <= MAX_INDENTATION_FRACTION * variant.depth_mm
    }
    if survey:
        depth = next(parameter for parameter in parameters if parameter.name == "depth_mm")
        surveyed = {"ideal", *(depth.variant_name(value) for value in depth.variants)}
        variants = {name: variant for name, variant in variants.items() if name in surveyed}
    return variants


@dataclass(frozen=True)
class _LibraryPlan:
    """What :func:`calibrate` solves for one observation: its ideal section, the library's solved steps (mm), the
    grid the fields are sampled on (x, z; mm) and the variants."""

    spec: SectionSpec
    parameters: tuple[SectionParameter, ...]
    has_vessel: bool
    steps: np.ndarray
    grid_x: np.ndarray
    grid_z: np.ndarray
    variants: dict[str, SectionSpec]

    @classmethod
    def of(cls, observation: Observation, depth_mm: float | None, survey: bool) -> _LibraryPlan:
        """The plan for ``observation`` around ``depth_mm``; an indentation the section cannot take is refused."""
        spec, parameters, has_vessel = ideal_section(observation, depth_mm)
        top = _top_lambda_mm(observation)
        if top > MAX_INDENTATION_FRACTION * spec.depth_mm:
            raise InputError(
                f"{observation.name}: ProbeDisplacement: {np.max(observation.probe_displacement_mm):.3g} mm of "
                f"indentation is more than the calibrated section can take "
                f"({(MAX_INDENTATION_FRACTION * spec.depth_mm - 0.5) / 1.15:.3g} mm)"
            )
        variants = library_variants(observation, spec, parameters, has_vessel, survey=survey)
        # Steps on a lattice from 0 to the first node at or past ``top`` (within what every variant can take), so
        # that recordings of nearby indentations share their library entries (:mod:`usdeform.gap.library_cache`).
        steps = np.arange(int(np.ceil(top / _LAMBDA_STEP_MM - 1e-9)) + 1) * _LAMBDA_STEP_MM
        steps[-1] = min(steps[-1], MAX_INDENTATION_FRACTION * min(v.depth_mm for v in variants.values()))
        half_width = float(np.max(np.abs(observation.image_to_probe[0, 3]))) + 8.0
        depth = float(observation.row_depth_mm(observation.frame_shape[0])) * 1.15 + steps[-1] + 2.0
        return cls(
            spec=spec,
            parameters=parameters,
            has_vessel=has_vessel,
            steps=steps,
            grid_x=np.arange(-half_width, half_width + 1e-9, _GRID_SPACING_MM),
            grid_z=np.arange(0.0, min(depth, spec.depth_mm) + 1e-9, _GRID_SPACING_MM),
            variants=variants,
        )

    def key(self, variant: SectionSpec) -> tuple[str, bytes, bytes]:
        """What identifies ``variant``'s library entry: its solve's cache key and the grid."""
        return variant.cache_key(self.steps), self.grid_x.tobytes(), self.grid_z.tobytes()

    def solves(self) -> dict[tuple[str, bytes, bytes], tuple[SectionSpec, np.ndarray, np.ndarray, np.ndarray]]:
        """The arguments of :func:`library_entry` for each variant, by :meth:`key`."""
        return {
            self.key(variant): (variant, self.steps, self.grid_x, self.grid_z) for variant in self.variants.values()
        }


def library_solves(
    observations: Sequence[Observation], depths_mm: Sequence[float | None] | None = None, *, survey: bool = False
) -> int:
    """How many library sections :func:`calibrate` solves or reads for ``observations`` (a progress bar's total)."""
    depths_mm = [None] * len(observations) if depths_mm is None else depths_mm
    plans = [
        _LibraryPlan.of(observation, depth, survey) for observation, depth in zip(observations, depths_mm, strict=True)
    ]
    return len({key for plan in plans for key in plan.solves()})


def calibrate(
    observations: Sequence[Observation],
    *,
    depths_mm: Sequence[float | None] | None = None,
    survey: bool = False,
    progress=None,
    pool: Executor | None = None,
) -> list[CalibratedSection]:
    """Calibrate the ideal simulator (geometry, modulus) to each observation and build its variant library.

    ``depths_mm``: per observation, the fitted tissue depth to solve the library around (see
    :func:`ideal_section`; None: the survey's 60 mm). ``survey``: solve only the ideal section and its depth
    variants, which is all that fitting the depth takes (:func:`usdeform.gap.models.surveyed_depth_mm`).
    ``progress``: an optional tqdm-like object whose ``update(1)`` is called after each solve or read.
    ``pool``: worker processes (:func:`usdeform.gap.processes.worker_pool`) for the uncached solves of all the
    observations together (None: solved in this process; the result is the same).
    """
    depths_mm = [None] * len(observations) if depths_mm is None else depths_mm
    if len(depths_mm) != len(observations):
        raise ValueError(f"depths_mm: expected {len(observations)} depths, got {len(depths_mm)}")
    plans = [
        _LibraryPlan.of(observation, depth, survey) for observation, depth in zip(observations, depths_mm, strict=True)
    ]
    solves = {key: args for plan in plans for key, args in plan.solves().items()}
    uncached = {key: args for key, args in solves.items() if not entry_is_cached(*args)}
    solved = run_all(pool, cached_library_entry, list(uncached.values()), progress)
    entries = dict(zip(uncached, solved, strict=True))
    for key, args in solves.items():
        if key not in entries:
            entries[key] = cached_library_entry(*args)
            if progress is not None:
                progress.update(1)
    sections = []
    for observation, plan in zip(observations, plans, strict=True):
        library = {name: entries[plan.key(variant)] for name, variant in plan.variants.items()}
        sections.append(_calibrated_section(observation, plan, library))
    return sections


def _calibrated_section(
    observation: Observation, plan: _LibraryPlan, solved: dict[str, LibraryEntry | str]
) -> CalibratedSection:
    """The calibrated section from its library's entries by variant (:func:`library_entry`: an entry, or why it
    could not be solved), the modulus scaled to the recorded loading force. A section that could not be solved is
    left out with every variant of the effect it models (:mod:`usdeform.gap.library_entries`)."""
    failed = {name: entry for name, entry in solved.items() if isinstance(entry, str)}
    if "ideal" in failed:
        raise InputError(
            f"{observation.name}: the calibrated FEM section cannot be solved at the recorded indentation "
            f"({failed['ideal']})"
        )
    unsolved = [
        UnsolvedSection(observation.name, name, error, effect_of_variant(name)) for name, error in failed.items()
    ]
    left_out = {entry.effect for entry in unsolved if entry.effect}
    for name in solved:
        if name not in failed and effect_of_variant(name) in left_out:
            unsolved.append(
                UnsolvedSection(
                    observation.name, name, "its effect's other sections were left out", effect_of_variant(name)
                )
            )
    left_names = {entry.section for entry in unsolved}
    entries = {name: entry for name, entry in solved.items() if name not in left_names and not isinstance(entry, str)}
    fields = {name: entry.field for name, entry in entries.items()}
    areas = {name: entry.lumen_area_mm2 for name, entry in entries.items()}
    forces = {name: entry.force_n for name, entry in entries.items()}
    loading = observation.phase == 0
    lam = observation.probe_displacement_mm
    fem_force = np.interp(np.clip(lam[loading], 0, None), plan.steps, forces["ideal"])
    scale = float(fem_force @ observation.force_n[loading] / max(fem_force @ fem_force, 1e-12))
    if not scale > 0:
        raise InputError(f"{observation.name}: ContactForce: the force does not rise with ProbeDisplacement")
    return CalibratedSection(
        spec=plan.spec,
        grid_x_mm=plan.grid_x,
        grid_z_mm=plan.grid_z,
        lambda_mm=plan.steps,
        fields=fields,
        lumen_area_mm2=areas,
        force_n=forces,
        shear_modulus_kpa=LIBRARY_SHEAR_MODULUS_KPA * scale,
        has_vessel=plan.has_vessel,
        parameters=plan.parameters,
        unsolved=tuple(unsolved),
        resolved=tuple((name, entry.resolved) for name, entry in entries.items() if entry.resolved),
    )
