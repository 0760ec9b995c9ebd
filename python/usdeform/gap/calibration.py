"""Real-to-sim calibration: the ideal simulator fitted to a recording, with cached mechanical variants.

What makes it fast (stated, since FEM is slow):

* **Geometry on a grid.** The vessel's lateral position, depth and radius come from the lumen
  segmented in the lowest-lambda frame, snapped to a 1 mm / 0.5 mm / 0.5 mm grid so that
  recordings of one phantom share cached solves (``usdeform.sim.solve_section`` caches on disk).
* **Modulus scaling.** Every solve is made at one shear modulus (``LIBRARY_SHEAR_MODULUS_KPA``); the
  field does not depend on it and the force scales with it, so the tissue modulus is a one-number
  least-squares fit of the scaled FEM force to the recorded force.
* **A small library of mechanical variants** of the calibrated section (sliding contact, a soft top
  layer on a 2 x 2 grid of thickness and modulus ratio, lumen pressure at two levels), solved once
  and gridded; intermediate parameters interpolate the field *differences* from the ideal section
  linearly (a reduced model: exact at the grid points, linear between them).
* **Compressibility is a free parameter of the ideal simulator**, like the modulus: tissue is nearly
  incompressible, but how nearly (Poisson's ratio 0.45-0.5) differs between tissues, phantom materials
  and FEM engines, and it sets how far the tissue bulges sideways under the probe. The library solves
  the ideal section at ``POISSON_RATIOS`` (the library's 0.45 and 0.49); the field is linear in
  1 - 2 nu between them (:func:`usdeform.gap.models.predict` fits the weight of the difference).
* **No rendering for the mechanical measures.** The simulated displacement of a tracked point is
  the FEM field at the point's material position; frames are rendered only for image measures.
* The elastic force curve of the ideal simulator is a cubic in lambda through the origin, fitted
  to the recording: its shape absorbs the unknown material law (a nuisance, not an effect). What a
  variant adds to the force at first contact (a pressurised lumen pushing the surface against the
  probe) is kept: a cubic through the origin cannot take it up.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np
from scipy.ndimage import map_coordinates

from ..errors import InputError
from ..sim import Layer, MechanicsSolution, SectionSpec, solve_section
from .observations import Observation

__all__ = [
    "LAYER_MODULUS_RATIOS",
    "LAYER_THICKNESSES_MM",
    "LIBRARY_SHEAR_MODULUS_KPA",
    "POISSON_RATIOS",
    "PRESSURE_RATIOS",
    "CalibratedSection",
    "calibrate",
]

LIBRARY_SHEAR_MODULUS_KPA = 20.0
LIBRARY_MESH_MM = 2.5
LAYER_THICKNESSES_MM = (4.0, 10.0)
LAYER_MODULUS_RATIOS = (0.2, 0.5)
PRESSURE_RATIOS = (0.05, 0.2)  # lumen pressure / tissue shear modulus
POISSON_RATIOS = (0.45, 0.49)  # the library's (SectionSpec's default) and the nearly incompressible variant's
_GRID_SPACING_MM = 0.75
_LAMBDA_STEP_MM = 0.75
_PLACEHOLDER_VESSEL = (45.0, 50.0, 3.0)  # x, depth, radius (mm): far from the probe when no lumen is seen


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

    def field(self, variant_weights: dict[str, float]) -> np.ndarray:
        """Ideal field plus the weighted differences of the named variants to it, (2, ns, nz, nx)."""
        ideal = self.fields["ideal"]
        result = ideal.copy()
        for name, weight in variant_weights.items():
            if weight:
                result += weight * (self.fields[name] - ideal)
        return result

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
        """Displacement (m, 2), mm, of section points (m, 2) at probe displacements (m,), from a gridded field.

        Trilinear in (lambda, z, x): exact in lambda between solved steps (the FEM field is linear
        there); bilinear in space on the grid. Points outside the grid get NaN.
        """
        step = np.interp(np.clip(lambda_mm, 0.0, None), self.lambda_mm, np.arange(len(self.lambda_mm)))
        iz = (points_mm[:, 1] - self.grid_z_mm[0]) / (self.grid_z_mm[1] - self.grid_z_mm[0])
        ix = (points_mm[:, 0] - self.grid_x_mm[0]) / (self.grid_x_mm[1] - self.grid_x_mm[0])
        coordinates = np.vstack([step, iz, ix])
        result = np.column_stack(
            [map_coordinates(field[c], coordinates, order=1, mode="constant", cval=np.nan) for c in (0, 1)]
        )
        return result


def variant_specs(spec: SectionSpec) -> dict[str, SectionSpec]:
    """The library's sections: ideal, nearly incompressible, sliding, soft top layers on a grid, lumen pressures."""
    variants = {
        "ideal": spec,
        "poisson": dataclasses.replace(spec, poisson_ratio=POISSON_RATIOS[1]),
        "slide": dataclasses.replace(spec, contact="slide"),
    }
    for thickness in LAYER_THICKNESSES_MM:
        for ratio in LAYER_MODULUS_RATIOS:
            layer = Layer(thickness_mm=thickness, shear_modulus_kpa=spec.shear_modulus_kpa * ratio)
            variants[f"layer_{thickness:g}_{ratio:g}"] = dataclasses.replace(spec, layers=(layer,))
    for ratio in PRESSURE_RATIOS:
        variants[f"pressure_{ratio:g}"] = dataclasses.replace(spec, lumen_pressure_kpa=spec.shear_modulus_kpa * ratio)
    return variants


