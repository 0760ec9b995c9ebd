"""Vessel phantoms whose stiffness and vessel vary along the sweep direction s (mm).

A :class:`Phantom` is a family of cross-sections :class:`~usdeform.sim.mechanics.SectionSpec`
indexed by the sweep coordinate ``s`` in ``[0, length_mm]``:

* the **stiffness** varies as ``scale(s) = 1 + stiffness_amplitude * sin(2 pi s / length_mm)``
  (1 at both ends and in the middle, a maximum at a quarter and a minimum at three quarters), and
  multiplies every modulus of ``base_section``;
* the **vessel** moves smoothly (raised cosine in s) from the base geometry at s = 0 by
  ``vessel_shift_x_mm``, ``vessel_shift_depth_mm`` and ``vessel_radius_change_mm`` at the far end;
  the section's extra vessels (a vein beside the artery) move with it and keep their radius, or move and
  change towards ``extra_vessels_end`` (a branch leaving the artery).

Solving costs: the force and field of a hyperelastic section scale exactly with its moduli (see
:mod:`usdeform.sim.mechanics`), so only the vessel geometry needs separate solves. The phantom
solves ``geometry_knots`` sections equally spaced in s at unit stiffness scale (each cached on
disk); at other positions it blends the two neighbouring knot solutions linearly in s (fields and
forces) and scales the force by ``scale(s)``. The blend is an approximation whose error grows with
the geometry change between knots: with the presets' 5 knots (20 mm apart, at most ~0.9 mm of vessel
motion between knots) the force is within 0.2 %, the lumen wall within 0.2 mm and its area within
0.5 % of a direct solve at the same position.
In a phantom the lumen pressure scales with the local stiffness (needed for exact scaling).

Presets: :func:`stiff_phantom` and :func:`soft_phantom`, calibrated to the force-displacement
curves of the paper's gelatin phantom (3237 +/- 56 N/m up to 30 N, nearly linear) and commercial
CAE blue phantom (1489 +/- 617 N/m up to 16 N, clearly nonlinear), with the vessel areas it reports
(224 mm^2 and 57 mm^2); :func:`compliant_vessel_phantom`, whose small vessel collapses (loses about
a third of its area at the highest force), as in independent simulations of compliant vessels.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np

from ..errors import InputError
from .mechanics import Layer, MechanicsSolution, SectionSpec, Vessel, solve_section

__all__ = [
    "PRESET_MESH_SIZE_MM",
    "Phantom",
    "artery_vein_phantom",
    "branching_phantom",
    "coarse_phantom",
    "compliant_vessel_phantom",
    "soft_phantom",
    "stiff_phantom",
]


@dataclass(frozen=True)
class Phantom:
    """A vessel phantom: cross-sections along the sweep coordinate s in [0, length_mm] (mm).

    base_section: the section at s = 0 (stiffness scale 1). max_probe_displacement_mm and
    n_probe_steps: the lambda grid (mm) every position is solved on. max_force_n: the largest
    palpation force (N) meant for this phantom (the paper's range).
    """

    name: str
    base_section: SectionSpec
    length_mm: float = 80.0
    stiffness_amplitude: float = 0.1
    vessel_shift_x_mm: float = 0.0
    vessel_shift_depth_mm: float = 0.0
    vessel_radius_change_mm: float = 0.0
    max_force_n: float = 30.0
    max_probe_displacement_mm: float = 12.0
    n_probe_steps: int = 25
    geometry_knots: int = 5
    extra_vessels_end: tuple[Vessel, ...] = ()

    def __post_init__(self) -> None:
        if not isinstance(self.base_section, SectionSpec):
            raise InputError("Phantom.base_section must be a SectionSpec")
        object.__setattr__(self, "extra_vessels_end", tuple(self.extra_vessels_end))
        if self.extra_vessels_end and len(self.extra_vessels_end) != len(self.base_section.extra_vessels):
            raise InputError(
                f"Phantom.extra_vessels_end: expected one Vessel per extra vessel of the base section "
                f"({len(self.base_section.extra_vessels)}), got {len(self.extra_vessels_end)}"
            )
        if not (self.length_mm > 0 and 0 <= self.stiffness_amplitude < 1 and self.max_force_n > 0):
            raise InputError("Phantom needs length_mm > 0, 0 <= stiffness_amplitude < 1 and max_force_n > 0")
        if self.n_probe_steps < 2 or self.geometry_knots < 2 or self.max_probe_displacement_mm <= 0:
            raise InputError(
                "Phantom needs n_probe_steps >= 2, geometry_knots >= 2 and a positive max_probe_displacement_mm"
            )
        for s in (0.0, self.length_mm):  # the far-end geometry must be a valid section too
            self.section_at(s)

    @property
    def probe_displacement_mm(self) -> np.ndarray:
        """The lambda steps (mm) every position is solved on."""
        return np.linspace(0.0, self.max_probe_displacement_mm, self.n_probe_steps)

    @property
    def knot_positions_mm(self) -> np.ndarray:
        """Sweep positions (mm) at which the vessel geometry is solved."""
        return np.linspace(0.0, self.length_mm, self.geometry_knots)

    def _check_position(self, s_mm: float) -> float:
        s = float(s_mm)
        if not (np.isfinite(s) and 0.0 <= s <= self.length_mm):
            raise InputError(f"sweep position {s_mm} mm is outside the phantom [0, {self.length_mm}] mm")
        return s

    def stiffness_scale_at(self, s_mm):
        """Factor (dimensionless) multiplying every modulus at sweep position(s) s (mm)."""
        s = np.asarray(s_mm, dtype=float)
        if np.any(~np.isfinite(s)) or np.any(s < 0) or np.any(s > self.length_mm):
            raise InputError(f"sweep positions must lie in [0, {self.length_mm}] mm")
        return 1.0 + self.stiffness_amplitude * np.sin(2 * np.pi * s / self.length_mm)

    def unscaled_section_at(self, s_mm: float) -> SectionSpec:
        """The cross-section at sweep position s (mm) with the moduli of ``base_section`` (scale 1)."""
        s = self._check_position(s_mm)
        progress = 0.5 * (1.0 - np.cos(np.pi * s / self.length_mm))
        base = self.base_section
        return dataclasses.replace(
            base,
            vessel_center_x_mm=base.vessel_center_x_mm + progress * self.vessel_shift_x_mm,
            vessel_depth_mm=base.vessel_depth_mm + progress * self.vessel_shift_depth_mm,
            vessel_radius_mm=base.vessel_radius_mm + progress * self.vessel_radius_change_mm,
            extra_vessels=tuple(
                self._extra_vessel_at(index, float(progress)) for index in range(len(base.extra_vessels))
            ),
        )

    def _extra_vessel_at(self, index: int, progress: float) -> Vessel:
        """Extra vessel ``index`` at the sweep's ``progress`` (0 to 1, raised cosine in s): moving towards its
        entry of ``extra_vessels_end`` where given, else with the main vessel's shift and its own radius."""
        vessel = self.base_section.extra_vessels[index]
        if not self.extra_vessels_end:
            return dataclasses.replace(
                vessel,
                center_x_mm=vessel.center_x_mm + progress * self.vessel_shift_x_mm,
                depth_mm=vessel.depth_mm + progress * self.vessel_shift_depth_mm,
            )
        end = self.extra_vessels_end[index]
        return Vessel(
            *(
                a + progress * (b - a)
                for a, b in zip(dataclasses.astuple(vessel), dataclasses.astuple(end), strict=True)
            )
        )

    def section_at(self, s_mm: float) -> SectionSpec:
        """The cross-section (moduli scaled, vessel moved) at sweep position s (mm)."""
        s = self._check_position(s_mm)
        return self.unscaled_section_at(s).scaled(float(self.stiffness_scale_at(s)))

    def solution_at(self, s_mm: float, probe_displacement_mm: np.ndarray | None = None) -> MechanicsSolution:
        """Mechanics at sweep position s (mm), on ``self.probe_displacement_mm`` unless given.

        Blends the cached solves of the two neighbouring geometry knots and scales the force.
        """
        s = self._check_position(s_mm)
        lam = self.probe_displacement_mm if probe_displacement_mm is None else probe_displacement_mm
        knots = self.knot_positions_mm
        upper = int(np.clip(np.searchsorted(knots, s, side="right"), 1, len(knots) - 1))
        weight_upper = (s - knots[upper - 1]) / (knots[upper] - knots[upper - 1])
        weights = {upper - 1: 1.0 - weight_upper, upper: weight_upper}
        used = [i for i, weight in weights.items() if weight > 0]
        knot_solutions = [solve_section(self.unscaled_section_at(float(knots[i])), lam) for i in used]
        blended = MechanicsSolution.blend(knot_solutions, [weights[i] for i in used], self.unscaled_section_at(s))
        return blended.scaled(float(self.stiffness_scale_at(s)))

    def with_section_changes(self, **changes) -> Phantom:
        """The same phantom with fields of ``base_section`` replaced (e.g. contact="slide", layers=...)."""
        return dataclasses.replace(self, base_section=dataclasses.replace(self.base_section, **changes))


# Calibration. The Yeoh ratios set the curvature of F(lambda) (the SD of the dynamic stiffness
# relative to its mean) and the shear modulus its level (exact, by the force scaling); both were
# fitted on the preset mesh (PRESET_MESH_SIZE_MM) against the paper's numbers with lambda sampled
# uniformly from 0 to the force limit. The moduli are therefore effective values, not material
# data: they depend on the effective out-of-plane width (20 mm, standing for the probe's ~10 mm
# elevational footprint plus the spread of the deformation beyond it; moduli scale inversely with
# it) and on the section depth (60 mm). For orientation, they correspond to Young's moduli of
# about 100 kPa (stiff) and 30 kPa (soft), the range reported for gelatin and elastomer
# tissue-mimicking phantoms (e.g. Hall et al. 1997, IEEE TUFFC 44:1355).
PRESET_MESH_SIZE_MM = 2.0
_STIFF_SHEAR_MODULUS_KPA = 40.8
_STIFF_YEOH = (-0.17, 0.02)
_SOFT_SHEAR_MODULUS_KPA = 9.2
_SOFT_YEOH = (3.35, 6.4)


def stiff_phantom() -> Phantom:
    """The paper's custom gelatin phantom (175 g/L gelatin, paper pulp): stiff and nearly linear.

    k = 3237 +/- 56 N/m over forces up to 30 N; vessel area 224 mm^2 (radius 8.44 mm). A mildly
    softening-then-stiffening Yeoh law (c2 < 0 < c3) offsets the geometric stiffening of the
    indentation (the layer under the probe thins) so that F(lambda) is as linear as measured.
    Homogeneous: stiffness varies by +/-4 % along s.
    """
    section = SectionSpec(
        vessel_center_x_mm=0.0,
        vessel_depth_mm=20.0,
        vessel_radius_mm=8.44,
        shear_modulus_kpa=_STIFF_SHEAR_MODULUS_KPA,
        yeoh_c2=_STIFF_YEOH[0],
        yeoh_c3=_STIFF_YEOH[1],
        mesh_size_mm=PRESET_MESH_SIZE_MM,
    )
    return Phantom(
        name="stiff",
        base_section=section,
        length_mm=80.0,
        stiffness_amplitude=0.04,
        vessel_shift_x_mm=3.0,
        vessel_shift_depth_mm=2.0,
        vessel_radius_change_mm=-0.5,
        max_force_n=30.0,
        max_probe_displacement_mm=11.0,
        n_probe_steps=23,
    )


def soft_phantom() -> Phantom:
    """The paper's commercial blue phantom (CAE, an elastomer): soft and clearly nonlinear.

    k = 1489 +/- 617 N/m over forces up to 16 N; vessel area 57 mm^2 (radius 4.26 mm). Strong
    Yeoh stiffening (c2, c3 > 0); stiffness varies by +/-15 % along s.
    """
    section = SectionSpec(
        vessel_center_x_mm=0.0,
        vessel_depth_mm=15.0,
        vessel_radius_mm=4.26,
        shear_modulus_kpa=_SOFT_SHEAR_MODULUS_KPA,
        yeoh_c2=_SOFT_YEOH[0],
        yeoh_c3=_SOFT_YEOH[1],
        mesh_size_mm=PRESET_MESH_SIZE_MM,
    )
    return Phantom(
        name="soft",
        base_section=section,
        length_mm=80.0,
        stiffness_amplitude=0.15,
        vessel_shift_x_mm=-4.0,
        vessel_shift_depth_mm=3.0,
        vessel_radius_change_mm=0.5,
        max_force_n=16.0,
        max_probe_displacement_mm=13.0,
        n_probe_steps=27,
    )


def compliant_vessel_phantom() -> Phantom:
    """A compliant vessel 15-22 mm deep that loses about 30 % of its lumen area at the highest force.

    Independent simulated data (another FEM engine and image model) show a compliant vessel 15 to
    22 mm deep, pressed 8 to 9 mm, whose area shrinks by 26 to 31 %; the presets' vessels keep
    their shape. Here: a 3.5 mm radius lumen centred 18.5 mm deep, 20 times softer than the tissue
    (neo-Hookean, shear modulus 20 kPa, stiffness varying by +/-5 % along s), pressed to 17 N,
    which takes 8.2 mm at the stiffest and 8.9 mm at the softest position. Finite-element area loss
    at lambda = 9 mm (``lumen_area_mm2``): 34.0 % on this 2 mm mesh, 34.2 % at 1.5 mm and 34.9 % at
    1 mm. The lumen has no speckle (as in every phantom). One vessel geometry along s: one solve.
    """
    section = SectionSpec(
        vessel_center_x_mm=0.0,
        vessel_depth_mm=18.5,
        vessel_radius_mm=3.5,
        shear_modulus_kpa=20.0,
        lumen_stiffness_ratio=0.05,
        mesh_size_mm=PRESET_MESH_SIZE_MM,
    )
    return Phantom(
        name="compliant-vessel",
        base_section=section,
        length_mm=80.0,
        stiffness_amplitude=0.05,
        max_force_n=17.0,
        max_probe_displacement_mm=9.5,
        n_probe_steps=20,
        geometry_knots=2,
    )


def coarse_phantom() -> Phantom:
    """A coarse, fast phantom for tests and smoke runs: about 2.4 N/mm, a vessel of radius 5 mm at 18 mm
    depth, a 3 mm mesh and one geometry solve (seconds, where the presets take minutes)."""
    section = SectionSpec(width_mm=115.0, depth_mm=50.0, vessel_depth_mm=18.0, vessel_radius_mm=5.0, mesh_size_mm=3.0)
    return Phantom(
        name="test",
        base_section=section,
        length_mm=60.0,
        stiffness_amplitude=0.2,
        max_force_n=15.0,
        max_probe_displacement_mm=8.0,
        n_probe_steps=5,
        geometry_knots=2,
    )


def artery_vein_phantom(
    bone_depth_mm: float = 32.0, vessel_shift_depth_mm: float = 0.0, vessel_radius_change_mm: float = 0.0
) -> Phantom:
    """A clinical section: skin (1.5 mm) and fat (5 mm) over muscle, an artery and a vein side by side,
    and a rigid bone ``bone_depth_mm`` (25-40 mm) deep, the section's fixed base.

    The artery (radius 3.5 mm, 14 mm deep, 5.5 mm left of the probe centre) has a lumen at 30 % of the
    muscle's modulus (a pressurised, thick-walled vessel); the vein (radius 2.9 mm, 12 mm deep, 5.5 mm
    right) at 3 %, so it collapses far more at the same force (about half its area where the artery
    loses an eighth). Muscle: neo-Hookean, 15 kPa; fat 6 kPa; skin 40 kPa. Stiffness varies by +/-10 %
    along s; both vessels move by ``vessel_shift_depth_mm`` over the sweep and the artery's radius
    changes by ``vessel_radius_change_mm``. Forces up to about 16 N (pressed 7 mm).
    """
    section = SectionSpec(
        width_mm=115.0,
        depth_mm=float(bone_depth_mm),
        vessel_center_x_mm=-5.5,
        vessel_depth_mm=14.0,
        vessel_radius_mm=3.5,
        shear_modulus_kpa=15.0,
        lumen_stiffness_ratio=0.3,
        layers=(Layer(1.5, 40.0), Layer(5.0, 6.0)),
        mesh_size_mm=1.5,
        extra_vessels=(Vessel(5.5, 12.0, 2.9, 0.03),),
    )
    return Phantom(
        name="artery-vein",
        base_section=section,
        length_mm=60.0,
        stiffness_amplitude=0.1,
        vessel_shift_depth_mm=vessel_shift_depth_mm,
        vessel_radius_change_mm=vessel_radius_change_mm,
        max_force_n=16.0,
        max_probe_displacement_mm=8.0,
        n_probe_steps=17,
        geometry_knots=_knots_for(max(abs(vessel_shift_depth_mm), abs(vessel_radius_change_mm))),
    )


#: Most vessel motion (mm) between two geometry knots of the clinical phantoms. Blending two knots' fields
#: smears a soft lumen's collapse: midway between knots, 5 mm pressed, the vein kept 83 % of its area with
#: knots 3.5 mm of motion apart, 72 % at 1 mm and 69.5 % at 0.5 mm, against 67.5 % solved directly.
_MAX_MOTION_PER_KNOT_MM = 0.5


def _knots_for(change_mm: float) -> int:
    """Geometry knots of a phantom whose vessels move or change by ``change_mm`` over the sweep."""
    return 2 + int(np.ceil(change_mm / _MAX_MOTION_PER_KNOT_MM)) if change_mm > 0 else 2


def branching_phantom() -> Phantom:
    """An artery (radius 3.5 mm, 16 mm deep, 4 mm left of the probe centre) with a side branch that leaves it
    along the sweep: 3 mm from its wall with a radius of 1.5 mm at the start, 8 mm from it, 2 mm shallower
    and 2.6 mm in radius at the far end (both lumens at 30 % of the muscle's modulus). The section is
    :func:`artery_vein_phantom`'s: skin and fat over muscle, a bone at 32 mm. Circles stand for the lumens, so
    the branch starts as a small vessel beside the artery rather than from its wall."""
    phantom = artery_vein_phantom()
    section = dataclasses.replace(
        phantom.base_section,
        vessel_center_x_mm=-4.0,
        vessel_depth_mm=16.0,
        extra_vessels=(Vessel(4.0, 16.0, 1.5, 0.3),),
    )
    return dataclasses.replace(
        phantom,
        name="branching",
        base_section=section,
        extra_vessels_end=(Vessel(10.1, 14.0, 2.6, 0.3),),
        geometry_knots=_knots_for(10.1 - 4.0),
    )
