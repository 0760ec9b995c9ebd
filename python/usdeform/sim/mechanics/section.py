"""The section a mechanics solve models: geometry, layers and Yeoh material (see :mod:`usdeform.sim.mechanics`)."""

from __future__ import annotations

import dataclasses
import hashlib
import json
import math
from dataclasses import dataclass
from typing import Literal

import numpy as np

from ...errors import InputError, UsdeformError

PROBE_WIDTH_MM = 37.5
"""Default width of the flat probe face (Cephasonics CPLA12875 footprint used in the paper), mm."""

_MAX_FACE_TILT_DEG = 30.0
_SOLVER_VERSION = 1  # bump whenever the discretisation or the solver changes its results


class MechanicsConvergenceError(UsdeformError, RuntimeError):
    """Newton's method did not converge at a load step (the message names the step)."""


def _check_yeoh(owner: str, c2: float, c3: float) -> None:
    """The Yeoh energy must increase with I1bar: 1 + 2 c2 x + 3 c3 x^2 > 0 for all x >= 0."""
    if not (np.isfinite(c2) and np.isfinite(c3) and c3 >= 0 and (c2 >= 0 or c2 * c2 < 3 * c3)):
        raise InputError(f"{owner}: Yeoh ratios need c3 >= 0 and c2^2 < 3 c3 when c2 < 0, got c2={c2}, c3={c3}")


@dataclass(frozen=True)
class Layer:
    """A tissue layer below the surface (or below the previous layer).

    thickness_mm: layer thickness, mm. shear_modulus_kpa: small-strain shear modulus, kPa.
    yeoh_c2, yeoh_c3: Yeoh ratios C20/C10 and C30/C10 (dimensionless, 0 = neo-Hookean).
    """

    thickness_mm: float
    shear_modulus_kpa: float
    yeoh_c2: float = 0.0
    yeoh_c3: float = 0.0


@dataclass(frozen=True)
class Vessel:
    """A further lumen of a section, beside its main vessel (a vein beside an artery, a branch).

    center_x_mm: lateral position of its centre, mm. depth_mm: depth of its centre below the undeformed
    surface, mm. radius_mm: its radius, mm. lumen_stiffness_ratio: its lumen's modulus / the surrounding
    modulus (a vein's collapsible lumen: a few percent).
    """

    center_x_mm: float
    depth_mm: float
    radius_mm: float
    lumen_stiffness_ratio: float = 0.05