def _section_from(observation: Observation) -> tuple[SectionSpec, bool]:
    """The ideal section with the reference lumen snapped to the geometry grid."""
    if observation.vessel_center_probe_mm is None or observation.vessel_radius_mm is None:
        x, depth, radius = _PLACEHOLDER_VESSEL
        has_vessel = False
    else:
        reference_lambda = max(float(observation.probe_displacement_mm[observation.reference_index]), 0.0)
        x = float(np.round(observation.vessel_center_probe_mm[0]))
        depth = float(np.round(2 * (observation.vessel_center_probe_mm[1] + reference_lambda)) / 2)
        radius = float(np.clip(np.round(2 * observation.vessel_radius_mm) / 2, 1.5, 12.0))
        depth = float(np.clip(depth, radius + 3.0, 60.0 - radius - 3.0))
        x = float(np.clip(x, -55.0 + radius, 55.0 - radius))
        has_vessel = True
    spec = SectionSpec(
        vessel_center_x_mm=x,
        vessel_depth_mm=depth,
        vessel_radius_mm=radius,
        shear_modulus_kpa=LIBRARY_SHEAR_MODULUS_KPA,
        poisson_ratio=POISSON_RATIOS[0],
        mesh_size_mm=min(LIBRARY_MESH_MM, radius),
    )
    return spec, has_vessel


def _grid(solution: MechanicsSolution, grid_x: np.ndarray, grid_z: np.ndarray) -> np.ndarray:
    """(2, ns, nz, nx) displacement of the grid points at every solved step."""
    xx, zz = np.meshgrid(grid_x, grid_z)
    points = np.column_stack([xx.ravel(), zz.ravel()])
    steps = solution.probe_displacement_mm
    values = np.stack([solution.displacement(points, float(lam), outside="nan") for lam in steps])
    return values.reshape(len(steps), len(grid_z), len(grid_x), 2).transpose(3, 0, 1, 2)


def calibrate(observation: Observation, *, progress=None) -> CalibratedSection:
    """Calibrate the ideal simulator (geometry, modulus) to one observation and build its variant library.

    ``progress``: an optional tqdm-like object whose ``update(1)`` is called after each solve.
    """
    spec, has_vessel = _section_from(observation)
    lam = observation.probe_displacement_mm
    top = float(np.max(lam)) * 1.15 + 0.5
    if top > 0.45 * spec.depth_mm:
        raise InputError(
            f"{observation.name}: ProbeDisplacement: {np.max(lam):.3g} mm of indentation is more than the "
            f"calibrated section can take ({0.45 * spec.depth_mm / 1.15:.3g} mm)"
        )
    steps = np.linspace(0.0, top, int(np.ceil(top / _LAMBDA_STEP_MM)) + 1)
    half_width = float(np.max(np.abs(observation.image_to_probe[0, 3]))) + 8.0
    rows = observation.frame_shape[0]
    depth = float(observation.image_to_probe[2, 1] * rows + observation.image_to_probe[2, 3]) * 1.15 + top + 2.0
    grid_x = np.arange(-half_width, half_width + 1e-9, _GRID_SPACING_MM)
    grid_z = np.arange(0.0, min(depth, spec.depth_mm) + 1e-9, _GRID_SPACING_MM)
    fields, areas, forces = {}, {}, {}
    for name, variant in variant_specs(spec).items():
        if not has_vessel and name.startswith("pressure"):
            continue
        solution = solve_section(variant, steps)
        fields[name] = _grid(solution, grid_x, grid_z)
        areas[name] = np.array([solution.lumen_area_mm2(float(v)) for v in steps])
        forces[name] = solution.force_n  # at lambda = 0 the reaction of a pressurised lumen, 0 otherwise
        if progress is not None:
            progress.update(1)
    loading = observation.phase == 0
    fem_force = np.interp(np.clip(lam[loading], 0, None), steps, forces["ideal"])
    scale = float(fem_force @ observation.force_n[loading] / max(fem_force @ fem_force, 1e-12))
    if not scale > 0:
        raise InputError(f"{observation.name}: ContactForce: the force does not rise with ProbeDisplacement")
    return CalibratedSection(
        spec=spec,
        grid_x_mm=grid_x,
        grid_z_mm=grid_z,
        lambda_mm=steps,
        fields=fields,
        lumen_area_mm2=areas,
        force_n=forces,
        shear_modulus_kpa=LIBRARY_SHEAR_MODULUS_KPA * scale,
        has_vessel=has_vessel,
    )
