"""Finite-element mechanics of one tissue cross-section pressed by a flat ultrasound probe.

What is modelled
----------------
* A rectangular section (x lateral, z depth; mm) in **plane strain**, bottom fixed, sides and the
  surface beside the probe traction-free.
* The probe is a rigid flat face 37.5 mm wide centred at x = 0, pressed down by a displacement
  ``lambda`` (mm). Contact under the face is either *sticking* (u_x = 0, u_z = lambda) or
  frictionless *sliding* (only u_z = lambda). The face is assumed to stay in full contact (no
  lift-off check; under a flat punch the contact pressure is compressive everywhere).
* Material: a compressible **Yeoh hyperelastic** law (Yeoh 1993, Rubber Chem. Technol. 66:754)
  ``W = mu/2 (x + c2 x^2 + c3 x^3) + kappa/4 (J^2 - 1 - 2 ln J)``, ``x = I1bar - 3``
  (isochoric first invariant of the plane-strain C, J = det F). ``mu`` is the small-strain shear
  modulus (so C10 = mu/2), ``c2 = C20/C10`` and ``c3 = C30/C10`` are dimensionless. ``c2 = c3 = 0``
  is neo-Hookean; ``c2, c3 > 0`` give strong strain-stiffening (the soft phantom: the CAE blue
  phantom is a rubber-like elastomer, and Yeoh is the usual law for rubbers and tissue-mimicking
  elastomers); ``c2 < 0 < c3`` (the classic filled-rubber shape) softens mildly at moderate strain
  and stiffens at large strain, which keeps the law stable at the singular probe edges (the stiff
  phantom). ``kappa`` follows from ``mu`` and the small-strain Poisson ratio. Neo-Hookean alone
  stiffens only mildly (5-8 % of k over the paper's indentations, mostly because the layer under
  the probe thins), too little for the soft phantom and too much for the stiff one.
* The vessel is a circular **soft inclusion** (same law, moduli times ``lumen_stiffness_ratio``,
  default 1/20; no self-contact), meshed conformingly, so that the displacement field is defined
  everywhere in the section. The inclusion does not conserve its volume: the phantom vessel is open
  at its ends, so fluid leaves as it collapses. An optional lumen pressure acts as the isotropic
  Cauchy stress ``-p I`` inside the lumen, which by the divergence theorem is exactly a follower
  pressure ``p`` on the lumen wall. It is ramped up at lambda = 0 with the probe face already held
  at z = 0: the reference circle is the unpressurised lumen, the lambda = 0 state is distended, and
  ``force_n[0]`` is the reaction of the pressurised vessel on the probe, not zero.
* Optional layers (skin / fat / muscle) from the surface downward, each with its own moduli.
* Quasi-static load stepping in lambda, full Newton on P2 (quadratic) triangles (a Delaunay mesh
  of a triangular lattice with rings of nodes on and around the lumen wall), with increment
  halving when Newton fails; the contact force is the reaction on the probe face (N per mm out of
  plane) times an effective out-of-plane width.

What is left out (on purpose; candidates for a sim-to-real diagnosis)
----------------------------------------------------------------------
Out-of-plane (3D) deformation beyond the effective width, probe tilt and rounded probe edges,
friction other than the two limits stick / frictionless slide, lift-off, self-contact of a
collapsed lumen, viscoelasticity and rate effects, gravity, fluid flow out of the vessel, and any
pre-stress of the phantom.

Scaling
-------
All loads are displacements (plus the lumen pressure), so multiplying every modulus (and the
lumen pressure) by a factor ``s`` leaves the displacement field unchanged and multiplies the force
by ``s``. :meth:`MechanicsSolution.scaled` exploits this; :mod:`usdeform.sim.phantoms` uses it to
serve many sweep positions from a few solves.

Units: mm, kPa for moduli and pressure, N for forces.
"""

from __future__ import annotations

import dataclasses
import hashlib
import itertools
import json
import os
import tempfile
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import numpy as np
import scipy.sparse.linalg
from scipy.spatial import Delaunay, cKDTree
from skfem import Basis, BilinearForm, ElementTriP2, ElementVector, LinearForm, MeshTri
from skfem.helpers import grad

from ..errors import InputError, UsdeformError

__all__ = [
    "PROBE_WIDTH_MM",
    "Layer",
    "MechanicsConvergenceError",
    "MechanicsSolution",
    "SectionSpec",
    "cache_dir",
    "section_mesh",
    "solve_section",
]

PROBE_WIDTH_MM = 37.5
"""Width of the flat probe face (Cephasonics CPLA12875 footprint used in the paper), mm."""