@dataclass(frozen=True)
class SectionSpec:
    """One tissue cross-section: geometry, material, boundary conditions and mesh size.

    Lengths in mm, moduli and pressures in kPa; frame: x lateral (0 at the probe centre), z depth
    (0 at the undeformed surface, down positive). ``vessel_depth_mm`` is the depth of the lumen
    centre below the undeformed surface. The base material (below the layers) has shear modulus
    ``shear_modulus_kpa`` and Yeoh ratios ``yeoh_c2`` = C20/C10, ``yeoh_c3`` = C30/C10
    (dimensionless; the energy must grow with I1bar: c3 >= 0, and c2^2 < 3 c3 when c2 < 0).
    Every material shares the small-strain ``poisson_ratio`` (0.45: a compressible stand-in for
    nearly incompressible tissue that P2 elements resolve without locking).
    ``lumen_stiffness_ratio`` is lumen modulus / surrounding modulus (0.05 = 20 times softer).
    ``out_of_plane_width_mm`` converts the plane-strain reaction (N/mm) to newtons. ``layers`` run
    from the surface down; ``contact`` is ``"stick"`` or ``"slide"`` (frictionless);
    ``lumen_pressure_kpa`` is the pressure inside the lumen. ``probe_width_mm`` is the width of the flat
    probe face, centred at x = 0 (the transducer array and the housing around it). ``mesh_size_mm`` is the
    target edge length of the triangles. ``lateral_stiffness_gradient`` g makes every modulus vary across
    the section: times ``1 + g * clip(x / (probe_width_mm / 2), -1, 1)`` (|g| < 1; 0.3: 30 % softer under the
    probe's left edge and 30 % stiffer under its right, as tissue that changes across the probe face).
    ``face_tilt_deg`` is the angle of the face to the undeformed surface within the section (|tilt| <= 30;
    positive: the face's +x edge is the lower one and touches first), a probe tilted over the surface or a
    surface inclined under the probe; ``face_radius_mm`` is the radius of a convex face (inf: flat). A face that
    is not flat and level meets the surface progressively: lambda counts from first contact, a node under the face
    is in contact once the face reaches it and leaves contact when the face would pull it (see
    :mod:`usdeform.sim.mechanics`). ``face_travel_deg`` is the angle of the face's travel to the surface normal
    (|angle| <= 30; positive towards +x; lambda is its normal component): 0 for a robot pressing along the
    surface normal, ``-face_tilt_deg`` for one pressing along the axis of a probe whose face is tilted to the
    surface. Only a sticking face drags the tissue along with its lateral travel.
    ``extra_vessels`` are further lumens (:class:`Vessel`), each with its own lumen stiffness, apart from the main
    vessel and each other by at least two mesh sizes.
    The defaults are the ideal variants (no layers, sticking, no pressure, laterally uniform, flat level face).
    """

    width_mm: float = 120.0
    depth_mm: float = 60.0
    vessel_center_x_mm: float = 0.0
    vessel_depth_mm: float = 20.0
    vessel_radius_mm: float = 5.0
    shear_modulus_kpa: float = 20.0
    yeoh_c2: float = 0.0
    yeoh_c3: float = 0.0
    poisson_ratio: float = 0.45
    lumen_stiffness_ratio: float = 0.05
    out_of_plane_width_mm: float = 20.0
    layers: tuple[Layer, ...] = ()
    contact: Literal["stick", "slide"] = "stick"
    lumen_pressure_kpa: float = 0.0
    probe_width_mm: float = PROBE_WIDTH_MM
    mesh_size_mm: float = 1.5
    lateral_stiffness_gradient: float = 0.0
    face_tilt_deg: float = 0.0
    face_radius_mm: float = math.inf
    face_travel_deg: float = 0.0
    extra_vessels: tuple[Vessel, ...] = ()

    def __post_init__(self) -> None:
        object.__setattr__(self, "layers", tuple(self.layers))
        object.__setattr__(self, "extra_vessels", tuple(self.extra_vessels))
        for field in dataclasses.fields(self):
            value = getattr(self, field.name)
            if field.name not in ("layers", "contact", "extra_vessels") and not isinstance(
                value, (int, float, np.number)
            ):
                raise InputError(f"SectionSpec.{field.name} must be a number, got {value!r}")
        for name in (
            "width_mm",
            "depth_mm",
            "vessel_radius_mm",
            "shear_modulus_kpa",
            "lumen_stiffness_ratio",
            "out_of_plane_width_mm",
            "probe_width_mm",
            "mesh_size_mm",
        ):
            value = getattr(self, name)
            if not (np.isfinite(value) and value > 0):
                raise InputError(f"SectionSpec.{name} must be a positive finite number, got {value!r}")
        if not (abs(self.face_tilt_deg) <= _MAX_FACE_TILT_DEG):
            raise InputError(
                f"SectionSpec.face_tilt_deg must be within +-{_MAX_FACE_TILT_DEG} degrees, got {self.face_tilt_deg}"
            )
        if not (abs(self.face_travel_deg) <= _MAX_FACE_TILT_DEG):
            raise InputError(
                f"SectionSpec.face_travel_deg must be within +-{_MAX_FACE_TILT_DEG} degrees, got {self.face_travel_deg}"
            )
        if not (self.face_radius_mm >= self.probe_width_mm / 2):  # NaN fails too
            raise InputError(
                f"SectionSpec.face_radius_mm must be at least half the probe width ({self.probe_width_mm / 2} mm) "
                f"or inf (flat), got {self.face_radius_mm}"
            )
        for name in ("vessel_center_x_mm", "vessel_depth_mm", "lumen_pressure_kpa"):
            if not np.isfinite(getattr(self, name)):
                raise InputError(f"SectionSpec.{name} must be finite, got {getattr(self, name)!r}")
        _check_yeoh("SectionSpec", self.yeoh_c2, self.yeoh_c3)
        if not abs(self.lateral_stiffness_gradient) < 1:
            raise InputError(
                f"SectionSpec.lateral_stiffness_gradient must be in (-1, 1), got {self.lateral_stiffness_gradient}"
            )
        if not 0.0 <= self.poisson_ratio < 0.5:
            raise InputError(f"SectionSpec.poisson_ratio must be in [0, 0.5), got {self.poisson_ratio}")
        if self.lumen_stiffness_ratio > 1:
            raise InputError(
                "SectionSpec.lumen_stiffness_ratio is lumen modulus / tissue modulus and must be in (0, 1], "
                f"got {self.lumen_stiffness_ratio}"
            )
        if self.contact not in ("stick", "slide"):
            raise InputError(f"SectionSpec.contact must be 'stick' or 'slide', got {self.contact!r}")
        if self.width_mm < 3 * self.probe_width_mm:
            raise InputError(
                f"SectionSpec.width_mm must be at least 3 probe widths ({3 * self.probe_width_mm} mm), "
                f"got {self.width_mm}"
            )
        if self.mesh_size_mm > min(self.vessel_radius_mm, self.depth_mm / 8):
            raise InputError(
                f"SectionSpec.mesh_size_mm={self.mesh_size_mm} is too coarse for a vessel of radius "
                f"{self.vessel_radius_mm} mm in a {self.depth_mm} mm deep section"
            )
        margin = self.mesh_size_mm
        top, bottom = self.vessel_depth_mm - self.vessel_radius_mm, self.vessel_depth_mm + self.vessel_radius_mm
        if top < margin or bottom > self.depth_mm - margin:
            raise InputError(
                f"vessel (depth {self.vessel_depth_mm} mm, radius {self.vessel_radius_mm} mm) must lie inside the "
                f"section depth [0, {self.depth_mm}] mm with at least one mesh size ({margin} mm) to spare"
            )
        if abs(self.vessel_center_x_mm) + self.vessel_radius_mm > self.width_mm / 2 - margin:
            raise InputError(
                f"vessel (x {self.vessel_center_x_mm} mm, radius {self.vessel_radius_mm} mm) must lie inside the "
                f"section width [{-self.width_mm / 2}, {self.width_mm / 2}] mm"
            )
        for index, layer in enumerate(self.layers):
            if not isinstance(layer, Layer):
                raise InputError(f"SectionSpec.layers[{index}] must be a Layer, got {type(layer).__name__}")
            if not (layer.thickness_mm > 0 and layer.shear_modulus_kpa > 0):
                raise InputError(f"SectionSpec.layers[{index}] needs positive thickness and modulus, got {layer}")
            _check_yeoh(f"SectionSpec.layers[{index}]", layer.yeoh_c2, layer.yeoh_c3)
        if sum(layer.thickness_mm for layer in self.layers) >= self.depth_mm:
            raise InputError("SectionSpec.layers are thicker than the section")
        self._check_extra_vessels()

    def _check_extra_vessels(self) -> None:
        """Each extra vessel is a Vessel inside the section, clear of the other lumens by two mesh sizes."""
        margin = self.mesh_size_mm
        for index, vessel in enumerate(self.extra_vessels):
            where = f"SectionSpec.extra_vessels[{index}]"
            if not isinstance(vessel, Vessel):
                raise InputError(f"{where} must be a Vessel, got {type(vessel).__name__}")
            if not all(np.isfinite([vessel.center_x_mm, vessel.depth_mm])):
                raise InputError(f"{where}: centre must be finite, got {vessel}")
            if not (margin <= vessel.radius_mm and 0 < vessel.lumen_stiffness_ratio <= 1):
                raise InputError(
                    f"{where}: needs a radius of at least one mesh size and a ratio in (0, 1], got {vessel}"
                )
            if (
                vessel.depth_mm - vessel.radius_mm < margin
                or vessel.depth_mm + vessel.radius_mm > self.depth_mm - margin
                or abs(vessel.center_x_mm) + vessel.radius_mm > self.width_mm / 2 - margin
            ):
                raise InputError(f"{where} must lie inside the section with one mesh size ({margin} mm) to spare")
        lumens = self.lumens
        for first in range(len(lumens)):
            for second in range(first + 1, len(lumens)):
                gap = np.hypot(*(lumens[first][:2] - lumens[second][:2])) - lumens[first][2] - lumens[second][2]
                if gap < 2 * margin:
                    raise InputError(
                        f"SectionSpec: lumens {first} and {second} are {gap:.3g} mm apart, less than two mesh sizes"
                    )

    @property
    def lumens(self) -> np.ndarray:
        """(n_vessels, 4) of (centre x, centre depth, radius, lumen stiffness ratio), mm: the main vessel first,
        then ``extra_vessels``."""
        return np.array(
            [(self.vessel_center_x_mm, self.vessel_depth_mm, self.vessel_radius_mm, self.lumen_stiffness_ratio)]
            + [(v.center_x_mm, v.depth_mm, v.radius_mm, v.lumen_stiffness_ratio) for v in self.extra_vessels],
            dtype=np.float64,
        )

    def lumen_index(self, points_xz_mm: np.ndarray) -> np.ndarray:
        """(m,) int: the lumen (row of :attr:`lumens`) each reference point (m, 2) (x, depth, mm) lies in; -1: none."""
        points = np.asarray(points_xz_mm, dtype=np.float64).reshape(-1, 2)
        lumens = self.lumens
        distance = np.hypot(points[:, None, 0] - lumens[:, 0], points[:, None, 1] - lumens[:, 1]) - lumens[:, 2]
        nearest = np.argmin(distance, axis=1)
        return np.where(distance[np.arange(len(points)), nearest] < 0, nearest, -1)

    def lumen_modulus_factor(self, points_xz_mm: np.ndarray) -> np.ndarray:
        """(m,) the factor on the moduli at reference points (m, 2) (x, depth, mm): the lumen stiffness ratio of
        the lumen a point lies in, 1 outside the lumens."""
        index = self.lumen_index(points_xz_mm)
        return np.where(index >= 0, self.lumens[np.maximum(index, 0), 3], 1.0)

    @property
    def bulk_modulus_ratio(self) -> float:
        """kappa / mu of every material, from the small-strain Poisson ratio."""
        nu = self.poisson_ratio
        return 2 * (1 + nu) / (3 * (1 - 2 * nu))

    def scaled(self, factor: float) -> SectionSpec:
        """The same section with every modulus and the lumen pressure multiplied by ``factor``.

        Its solution has the same displacement field and ``factor`` times the force.
        """
        if not (np.isfinite(factor) and factor > 0):
            raise InputError(f"modulus scale factor must be positive and finite, got {factor!r}")
        return dataclasses.replace(
            self,
            shear_modulus_kpa=self.shear_modulus_kpa * factor,
            lumen_pressure_kpa=self.lumen_pressure_kpa * factor,
            layers=tuple(
                dataclasses.replace(layer, shear_modulus_kpa=layer.shear_modulus_kpa * factor) for layer in self.layers
            ),
        )

    def lateral_factor(self, x_mm: np.ndarray) -> np.ndarray:
        """The factor (dimensionless) of ``lateral_stiffness_gradient`` on the moduli at lateral positions x (mm)."""
        return 1.0 + self.lateral_stiffness_gradient * np.clip(x_mm / (self.probe_width_mm / 2), -1.0, 1.0)

    @property
    def face_is_flat_and_level(self) -> bool:
        """Whether the whole face touches the surface at once (lambda = 0)."""
        return self.face_tilt_deg == 0 and math.isinf(self.face_radius_mm)

    def _face_height_mm(self, x_mm: np.ndarray) -> np.ndarray:
        """Height (mm, up) of the face above the line through its centre parallel to the surface, at x (mm)."""
        height = -x_mm * np.tan(np.radians(self.face_tilt_deg))
        if math.isfinite(self.face_radius_mm):
            height = height + self.face_radius_mm - np.sqrt(self.face_radius_mm**2 - x_mm**2)
        return height

    def face_gap_mm(self, x_mm: np.ndarray) -> np.ndarray:
        """Distance (mm, along z) between the face and the undeformed surface at lateral positions x (mm) under the
        face, at first contact (lambda = 0): 0 where the face touches first."""
        half = self.probe_width_mm / 2
        candidates = [-half, half]
        if math.isfinite(self.face_radius_mm):  # where the arc's slope equals the tilt's
            candidates.append(float(np.clip(self.face_radius_mm * np.sin(np.radians(self.face_tilt_deg)), -half, half)))
        lowest = float(np.min(self._face_height_mm(np.array(candidates))))
        return self._face_height_mm(np.asarray(x_mm, dtype=np.float64)) - lowest

    def cache_key(self, probe_displacement_mm: np.ndarray) -> str:
        """Hex digest of every parameter, the lambda steps and the solver version (parameters at their ideal values
        that were added later are left out, so that solutions cached before they existed stay valid)."""
        spec = dataclasses.asdict(self)
        for name in (
            "lateral_stiffness_gradient",
            "face_tilt_deg",
            "face_radius_mm",
            "face_travel_deg",
            "extra_vessels",
        ):
            if spec[name] == SectionSpec.__dataclass_fields__[name].default:
                del spec[name]
        payload = {
            "spec": spec,
            "lambda_mm": [float(v) for v in np.asarray(probe_displacement_mm, dtype=float)],
            "solver_version": _SOLVER_VERSION,
        }
        return hashlib.sha256(json.dumps(payload, sort_keys=True).encode()).hexdigest()[:32]