_KPA_TO_N_PER_MM2 = 1e-3
_SOLVER_VERSION = 1  # bump whenever the discretisation or the solver changes its results
_MAX_NEWTON_ITERATIONS = 12  # converged steps take 3-5; more means the increment is too large
_MAX_INVERSE_ITERATIONS = 20
_FIRST_INCREMENT_MM = 0.5  # first lambda increment from the unloaded state (no predictor yet), mm
_MAX_STEP_HALVINGS = 6


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
    ``lumen_pressure_kpa`` is the pressure inside the lumen. ``mesh_size_mm`` is the target edge
    length of the triangles. The defaults are the ideal variants (no layers, sticking, no pressure).
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
    mesh_size_mm: float = 1.5

    def __post_init__(self) -> None:
        object.__setattr__(self, "layers", tuple(self.layers))
        for field in dataclasses.fields(self):
            value = getattr(self, field.name)
            if field.name not in ("layers", "contact") and not isinstance(value, (int, float, np.number)):
                raise InputError(f"SectionSpec.{field.name} must be a number, got {value!r}")
        for name in (
            "width_mm",
            "depth_mm",
            "vessel_radius_mm",
            "shear_modulus_kpa",
            "lumen_stiffness_ratio",
            "out_of_plane_width_mm",
            "mesh_size_mm",
        ):
            value = getattr(self, name)
            if not (np.isfinite(value) and value > 0):
                raise InputError(f"SectionSpec.{name} must be a positive finite number, got {value!r}")
        for name in ("vessel_center_x_mm", "vessel_depth_mm", "lumen_pressure_kpa"):
            if not np.isfinite(getattr(self, name)):
                raise InputError(f"SectionSpec.{name} must be finite, got {getattr(self, name)!r}")
        _check_yeoh("SectionSpec", self.yeoh_c2, self.yeoh_c3)
        if not 0.0 <= self.poisson_ratio < 0.5:
            raise InputError(f"SectionSpec.poisson_ratio must be in [0, 0.5), got {self.poisson_ratio}")
        if self.lumen_stiffness_ratio > 1:
            raise InputError(
                "SectionSpec.lumen_stiffness_ratio is lumen modulus / tissue modulus and must be in (0, 1], "
                f"got {self.lumen_stiffness_ratio}"
            )
        if self.contact not in ("stick", "slide"):
            raise InputError(f"SectionSpec.contact must be 'stick' or 'slide', got {self.contact!r}")
        if self.width_mm < 3 * PROBE_WIDTH_MM:
            raise InputError(
                f"SectionSpec.width_mm must be at least 3 probe widths ({3 * PROBE_WIDTH_MM} mm), got {self.width_mm}"
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

    def cache_key(self, probe_displacement_mm: np.ndarray) -> str:
        """Hex digest of every parameter, the lambda steps and the solver version."""
        payload = {
            "spec": dataclasses.asdict(self),
            "lambda_mm": [float(v) for v in np.asarray(probe_displacement_mm, dtype=float)],
            "solver_version": _SOLVER_VERSION,
        }
        return hashlib.sha256(json.dumps(payload, sort_keys=True).encode()).hexdigest()[:32]


# ----------------------------------------------------------------------------------------------
# Mesh


def section_mesh(spec: SectionSpec) -> tuple[MeshTri, np.ndarray, np.ndarray]:
    """Triangulate the section conformingly to the lumen circle, the layer interfaces and the probe edges.

    Returns the mesh (node coordinates in mm, x lateral, z depth), a boolean per element that is
    True inside the lumen, and the material index per element (0..len(layers)-1 for the layers,
    len(layers) for the base material below them).
    """
    h = spec.mesh_size_mm
    half_width, half_probe = spec.width_mm / 2, PROBE_WIDTH_MM / 2
    # Lateral node positions: the probe edges are nodes, so the probe face is a union of edges.
    x_nodes = np.concatenate(
        [
            np.linspace(-half_width, -half_probe, max(2, int(np.ceil((half_width - half_probe) / h)) + 1))[:-1],
            np.linspace(-half_probe, half_probe, max(2, int(np.ceil(PROBE_WIDTH_MM / h)) + 1))[:-1],
            np.linspace(half_probe, half_width, max(2, int(np.ceil((half_width - half_probe) / h)) + 1)),
        ]
    )
    x_offset = np.concatenate([[x_nodes[0]], 0.5 * (x_nodes[1:] + x_nodes[:-1]), [x_nodes[-1]]])
    # Depth rows: layer interfaces are rows; rows about h*sqrt(3)/2 apart (equilateral-ish triangles).
    interfaces = np.concatenate([[0.0], np.cumsum([layer.thickness_mm for layer in spec.layers]), [spec.depth_mm]])
    row_spacing = h * np.sqrt(3) / 2
    z_rows = np.unique(
        np.concatenate(
            [
                np.linspace(a, b, max(2, int(np.ceil((b - a) / row_spacing)) + 1))
                for a, b in itertools.pairwise(interfaces)
            ]
        )
    )
    points = np.concatenate(
        [
            np.column_stack([x_nodes if i % 2 == 0 else x_offset, np.full(len(x_nodes) + (i % 2), z)])
            for i, z in enumerate(z_rows)
        ]
    )
    # Replace lattice points near the lumen wall by points on the wall and on two rings either side.
    centre = np.array([spec.vessel_center_x_mm, spec.vessel_depth_mm])
    radius = spec.vessel_radius_mm
    distance = np.linalg.norm(points - centre, axis=1)
    points = points[np.abs(distance - radius) > 0.75 * h]
    rings = [radius]
    if radius - 0.75 * h > 0.5 * h:
        rings.append(radius - 0.75 * h)
    rings.append(radius + 0.75 * h)
    n_wall = max(12, int(np.ceil(2 * np.pi * radius / h)))
    angles = 2 * np.pi * np.arange(n_wall) / n_wall
    ring_points = [
        centre + r * np.column_stack([np.cos(angles + k * np.pi / n_wall), np.sin(angles + k * np.pi / n_wall)])
        for k, r in enumerate(rings)
    ]
    points = np.concatenate([points] + ring_points)
    triangles = Delaunay(points).simplices
    corners = points[triangles]
    signed_area = 0.5 * (
        (corners[:, 1, 0] - corners[:, 0, 0]) * (corners[:, 2, 1] - corners[:, 0, 1])
        - (corners[:, 2, 0] - corners[:, 0, 0]) * (corners[:, 1, 1] - corners[:, 0, 1])
    )
    triangles = triangles[np.abs(signed_area) > 1e-9 * h * h]
    mesh = MeshTri(points.T.copy(), triangles.T.copy())
    centroids = mesh.p[:, mesh.t].mean(axis=1)
    in_lumen = np.linalg.norm(centroids.T - centre, axis=1) < radius
    material = np.searchsorted(interfaces[1:-1], centroids[1], side="right")
    return mesh, in_lumen, material


# ----------------------------------------------------------------------------------------------
# Material: compressible Yeoh law in plane strain (F33 = 1), stresses in N/mm^2


def _first_piola_and_tangent(
    displacement_gradient: np.ndarray,
    shear_modulus: np.ndarray,
    yeoh_c2: np.ndarray,
    yeoh_c3: np.ndarray,
    bulk_modulus: np.ndarray,
    lumen_pressure: np.ndarray,
) -> tuple[np.ndarray, np.ndarray]:
    """First Piola-Kirchhoff stress P (2,2,...) and tangent dP/dF (2,2,2,2,...) at quadrature points.

    displacement_gradient: (2, 2, n_elements, n_points). The material arrays broadcast against
    (n_elements, n_points); moduli and pressure in N/mm^2. Raises FloatingPointError when an
    element is inverted (J <= 0).
    """
    eye = np.eye(2)[:, :, None, None]
    F = eye + displacement_gradient
    J = F[0, 0] * F[1, 1] - F[0, 1] * F[1, 0]
    if not np.all(J > 0):
        raise FloatingPointError("inverted element (J <= 0)")
    FinvT = np.stack([np.stack([F[1, 1], -F[1, 0]]), np.stack([-F[0, 1], F[0, 0]])]) / J
    I1 = np.einsum("ij...,ij...->...", F, F) + 1.0
    J23 = J ** (-2.0 / 3.0)
    dI1bar = J23 * (2 * F - (2.0 / 3.0) * I1 * FinvT)
    x = J23 * I1 - 3.0
    psi1 = 0.5 * shear_modulus * (1.0 + 2.0 * yeoh_c2 * x + 3.0 * yeoh_c3 * x**2)  # dW/dI1bar
    dpsi1 = 0.5 * shear_modulus * (2.0 * yeoh_c2 + 6.0 * yeoh_c3 * x)
    volumetric = 0.5 * bulk_modulus * (J**2 - 1.0)
    P = psi1 * dI1bar + volumetric * FinvT - lumen_pressure * J * FinvT

    outer = np.einsum  # readability: the tangent is a sum of outer products
    FinvT_FinvT = outer("ij...,kl...->ijkl...", FinvT, FinvT)
    FinvT_cross = outer("il...,kj...->ijkl...", FinvT, FinvT)  # d(FinvT_ij)/dF_kl = -FinvT_il FinvT_kj
    delta = np.einsum("ik,jl->ijkl", np.eye(2), np.eye(2))[..., None, None]
    d_dI1bar = -(2.0 / 3.0) * outer("ij...,kl...->ijkl...", dI1bar, FinvT) + J23 * (
        2 * delta - (4.0 / 3.0) * outer("ij...,kl...->ijkl...", FinvT, F) + (2.0 / 3.0) * I1 * FinvT_cross
    )
    A = (
        dpsi1 * outer("ij...,kl...->ijkl...", dI1bar, dI1bar)
        + psi1 * d_dI1bar
        + bulk_modulus * J**2 * FinvT_FinvT
        - volumetric * FinvT_cross
        - lumen_pressure * J * (FinvT_FinvT - FinvT_cross)
    )
    return P, A


@LinearForm
def _internal_force_form(v, w):
    return np.einsum("ij...,ij...->...", w["stress"], grad(v))


@BilinearForm
def _tangent_form(u, v, w):
    return np.einsum("ijkl...,kl...,ij...->...", w["tangent"], grad(u), grad(v))


class _SectionProblem:
    """The discretised section: mesh, P2 basis, per-element materials and boundary DOFs."""

    def __init__(self, spec: SectionSpec):
        self.spec = spec
        self.mesh, self.in_lumen, material_index = section_mesh(spec)
        self.basis = Basis(self.mesh, ElementVector(ElementTriP2()), intorder=4)
        moduli = np.array([layer.shear_modulus_kpa for layer in spec.layers] + [spec.shear_modulus_kpa])
        c2 = np.array([layer.yeoh_c2 for layer in spec.layers] + [spec.yeoh_c2])
        c3 = np.array([layer.yeoh_c3 for layer in spec.layers] + [spec.yeoh_c3])
        shear = moduli[material_index] * np.where(self.in_lumen, spec.lumen_stiffness_ratio, 1.0)
        self.shear_modulus = (shear * _KPA_TO_N_PER_MM2)[:, None]
        self.yeoh_c2, self.yeoh_c3 = c2[material_index][:, None], c3[material_index][:, None]
        self.bulk_modulus = self.shear_modulus * spec.bulk_modulus_ratio
        self.lumen_pressure = (np.where(self.in_lumen, spec.lumen_pressure_kpa, 0.0) * _KPA_TO_N_PER_MM2)[:, None]
        self.pressure_fraction = 1.0  # share of the lumen pressure applied (ramped up at lambda = 0)

        tolerance = 1e-6 * spec.mesh_size_mm
        half_probe = PROBE_WIDTH_MM / 2
        bottom = self.basis.get_dofs(lambda x: x[1] > spec.depth_mm - tolerance)
        face = self.basis.get_dofs(lambda x: (x[1] < tolerance) & (np.abs(x[0]) < half_probe + tolerance))
        self.face_z_dofs = face.all("u^2")
        held_x = face.all("u^1") if spec.contact == "stick" else np.array([], dtype=np.int64)
        self.fixed_dofs = np.unique(np.concatenate([bottom.all(), self.face_z_dofs, held_x]))
        self.free_dofs = np.setdiff1d(np.arange(self.basis.N), self.fixed_dofs)

    def internal_force_and_tangent(self, u: np.ndarray, with_tangent: bool = True):
        """Internal nodal forces (N/mm, per mm out of plane) and, optionally, the tangent matrix."""
        displacement_gradient = self.basis.interpolate(u).grad
        stress, tangent = _first_piola_and_tangent(
            displacement_gradient,
            self.shear_modulus,
            self.yeoh_c2,
            self.yeoh_c3,
            self.bulk_modulus,
            self.pressure_fraction * self.lumen_pressure,
        )
        force = _internal_force_form.assemble(self.basis, stress=stress)
        if not with_tangent:
            return force, None
        return force, _tangent_form.assemble(self.basis, tangent=tangent).tocsr()

    def solve_step(self, u_guess: np.ndarray, probe_displacement: float) -> tuple[np.ndarray, int]:
        """Newton iterations at one lambda from ``u_guess``; returns (u, iterations).

        Raises FloatingPointError when the iterations invert an element, diverge or stall.
        """
        u = u_guess.copy()
        u[self.fixed_dofs] = 0.0
        u[self.face_z_dofs] = probe_displacement
        free = self.free_dofs
        for iteration in range(1, _MAX_NEWTON_ITERATIONS + 1):
            force, stiffness = self.internal_force_and_tangent(u)
            reaction_scale = np.abs(force[self.fixed_dofs]).max() + 1e-12
            step = scipy.sparse.linalg.spsolve(stiffness[free][:, free].tocsc(), -force[free])
            if not np.all(np.isfinite(step)):
                raise FloatingPointError("singular tangent")
            u[free] += step
            step_size = np.abs(step).max()
            if (
                step_size < 1e-9 * max(1.0, abs(probe_displacement))
                and np.abs(force[free]).max() < 1e-6 * reaction_scale
            ):
                return u, iteration
            if step_size > 1e3 * max(1.0, abs(probe_displacement)):
                raise FloatingPointError("Newton diverged")
        raise FloatingPointError(f"no convergence in {_MAX_NEWTON_ITERATIONS} iterations")

    def probe_force(self, u: np.ndarray) -> float:
        """Contact force (N, compression positive) of the solved state ``u``."""
        force, _ = self.internal_force_and_tangent(u, with_tangent=False)
        return float(force[self.face_z_dofs].sum() * self.spec.out_of_plane_width_mm)


def _continuation(
    solve,
    start: float,
    target: float,
    u_start: np.ndarray,
    what: str,
    before_start: tuple | None = None,
    first_increment: float | None = None,
) -> tuple[np.ndarray, int, tuple[np.ndarray, float]]:
    """Follow ``solve(guess, load) -> (u, iterations)`` from load ``start`` to ``target``.

    Tries the whole increment first, halves it when Newton fails and doubles it after an easy
    increment (at most 4 iterations); the predictor extrapolates
    the last converged increment linearly (``before_start``: the (u, load) converged before
    ``start``, if any; without it the first increment is at most ``first_increment``). Returns (u at target, iterations, the (u, load) converged before target,
    for the next call). Raises MechanicsConvergenceError naming ``what``.
    """
    u_previous, load_previous = before_start if before_start is not None else (u_start, start)
    u_current, load_current = u_start, start
    increment, halvings, iterations = target - start, 0, 0
    if before_start is None and first_increment is not None:
        increment = min(increment, first_increment)
    while load_current < target:
        load_next = min(load_current + increment, target)
        guess = u_current
        if load_current > load_previous:
            guess = u_current + (load_next - load_current) / (load_current - load_previous) * (u_current - u_previous)
        try:
            u_next, n_iterations = solve(guess, load_next)
        except FloatingPointError as failure:
            halvings += 1
            if halvings > _MAX_STEP_HALVINGS:
                raise MechanicsConvergenceError(
                    f"Newton failed at {what} (reached {load_current:.4g} of {target:.4g}, increment halved "
                    f"{halvings - 1} times): {failure}"
                ) from failure
            increment /= 2
            continue
        iterations += n_iterations
        if n_iterations <= 4:  # easy increment: try a larger one next
            increment *= 2
        u_previous, load_previous = u_current, load_current
        u_current, load_current = u_next, load_next
    return u_current, iterations, (u_previous, load_previous)


def _solve_uncached(spec: SectionSpec, probe_displacement_mm: np.ndarray) -> dict[str, np.ndarray]:
    problem = _SectionProblem(spec)
    n_steps = len(probe_displacement_mm)
    history = np.zeros((n_steps, problem.basis.N))
    forces = np.zeros(n_steps)
    iterations = np.zeros(n_steps, dtype=np.int64)

    def pressurised(guess, fraction):
        problem.pressure_fraction = fraction
        return problem.solve_step(guess, 0.0)

    # Step 0: lambda = 0, probe face held at z = 0, lumen pressure ramped up from zero.
    u, iterations[0], _ = _continuation(
        pressurised, 0.0, 1.0, history[0], f"load step 0 (lambda = 0 mm, lumen pressure {spec.lumen_pressure_kpa} kPa)"
    )
    history[0], forces[0] = u, problem.probe_force(u)
    before = None
    for index in range(1, n_steps):
        lam_start, lam_target = probe_displacement_mm[index - 1], probe_displacement_mm[index]
        what = f"load step {index} (lambda {lam_start:.4g} -> {lam_target:.4g} mm)"
        u, iterations[index], before = _continuation(
            problem.solve_step, lam_start, lam_target, u, what, before, _FIRST_INCREMENT_MM
        )
        history[index], forces[index] = u, problem.probe_force(u)
    return {
        "nodes": problem.mesh.p,
        "elements": problem.mesh.t,
        "in_lumen": problem.in_lumen,
        "displacement_dofs": history,
        "force_n": forces,
        "newton_iterations": iterations,
    }


# ----------------------------------------------------------------------------------------------
# Solutions: evaluation of the stored P2 displacement fields


def _barycentric(points: np.ndarray, corners: np.ndarray) -> np.ndarray:
    """Barycentric coordinates (m, 3) of ``points`` (m, 2) in triangles ``corners`` (m, 3, 2)."""
    e1, e2 = corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0]
    rel = points - corners[:, 0]
    det = e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0]
    l1 = (rel[:, 0] * e2[:, 1] - rel[:, 1] * e2[:, 0]) / det
    l2 = (e1[:, 0] * rel[:, 1] - e1[:, 1] * rel[:, 0]) / det
    return np.column_stack([1 - l1 - l2, l1, l2])


class _TriangleLocator:
    """Finds the triangle of a linear mesh that contains each query point."""

    _INSIDE_TOLERANCE = 1e-7

    def __init__(self, nodes: np.ndarray, elements: np.ndarray):
        self.nodes, self.elements = nodes, elements  # (n, 2), (n_elements, 3)
        self.tree = cKDTree(nodes[elements].mean(axis=1))

    def locate(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(element index or -1 when outside, barycentric coordinates (m, 3)) of each point."""
        found = np.full(len(points), -1)
        coordinates = np.zeros((len(points), 3))
        pending = np.arange(len(points))
        for n_candidates in (8, 48, 256):
            if len(pending) == 0:
                break
            n_candidates = min(n_candidates, len(self.elements))
            _, candidates = self.tree.query(points[pending], n_candidates)
            candidates = candidates.reshape(len(pending), n_candidates)
            bary = _barycentric(
                np.repeat(points[pending], n_candidates, axis=0), self.nodes[self.elements[candidates.ravel()]]
            ).reshape(len(pending), n_candidates, 3)
            best = bary.min(axis=2).argmax(axis=1)
            best_bary = bary[np.arange(len(pending)), best]
            inside = best_bary.min(axis=1) >= -self._INSIDE_TOLERANCE
            found[pending[inside]] = candidates[np.arange(len(pending)), best][inside]
            coordinates[pending[inside]] = np.clip(best_bary[inside], 0.0, 1.0)
            pending = pending[~inside]
        return found, coordinates


class _FieldHistory:
    """One finite-element solve: the reference mesh and the P2 displacement at every lambda step."""

    def __init__(self, nodes: np.ndarray, elements: np.ndarray, displacement_dofs: np.ndarray):
        mesh = MeshTri(nodes, elements)
        scalar_basis = Basis(mesh, ElementTriP2(), intorder=1)
        self.nodes = nodes.T.copy()  # (n_nodes, 2)
        self.elements = elements.T.copy()  # (n_elements, 3)
        self.element_dofs = scalar_basis.element_dofs.T.copy()  # (n_elements, 6) scalar P2 dofs
        # Barycentric position of each element dof (0, 1/2 or 1 per coordinate) selects its shape function.
        corners = self.nodes[self.elements]
        dof_points = scalar_basis.doflocs.T[self.element_dofs]  # (n_elements, 6, 2)
        self.dof_barycentric = (
            np.round(2 * _barycentric(dof_points.reshape(-1, 2), np.repeat(corners, 6, axis=0))).reshape(-1, 6, 3) / 2
        )
        # Vector dofs are interleaved (x, z) per scalar dof: (n_steps, n_scalar_dofs, 2).
        self.history = displacement_dofs.reshape(len(displacement_dofs), -1, 2)
        self.locator = _TriangleLocator(self.nodes, self.elements)

    def shape_values(self, elements: np.ndarray, bary: np.ndarray) -> np.ndarray:
        """P2 shape function values (m, 6) at barycentric coordinates ``bary`` (m, 3)."""
        nodes = self.dof_barycentric[elements]  # (m, 6, 3)
        lam = bary[:, None, :]
        factor = np.where(nodes == 1.0, lam * (2 * lam - 1), np.where(nodes == 0.5, 2 * lam, 1.0))
        return factor.prod(axis=2)

    def vertex_displacement(self, step_weights: dict[int, float]) -> np.ndarray:
        """Displacement (n_nodes, 2) of the mesh vertices (the first scalar dofs are the vertices)."""
        return sum(weight * self.history[step][: len(self.nodes)] for step, weight in step_weights.items())


def _check_points(points_mm: np.ndarray, name: str = "points_mm") -> np.ndarray:
    points = np.asarray(points_mm, dtype=float)
    if points.ndim != 2 or points.shape[1] != 2:
        raise InputError(f"{name} must have shape (m, 2) (x lateral, z depth; mm), got {points.shape}")
    if not np.all(np.isfinite(points)):
        raise InputError(f"{name} must be finite")
    return points


class MechanicsSolution:
    """Solved (or blended / scaled) displacement fields and contact forces of one section.

    ``probe_displacement_mm`` (n_steps,) starts at 0 and increases; ``force_n`` (n_steps,) is the
    contact force in N (compression positive). Displacements are evaluated at points of the
    reference (undeformed) section frame: x lateral mm (0 at the probe centre), z depth mm (0 at
    the undeformed surface, positive down); between solved steps they are linear in lambda.
    ``newton_iterations`` (n_steps,) counts the Newton iterations of each step of a direct solve
    (None for blends of several solves).
    """

    def __init__(
        self,
        spec: SectionSpec,
        probe_displacement_mm: np.ndarray,
        force_n: np.ndarray,
        fields: Sequence[tuple[_FieldHistory, float]],
        newton_iterations: np.ndarray | None = None,
    ):
        self.spec = spec
        self.probe_displacement_mm = np.array(probe_displacement_mm, dtype=float)
        self.force_n = np.array(force_n, dtype=float)
        self.probe_displacement_mm.setflags(write=False)
        self.force_n.setflags(write=False)
        self.newton_iterations = newton_iterations
        self._fields = tuple(fields)

    # -- derived solutions -----------------------------------------------------------------

    def scaled(self, factor: float) -> MechanicsSolution:
        """The solution of ``spec.scaled(factor)``: same displacements, ``factor`` times the force."""
        return MechanicsSolution(
            self.spec.scaled(factor),
            self.probe_displacement_mm,
            self.force_n * factor,
            self._fields,
            self.newton_iterations,
        )

    @staticmethod
    def blend(solutions: Sequence[MechanicsSolution], weights: Sequence[float], spec: SectionSpec) -> MechanicsSolution:
        """Weighted mean of solutions on the same lambda steps (fields and forces), labelled ``spec``.

        An approximation for a section whose vessel lies between those of the blended solutions.
        """
        weight_array = np.asarray(weights, dtype=float)
        if (
            len(solutions) != len(weight_array)
            or len(solutions) == 0
            or np.any(weight_array < 0)
            or not np.isclose(weight_array.sum(), 1)
        ):
            raise InputError("blend needs one non-negative weight per solution, summing to 1")
        steps = solutions[0].probe_displacement_mm
        if any(not np.array_equal(s.probe_displacement_mm, steps) for s in solutions):
            raise InputError("blended solutions must share their lambda steps")
        used = [(s, float(w)) for s, w in zip(solutions, weight_array) if w > 0]
        fields = [(field, w * fw) for s, w in used for field, fw in s._fields]
        force = np.sum([w * s.force_n for s, w in used], axis=0)
        return MechanicsSolution(spec, steps, force, fields, used[0][0].newton_iterations if len(used) == 1 else None)

    # -- lambda and force --------------------------------------------------------------------

    def _step_weights(self, probe_displacement_mm: float) -> dict[int, float]:
        lam = float(probe_displacement_mm)
        steps = self.probe_displacement_mm
        if not (np.isfinite(lam) and steps[0] <= lam <= steps[-1] * (1 + 1e-12)):
            raise InputError(f"probe displacement {lam} mm is outside the solved range [{steps[0]}, {steps[-1]}] mm")
        upper = int(np.clip(np.searchsorted(steps, lam, side="right"), 1, len(steps) - 1))
        fraction = min(1.0, (lam - steps[upper - 1]) / (steps[upper] - steps[upper - 1]))
        return {upper - 1: 1.0 - fraction, upper: fraction}

    def force_at(self, probe_displacement_mm):
        """Contact force (N) at probe displacement(s) lambda (mm), piecewise linear between steps."""
        lam = np.asarray(probe_displacement_mm, dtype=float)
        if np.any(~np.isfinite(lam)) or np.any(lam < 0) or np.any(lam > self.probe_displacement_mm[-1] * (1 + 1e-12)):
            raise InputError(f"probe displacement outside the solved range [0, {self.probe_displacement_mm[-1]}] mm")
        return np.interp(lam, self.probe_displacement_mm, self.force_n)

    def probe_displacement_at_force(self, force_n):
        """Probe displacement (mm) at contact force(s) (N): the inverse of :meth:`force_at`."""
        force = np.asarray(force_n, dtype=float)
        if np.any(np.diff(self.force_n) <= 0):
            raise InputError("the force is not strictly increasing in lambda, so it cannot be inverted")
        if np.any(~np.isfinite(force)) or np.any(force < self.force_n[0]) or np.any(force > self.force_n[-1]):
            raise InputError(f"force outside the solved range [{self.force_n[0]:.4g}, {self.force_n[-1]:.4g}] N")
        return np.interp(force, self.force_n, self.probe_displacement_mm)

    # -- fields --------------------------------------------------------------------------------

    def _evaluate(self, points: np.ndarray, step_weights: dict[int, float]) -> tuple[np.ndarray, np.ndarray]:
        """Displacement (m, 2; NaN outside) and the element of the first solve holding each point (-1 outside)."""
        result = np.zeros_like(points)
        first_elements = np.full(len(points), -1)
        for index, (field, field_weight) in enumerate(self._fields):
            elements, bary = field.locator.locate(points)
            inside = elements >= 0
            result[~inside] = np.nan
            if index == 0:
                first_elements = elements
            shape = field.shape_values(elements[inside], bary[inside])  # (m, 6)
            dofs = field.element_dofs[elements[inside]]  # (m, 6)
            for step, weight in step_weights.items():
                if weight:
                    result[inside] += field_weight * weight * np.einsum("mk,mkc->mc", shape, field.history[step][dofs])
        return result, first_elements

    def displacement(
        self, points_mm: np.ndarray, probe_displacement_mm: float, outside: Literal["raise", "nan"] = "raise"
    ) -> np.ndarray:
        """Displacement (m, 2) in mm of reference points (m, 2) at probe displacement lambda (mm).

        Points outside the section raise :class:`InputError` (``outside="raise"``) or get NaN.
        """
        points = _check_points(points_mm)
        result, _ = self._evaluate(points, self._step_weights(probe_displacement_mm))
        missing = np.isnan(result[:, 0])
        if outside == "raise" and np.any(missing):
            raise InputError(
                f"{missing.sum()} of {len(points)} points lie outside the section (x in [{-self.spec.width_mm / 2}, "
                f"{self.spec.width_mm / 2}], z in [0, {self.spec.depth_mm}] mm), first: {points[missing][0].tolist()}"
            )
        return result

    def deformed_position_inverse(
        self, points_mm: np.ndarray, probe_displacement_mm: float, outside: Literal["raise", "nan"] = "nan"
    ) -> np.ndarray:
        """Reference positions (m, 2), mm, of material points found at ``points_mm`` after pressing.

        Solves X + u(X) = x (to 1e-6 mm) by Newton's method from the deformed-mesh estimate, with
        the piecewise-linear deformation gradient of the mesh as Jacobian. Points outside the
        deformed section get NaN (default; e.g. image pixels above the tissue) or raise. For a
        blend, the estimate and the Jacobian come from the first blended solve (quasi-Newton).
        """
        points = _check_points(points_mm)
        step_weights = self._step_weights(probe_displacement_mm)
        field = self._fields[0][0]
        vertex_displacement = field.vertex_displacement(step_weights)
        deformed = _TriangleLocator(field.nodes + vertex_displacement, field.elements)
        deformed_elements, bary = deformed.locate(points)
        missing = deformed_elements < 0
        if np.any(missing) and outside == "raise":
            raise InputError(f"{missing.sum()} of {len(points)} points lie outside the deformed section")
        reference = np.full_like(points, np.nan)
        active = np.flatnonzero(~missing)
        reference[active] = np.einsum(
            "mk,mkc->mc", bary[active], field.nodes[field.elements[deformed_elements[active]]]
        )
        low, high = np.array([-self.spec.width_mm / 2, 0.0]), np.array([self.spec.width_mm / 2, self.spec.depth_mm])
        for _ in range(_MAX_INVERSE_ITERATIONS):
            displacement, elements = self._evaluate(reference[active], step_weights)
            residual = np.nan_to_num(points[active] - reference[active] - displacement)
            unconverged = np.abs(residual).max(axis=1) >= 1e-6
            active, residual, elements = active[unconverged], residual[unconverged], elements[unconverged]
            if len(active) == 0:
                break
            elements = np.where(elements < 0, deformed_elements[active], elements)
            ref_corners = field.nodes[field.elements[elements]]
            def_corners = ref_corners + vertex_displacement[field.elements[elements]]
            dX = np.stack([ref_corners[:, 1] - ref_corners[:, 0], ref_corners[:, 2] - ref_corners[:, 0]], axis=2)
            dx = np.stack([def_corners[:, 1] - def_corners[:, 0], def_corners[:, 2] - def_corners[:, 0]], axis=2)
            step = np.linalg.solve(dx @ np.linalg.inv(dX), residual[..., None])[..., 0]
            reference[active] = np.clip(reference[active] + step, low, high)
        return reference

    def lumen_boundary(self, probe_displacement_mm: float, n_points: int = 128) -> np.ndarray:
        """Deformed lumen wall (n_points, 2), mm: the reference circle of ``spec`` moved by the field."""
        if int(n_points) < 3:
            raise InputError(f"n_points must be at least 3, got {n_points}")
        angles = 2 * np.pi * np.arange(int(n_points)) / int(n_points)
        circle = np.column_stack(
            [
                self.spec.vessel_center_x_mm + self.spec.vessel_radius_mm * np.cos(angles),
                self.spec.vessel_depth_mm + self.spec.vessel_radius_mm * np.sin(angles),
            ]
        )
        return circle + self.displacement(circle, probe_displacement_mm)

    def lumen_area_mm2(self, probe_displacement_mm: float, n_points: int = 256) -> float:
        """Area (mm^2) enclosed by the deformed lumen wall."""
        x, z = self.lumen_boundary(probe_displacement_mm, n_points).T
        return float(0.5 * abs(np.dot(x, np.roll(z, -1)) - np.dot(z, np.roll(x, -1))))


# ----------------------------------------------------------------------------------------------
# Solving with an on-disk cache


def cache_dir() -> Path:
    """Directory of cached mechanics solutions: ``$USDEFORM_CACHE_DIR`` or ``~/.cache/usdeform``, ``/mechanics``."""
    root = os.environ.get("USDEFORM_CACHE_DIR") or Path.home() / ".cache" / "usdeform"
    return Path(root) / "mechanics"


def _check_probe_displacements(probe_displacement_mm: np.ndarray, spec: SectionSpec) -> np.ndarray:
    lam = np.asarray(probe_displacement_mm, dtype=float)
    if lam.ndim != 1 or len(lam) < 2:
        raise InputError(f"probe_displacement_mm must be 1-D with at least 2 steps, got shape {lam.shape}")
    if not np.all(np.isfinite(lam)) or lam[0] != 0.0 or np.any(np.diff(lam) <= 0):
        raise InputError("probe_displacement_mm must start at 0 and increase strictly (mm)")
    if lam[-1] > 0.4 * spec.depth_mm:
        raise InputError(f"probe displacement {lam[-1]} mm exceeds 40 % of the section depth {spec.depth_mm} mm")
    return lam


def _write_atomically(path: Path, arrays: dict[str, np.ndarray]) -> None:
    """Write ``arrays`` to ``path`` (.npz) through a temporary file and a rename, so readers never see a partial file."""
    path.parent.mkdir(parents=True, exist_ok=True)
    with tempfile.NamedTemporaryFile(dir=path.parent, prefix=path.stem, suffix=".tmp", delete=False) as handle:
        try:
            np.savez(handle, **arrays)  # type: ignore[arg-type]  # numpy's stub mistypes **kwds
        except BaseException:
            Path(handle.name).unlink(missing_ok=True)
            raise
    os.replace(handle.name, path)


_MAX_SOLUTIONS_IN_MEMORY = 32
_loaded_solutions: dict[tuple[Path, str], MechanicsSolution] = {}  # solutions loaded in this process


def solve_section(spec: SectionSpec, probe_displacement_mm: np.ndarray, *, use_cache: bool = True) -> MechanicsSolution:
    """Solve the section at the lambda steps ``probe_displacement_mm`` (mm, from 0, increasing).

    Results are cached on disk (see :func:`cache_dir`), keyed by a hash of every parameter, and
    the last few loaded solutions in memory (treat their arrays as read-only).
    Raises :class:`InputError` for bad steps, :class:`MechanicsConvergenceError` if Newton fails.
    """
    if not isinstance(spec, SectionSpec):
        raise InputError(f"spec must be a SectionSpec, got {type(spec).__name__}")
    lam = _check_probe_displacements(probe_displacement_mm, spec)
    key = spec.cache_key(lam)
    path = cache_dir() / f"{key}.npz"
    if use_cache and (path, key) in _loaded_solutions:
        return _loaded_solutions[(path, key)]
    arrays = None
    if use_cache and path.exists():
        try:
            with np.load(path) as stored:
                arrays = {name: stored[name] for name in stored.files}
        except (OSError, ValueError, KeyError):
            arrays = None  # unreadable cache entry: solve again and overwrite it
    if arrays is None:
        arrays = _solve_uncached(spec, lam)
        if use_cache:
            _write_atomically(path, arrays)
    field = _FieldHistory(arrays["nodes"], arrays["elements"], arrays["displacement_dofs"])
    solution = MechanicsSolution(spec, lam, arrays["force_n"], [(field, 1.0)], arrays["newton_iterations"])
    if use_cache:
        if len(_loaded_solutions) >= _MAX_SOLUTIONS_IN_MEMORY:
            _loaded_solutions.pop(next(iter(_loaded_solutions)))
        _loaded_solutions[(path, key)] = solution
    return solution
