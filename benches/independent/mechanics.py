"""Mechanics of the independent generator: a 2-D plane-strain total-Lagrangian Q4 Demiray model with a rigid probe
face in sticking contact (flat, tilted or arc-shaped) or frictionless contact (flat and level), solved by
Newton-Raphson in probe-travel steps (mm, N). Tissue effects: a softer top layer (elementwise modulus), a
pressurised lumen (a fluid pressure in the soft inclusion, i.e. follower nodal forces on its boundary) and a stiff
circular inclusion (per Gauss point modulus)."""

from __future__ import annotations

import hashlib
import json
import time
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla

GENERATOR_VERSION = 2
"""Bumped when the recordings of a seed change: 2 added the kinds of effect and changed the case cycle."""


@dataclass(frozen=True)
class Phantom:
    """A tissue block with one vessel, mm, kPa; the force cap (N) ends the FEM load steps. The probe face (see
    :class:`Face`): tilt against the surface in the image plane (deg, positive: its right edge deeper), direction
    of travel from the surface normal (deg, positive: to the right), arc radius (mm, 0: flat)."""

    width_mm: float
    depth_mm: float
    probe_width_mm: float
    vessel_x_mm: float
    vessel_depth_mm: float
    vessel_radius_mm: float
    shear_modulus_kpa: float
    poisson_ratio: float
    stiffening_b: float
    lumen_ratio: float
    elevation_mm: float
    element_mm: float
    force_cap_n: float
    max_lambda_mm: float = 14.0
    face_tilt_deg: float = 0.0
    travel_deg: float = 0.0
    face_radius_mm: float = 0.0
    layer_depth_mm: float = 0.0
    layer_ratio: float = 1.0
    frictionless: bool = False
    lumen_pressure_kpa: float = 0.0
    inclusion_x_mm: float = 0.0
    inclusion_depth_mm: float = 0.0
    inclusion_radius_mm: float = 0.0
    inclusion_ratio: float = 1.0

    def key(self) -> str:
        """Cache key of the solve, hex; the tissue-effect fields (``_EFFECT_DEFAULTS``) enter only when set, so the
        keys of phantoms without them are those of the fields before they were added."""
        fields = {k: v for k, v in asdict(self).items() if _EFFECT_DEFAULTS.get(k, object()) != v}
        text = json.dumps({**fields, "version": GENERATOR_VERSION}, sort_keys=True)
        return hashlib.sha1(text.encode()).hexdigest()[:16]


_EFFECT_DEFAULTS: dict[str, object] = {
    "layer_depth_mm": 0.0,
    "layer_ratio": 1.0,
    "frictionless": False,
    "lumen_pressure_kpa": 0.0,
    "inclusion_x_mm": 0.0,
    "inclusion_depth_mm": 0.0,
    "inclusion_radius_mm": 0.0,
    "inclusion_ratio": 1.0,
}
"""Tissue-effect fields of :class:`Phantom` and their neutral values: ``layer_depth_mm`` (a top layer of
``layer_ratio`` times the shear modulus: an element whose centroid lies above this depth gets it; Lame's lambda
scales with it, the Poisson's ratio and stiffening are the tissue's), ``frictionless`` (the face constrains only the
normal displacement of the nodes it touches; flat level faces only), ``lumen_pressure_kpa`` (a uniform fluid
pressure in the lumen, see :class:`_Model`) and the ``inclusion_*`` fields (a disc of ``inclusion_radius_mm`` centred
at (``inclusion_x_mm``, ``inclusion_depth_mm``) with ``inclusion_ratio`` times the shear modulus: a Gauss point
inside it gets it; Lame's lambda scales with it, the Poisson's ratio and stiffening are the tissue's; the fine mesh
reaches 6 mm below it)."""


@dataclass(frozen=True)
class Face:
    """The rigid probe face in the tissue frame (x lateral, z depth downwards, mm): the probe frame's axes are
    e_x = (cos t, sin t) along the face and e_z = (-sin t, cos t) into the tissue; the face is the line (or the arc
    of ``radius_mm`` bulging towards the tissue) through its centre ``centre(s)``, which travels ``s`` mm along
    (sin a, cos a) from first contact."""

    width_mm: float
    tilt_rad: float = 0.0
    travel_rad: float = 0.0
    radius_mm: float = 0.0
    lift_mm: float = 0.0  # first contact this far above the undeformed surface (a surface bulged by lumen pressure)

    @classmethod
    def of(cls, phantom: Phantom, lift_mm: float = 0.0) -> Face:
        return cls(
            phantom.probe_width_mm,
            float(np.radians(phantom.face_tilt_deg)),
            float(np.radians(phantom.travel_deg)),
            phantom.face_radius_mm,
            lift_mm,
        )

    def axes(self) -> tuple[np.ndarray, np.ndarray]:
        """(e_x, e_z) of the probe frame in the tissue frame."""
        c, s = np.cos(self.tilt_rad), np.sin(self.tilt_rad)
        return np.array([c, s]), np.array([-s, c])

    def centre(self, travel: float | np.ndarray) -> np.ndarray:
        """Face centre (the arc's apex), mm, (..., 2), after ``travel`` mm: at first contact the lowest edge (or the
        apex) touches the undeformed surface z = 0 (z = -lift_mm: the top of a surface bulged before contact)."""
        start = np.array([0.0, -0.5 * self.width_mm * abs(np.sin(self.tilt_rad)) - self.lift_mm])
        return start + np.multiply.outer(travel, np.array([np.sin(self.travel_rad), np.cos(self.travel_rad)]))

    def height(self, xi: np.ndarray) -> np.ndarray:
        """Height of the face above its centre line (mm, towards the probe) at ``xi`` mm along it: the sagitta."""
        if not self.radius_mm:
            return np.zeros_like(xi)
        return self.radius_mm - np.sqrt(self.radius_mm**2 - np.minimum(xi**2, self.radius_mm**2))


@dataclass
class Solution:
    """FEM solution: node grid (x lateral, z depth, mm), lambda steps (mm), force (N), nodal displacements (mm);
    ``lift_mm``: the face's first contact above the undeformed surface (:attr:`Face.lift_mm`)."""

    x_nodes: np.ndarray
    z_nodes: np.ndarray
    lambdas: np.ndarray
    forces: np.ndarray
    displacements: np.ndarray  # (steps, nz, nx, 2) (u_x, u_z), u_z positive downwards
    lift_mm: float = 0.0

    def displacement_at(self, lam: float) -> np.ndarray:
        """(nz, nx, 2) nodal displacement at probe indentation ``lam`` (mm), linear between load steps."""
        lam = float(np.clip(lam, 0.0, self.lambdas[-1]))
        upper = int(np.clip(np.searchsorted(self.lambdas, lam), 1, len(self.lambdas) - 1))
        lo, hi = self.lambdas[upper - 1], self.lambdas[upper]
        weight = (lam - lo) / (hi - lo)
        return (1 - weight) * self.displacements[upper - 1] + weight * self.displacements[upper]

    def force_at(self, lam: np.ndarray) -> np.ndarray:
        """Elastic force F_e (N) at indentations ``lam`` (mm)."""
        return np.interp(lam, self.lambdas, self.forces)

    def lambda_at(self, force: np.ndarray) -> np.ndarray:
        """Indentation (mm) at elastic force ``force`` (N), inverting the monotone force curve."""
        return np.interp(force, self.forces, self.lambdas)


def _graded(start: float, stop: float, h0: float, h1: float, growth: float = 1.2) -> np.ndarray:
    """Coordinates from ``start`` to ``stop`` (mm), spacing growing geometrically from h0 towards h1."""
    length = abs(stop - start)
    steps: list[float] = []
    h = h0
    while sum(steps) < length - 1e-9:
        steps.append(h)
        h = min(h * growth, h1)
    if len(steps) > 1 and sum(steps) - length > 0.5 * steps[-1]:
        steps.pop()
    offsets = np.concatenate([[0.0], np.cumsum(steps)]) * length / sum(steps)
    return start + np.sign(stop - start) * offsets


def _uniform(start: float, stop: float, h: float) -> np.ndarray:
    return np.linspace(start, stop, max(1, round(abs(stop - start) / h)) + 1)


def _mesh_axes(phantom: Phantom) -> tuple[np.ndarray, np.ndarray]:
    """Node coordinates along x (lateral) and z (depth), mm: fine under the probe and around the vessel."""
    h = phantom.element_mm
    half_probe = phantom.probe_width_mm / 2
    fine = half_probe + 10.0
    outer = _graded(fine, phantom.width_mm / 2, h, 4 * h)
    right = np.concatenate([_uniform(0.0, half_probe, h), _uniform(half_probe, fine, h)[1:], outer[1:]])
    x = np.concatenate([-right[:0:-1], right])
    z_fine = min(phantom.vessel_depth_mm + phantom.vessel_radius_mm + 12.0, phantom.depth_mm - 10.0)
    if phantom.inclusion_radius_mm > 0:  # a stiff inclusion: the fine mesh covers it
        bottom = phantom.inclusion_depth_mm + phantom.inclusion_radius_mm + 6.0
        z_fine = min(max(z_fine, bottom), phantom.depth_mm - 10.0)
    z = np.concatenate([_uniform(0.0, z_fine, h), _graded(z_fine, phantom.depth_mm, h, 4 * h)[1:]])
    return x, z


class _Model:
    """Assembly of the Q4 plane-strain Demiray model (units: mm, N/mm^2 = MPa, forces per mm of thickness).

    The lumen is a soft inclusion (per Gauss point), not a hole. A lumen pressure p is the stress of a fluid filling
    it, Cauchy -p I, i.e. 2nd Piola-Kirchhoff S = -p J C^-1 at its Gauss points (energy -p times the lumen's
    current area): by the divergence theorem its nodal forces cancel inside the lumen and are those of the pressure
    on the (Gauss-point) inclusion boundary, normal to the *deformed* boundary and on its deformed length: a
    follower load, conservative (a closed lumen), with a symmetric tangent. ``pressure_factor`` scales it (the
    inflation before contact is ramped)."""

    def __init__(self, phantom: Phantom):
        self.x, self.z = _mesh_axes(phantom)
        nx, nz = len(self.x), len(self.z)
        self.n_nodes = nx * nz
        iz, ix = np.meshgrid(np.arange(nz - 1), np.arange(nx - 1), indexing="ij")
        base = (iz * nx + ix).ravel()
        self.conn = np.stack([base, base + 1, base + nx + 1, base + nx], axis=1)  # (ne, 4)
        hx = np.diff(self.x)[ix.ravel()]
        hz = np.diff(self.z)[iz.ravel()]
        xi_nodes = np.array([[-1.0, -1.0], [1.0, -1.0], [1.0, 1.0], [-1.0, 1.0]])
        gauss = np.array([[-1.0, -1.0], [1.0, -1.0], [1.0, 1.0], [-1.0, 1.0]]) / np.sqrt(3.0)

        def gradients(points: np.ndarray) -> np.ndarray:  # (ne, g, 4, 2) dN/dx, dN/dz
            d_xi = 0.25 * xi_nodes[None, :, 0] * (1 + xi_nodes[None, :, 1] * points[:, None, 1])
            d_eta = 0.25 * xi_nodes[None, :, 1] * (1 + xi_nodes[None, :, 0] * points[:, None, 0])
            return np.stack([d_xi[None] * (2 / hx)[:, None, None], d_eta[None] * (2 / hz)[:, None, None]], axis=-1)

        self.dn = gradients(gauss)
        self.weight = np.repeat((hx * hz / 4)[:, None], 4, axis=1)
        self.dn0 = gradients(np.zeros((1, 2)))[:, 0]
        self.area = hx * hz
        x0, z0 = self.x[ix.ravel()], self.z[iz.ravel()]
        gx = x0[:, None] + (1 + gauss[None, :, 0]) * hx[:, None] / 2
        gz = z0[:, None] + (1 + gauss[None, :, 1]) * hz[:, None] / 2
        lumen = (gx - phantom.vessel_x_mm) ** 2 + (gz - phantom.vessel_depth_mm) ** 2 < phantom.vessel_radius_mm**2
        mu = phantom.shear_modulus_kpa * 1e-3
        nu = phantom.poisson_ratio
        mu_tissue: float | np.ndarray = mu
        if phantom.layer_depth_mm > 0:  # elementwise: centroid above the layer depth; lambda scales (same nu)
            layer = (z0 + hz / 2 < phantom.layer_depth_mm)[:, None]
            mu_tissue = np.where(layer, mu * phantom.layer_ratio, mu)
        if phantom.inclusion_radius_mm > 0:  # per Gauss point, as the lumen; lambda scales (same nu)
            inside = (gx - phantom.inclusion_x_mm) ** 2 + (gz - phantom.inclusion_depth_mm) ** 2
            inclusion = inside < phantom.inclusion_radius_mm**2
            mu_tissue = np.where(inclusion, mu_tissue * phantom.inclusion_ratio, mu_tissue)
        self.mu = np.where(lumen, mu * phantom.lumen_ratio, mu_tissue)
        self.b = np.where(lumen, 0.0, phantom.stiffening_b)
        lam_tissue = 2 * mu_tissue * nu / (1 - 2 * nu)
        self.lumen = lumen
        self.pressure = np.where(lumen, phantom.lumen_pressure_kpa * 1e-3, 0.0)  # MPa at the Gauss points
        self.pressure_factor = 1.0
        lam_lumen = 2 * mu * phantom.lumen_ratio * 0.3 / (1 - 2 * 0.3)
        self.lam0 = np.where(lumen, lam_lumen, lam_tissue).mean(axis=1)
        edof = np.stack([2 * self.conn, 2 * self.conn + 1], axis=2).reshape(-1, 8)
        self.rows = np.repeat(edof[:, :, None], 8, axis=2).ravel()
        self.cols = np.repeat(edof[:, None, :], 8, axis=1).ravel()
        self.edof = edof
        zz, xx = np.meshgrid(self.z, self.x, indexing="ij")
        self.top = np.flatnonzero(zz.ravel() == 0.0)
        bottom = np.flatnonzero(zz.ravel() == self.z[-1])
        pin = bottom[np.argmin(np.abs(xx.ravel()[bottom]))]
        self.base = np.concatenate([2 * bottom + 1, [2 * pin]])  # roller base, one node pinned laterally

    @staticmethod
    def _material(
        f: np.ndarray, mu: np.ndarray, b: np.ndarray, lam: np.ndarray, part: str
    ) -> tuple[np.ndarray, np.ndarray]:
        """2nd Piola-Kirchhoff stress (m, 2, 2) and Voigt tangent (m, 3, 3) of the shear or volumetric part, or of
        the lumen's fluid pressure (``mu`` carries p): S = -p J C^-1, tangent -p J C^-1 x C^-1 + p J (sym)."""
        c = np.einsum("mki,mkj->mij", f, f)
        det_c = c[:, 0, 0] * c[:, 1, 1] - c[:, 0, 1] * c[:, 1, 0]
        ci = np.empty_like(c)
        ci[:, 0, 0], ci[:, 1, 1] = c[:, 1, 1] / det_c, c[:, 0, 0] / det_c
        ci[:, 0, 1] = ci[:, 1, 0] = -c[:, 0, 1] / det_c
        pairs = ((0, 0), (1, 1), (0, 1))
        civ = np.stack([ci[:, i, j] for i, j in pairs], axis=1)
        sym = np.empty((len(f), 3, 3))
        for a, (i, j) in enumerate(pairs):
            for bb, (k, m) in enumerate(pairs):
                sym[:, a, bb] = ci[:, i, k] * ci[:, j, m] + ci[:, i, m] * ci[:, j, k]
        if part == "shear":
            q = c[:, 0, 0] + c[:, 1, 1] - 2.0 - np.log(det_c)
            coef = 0.5 * mu * np.exp(np.minimum(b * q, 50.0))
            a_v = np.array([1.0, 1.0, 0.0])[None] - civ
            s_v = 2 * coef[:, None] * a_v
            d = 4 * (coef * b)[:, None, None] * a_v[:, :, None] * a_v[:, None, :] + 2 * coef[:, None, None] * sym
        elif part == "pressure":
            pj = mu * np.sqrt(det_c)
            s_v = -pj[:, None] * civ
            d = -pj[:, None, None] * civ[:, :, None] * civ[:, None, :] + pj[:, None, None] * sym
        else:
            ln_j = 0.5 * np.log(det_c)
            s_v = (lam * ln_j)[:, None] * civ
            d = lam[:, None, None] * civ[:, :, None] * civ[:, None, :] - (lam * ln_j)[:, None, None] * sym
        s = np.empty_like(c)
        s[:, 0, 0], s[:, 1, 1] = s_v[:, 0], s_v[:, 1]
        s[:, 0, 1] = s[:, 1, 0] = s_v[:, 2]
        return s, d

    def _part(
        self, ue: np.ndarray, dn: np.ndarray, w: np.ndarray, mu: np.ndarray, b: np.ndarray, lam: np.ndarray, part: str
    ) -> tuple[np.ndarray, np.ndarray, float]:
        """Element forces (ne, 8), stiffness (ne, 8, 8) and the smallest J of one quadrature part."""
        ne, g = dn.shape[:2]
        f = np.eye(2)[None, None] + np.einsum("eni,egnj->egij", ue, dn)
        jac = f[..., 0, 0] * f[..., 1, 1] - f[..., 0, 1] * f[..., 1, 0]
        min_j = float(jac.min())
        if min_j <= 0:
            return np.zeros((ne, 8)), np.zeros((ne, 8, 8)), min_j
        s, d = self._material(f.reshape(-1, 2, 2), mu.ravel(), b.ravel(), lam.ravel(), part)
        s, d = s.reshape(ne, g, 2, 2), d.reshape(ne, g, 3, 3)
        bm = np.zeros((ne, g, 3, 8))
        for k in range(2):
            bm[:, :, 0, k::2] = f[:, :, k, 0, None] * dn[..., 0]
            bm[:, :, 1, k::2] = f[:, :, k, 1, None] * dn[..., 1]
            bm[:, :, 2, k::2] = f[:, :, k, 0, None] * dn[..., 1] + f[:, :, k, 1, None] * dn[..., 0]
        s_v = np.stack([s[..., 0, 0], s[..., 1, 1], s[..., 0, 1]], axis=-1)
        forces = np.einsum("eg,egab,ega->eb", w, bm, s_v)
        stiffness = np.einsum("eg,egca,egcd,egdb->eab", w, bm, d, bm)
        geometric = np.einsum("eg,egai,egij,egbj->eab", w, dn, s, dn)
        stiffness[:, 0::2, 0::2] += geometric
        stiffness[:, 1::2, 1::2] += geometric
        return forces, stiffness, min_j

    def assemble(self, u: np.ndarray) -> tuple[np.ndarray, sp.csr_matrix | None]:
        """Internal force vector (2 n_nodes,) and tangent (None if an element inverted) at displacement u."""
        ue = u.reshape(-1, 2)[self.conn]
        f1, k1, j1 = self._part(ue, self.dn, self.weight, self.mu, self.b, np.zeros_like(self.mu), "shear")
        zeros = np.zeros((len(self.area), 1))
        f2, k2, j2 = self._part(
            ue, self.dn0[:, None], self.area[:, None], zeros, zeros, self.lam0[:, None], "volumetric"
        )
        if min(j1, j2) <= 0:
            return np.full(2 * self.n_nodes, np.nan), None
        element_forces, element_stiffness = f1 + f2, k1 + k2
        if self.pressure_factor and self.pressure.any():  # the lumen's fluid pressure (absent: sums unchanged)
            zeros4 = np.zeros_like(self.mu)
            p = self.pressure_factor * self.pressure
            f3, k3, _ = self._part(ue, self.dn, self.weight, p, zeros4, zeros4, "pressure")
            element_forces, element_stiffness = element_forces + f3, element_stiffness + k3
        forces = np.bincount(self.edof.ravel(), element_forces.ravel(), minlength=2 * self.n_nodes)
        matrix = sp.csr_matrix(((element_stiffness.ravel()), (self.rows, self.cols)), shape=(2 * self.n_nodes,) * 2)
        return forces, matrix

    def lumen_area(self, u: np.ndarray) -> float:
        """Current area (mm^2) of the lumen's Gauss points at displacement ``u`` (sum of w J)."""
        ue = u.reshape(-1, 2)[self.conn]
        f = np.eye(2)[None, None] + np.einsum("eni,egnj->egij", ue, self.dn)
        jac = f[..., 0, 0] * f[..., 1, 1] - f[..., 0, 1] * f[..., 1, 0]
        return float((self.weight * jac)[self.lumen].sum())


class _Contact:
    """Sticking contact of the surface nodes with the rigid face: a node touches when it would cross the face and
    from then on moves with it (its position on the face at touch-down plus the face's travel since).

    ``sliding``: frictionless contact (flat level faces only, whose normal is z): a touching node's depth follows
    the face, its lateral displacement is free; a node that slides past the face's edge is caught at the edge's
    corner and held there (both components: the corner's reaction may point any way in its normal cone). Releasing
    it instead chatters: freed, it slides back under the face and touches again.

    ``walls``: the probe's side walls (flat level faces; used in sliding contact, where the nodes under the face
    slide inwards, and under a surface bulged by lumen pressure, where the contact spreads from the bulge's top:
    there the tissue beside a face edge stands above the face and is drawn inwards): a free node that
    enters the face's extent from outside while above the face is held laterally at the wall (x of the edge, depth
    free; frictionless) instead of being projected onto the face, which would move it by up to the height it stands
    above the face and invert an element. The other kinds' faces have no walls (their contact is unchanged)."""

    def __init__(self, model: _Model, face: Face, sliding: bool = False, walls: bool = False):
        if (sliding or walls) and (face.tilt_rad or face.radius_mm):
            raise ValueError("frictionless contact and side walls are implemented for flat level faces only")
        self.model, self.face, self.sliding, self.walls = model, face, sliding, walls
        self.cornered = np.zeros(len(model.top), dtype=bool)  # sliding: held at the corner on side ``self.side``
        self.side = np.zeros(len(model.top))
        self.walled = np.zeros(len(model.top), dtype=bool)  # walls: held at the wall on side ``self.side``
        self.last_xi = np.full(len(model.top), np.nan)  # walls: xi at the last check (the last accepted state)
        self.reference = np.column_stack([model.x[model.top % len(model.x)], np.zeros(len(model.top))])
        self.active = np.zeros(len(model.top), dtype=bool)
        self.anchor = np.zeros((len(model.top), 2))  # displacement at touch-down, mm
        self.since = np.zeros(len(model.top))  # travel at touch-down, mm
        self.e_x, self.e_z = face.axes()
        self.direction = np.array([np.sin(face.travel_rad), np.cos(face.travel_rad)])

    def copy(self) -> _Contact:
        other = _Contact.__new__(_Contact)
        other.__dict__.update(self.__dict__)
        other.active, other.anchor, other.since = self.active.copy(), self.anchor.copy(), self.since.copy()
        other.cornered, other.side = self.cornered.copy(), self.side.copy()
        other.walled, other.last_xi = self.walled.copy(), self.last_xi.copy()
        return other

    def touch(self, u: np.ndarray, travel: float) -> bool:
        """Adds the free surface nodes on or beyond the face at ``travel`` mm (placed on it); True if any."""
        nodes = self.model.top
        position = self.reference + u.reshape(-1, 2)[nodes]
        relative = position - self.face.centre(travel)
        xi, eta = relative @ self.e_x, relative @ self.e_z
        gap = eta + self.face.height(xi)  # the face is at eta = -height
        new = ~self.active & (np.abs(xi) <= self.face.width_mm / 2 + 1e-9) & (gap < 1e-9)
        walled = np.zeros_like(new)
        if self.walls:  # entered from beside the face: against the side wall, not onto the face
            new &= ~self.walled
            walled = new & (np.abs(self.last_xi) > self.face.width_mm / 2 + 1e-9)
            self.walled |= walled
            self.side[walled] = np.sign(self.last_xi[walled])
            new &= ~walled
            self.last_xi = xi
        self.anchor[new] = u.reshape(-1, 2)[nodes[new]] - gap[new, None] * self.e_z
        self.since[new] = travel
        self.active |= new
        return bool(new.any() or walled.any())

    def prescribe(self, u: np.ndarray, travel: float) -> None:
        """Sets the contact nodes' displacements (in place) for the face at ``travel`` mm."""
        nodes = self.model.top[self.active]
        values = self.anchor[self.active] + (travel - self.since[self.active])[:, None] * self.direction
        if self.sliding:  # the normal (depth) only, and the lateral position of nodes held at a corner
            u[2 * nodes + 1] = values[:, 1]
            held = self.active & self.cornered
            corner = self.face.centre(travel)[0] + self.side[held] * self.face.width_mm / 2
            u[2 * self.model.top[held]] = corner - self.reference[held, 0]
        else:
            u[2 * nodes], u[2 * nodes + 1] = values[:, 0], values[:, 1]
        if self.walls:
            wall = self.face.centre(travel)[0] + self.side[self.walled] * self.face.width_mm / 2
            u[2 * self.model.top[self.walled]] = wall - self.reference[self.walled, 0]

    def catch(self, u: np.ndarray, travel: float) -> bool:
        """Sliding contact: the touching nodes that slid past the face's edge are held at its corner from now on;
        True if any."""
        if not self.sliding:
            return False
        position = self.reference + u.reshape(-1, 2)[self.model.top]
        xi = (position - self.face.centre(travel)) @ self.e_x
        new = self.active & ~self.cornered & (np.abs(xi) > self.face.width_mm / 2 + 1e-9)
        self.cornered |= new
        self.side[new] = np.sign(xi[new])
        return bool(new.any())

    def free(self) -> np.ndarray:
        nodes = self.model.top[self.active]
        if self.sliding or self.walls:
            lateral = nodes[~self.cornered[self.active]] if self.sliding else np.zeros(0, dtype=int)
            fixed = np.concatenate([2 * nodes, 2 * nodes + 1, self.model.base])
            fixed = np.setdiff1d(fixed, 2 * lateral)  # sliding: free laterally unless held at a corner
            fixed = np.concatenate([fixed, 2 * self.model.top[self.walled]])
        else:
            fixed = np.concatenate([2 * nodes, 2 * nodes + 1, self.model.base])
        return np.setdiff1d(np.arange(2 * self.model.n_nodes), fixed)

    def force(self, internal: np.ndarray) -> float:
        """Reaction on the face along the probe axis e_z, per mm of thickness."""
        nodes = self.model.top[self.active]
        return float((internal[2 * nodes] * self.e_z[0] + internal[2 * nodes + 1] * self.e_z[1]).sum())


def _newton(model: _Model, u: np.ndarray, free: np.ndarray, scale: float) -> tuple[np.ndarray, bool]:
    """Equilibrium from the start ``u`` (boundary values set), mm; returns (u, converged)."""
    forces, matrix = model.assemble(u)
    if matrix is None:
        return u, False
    for _ in range(25):
        residual = forces[free]
        norm = float(np.linalg.norm(residual))
        if norm < 1e-7 * scale:
            return u, True
        reduced = matrix[free][:, free]
        step = spla.spsolve(reduced.tocsc(), -residual)
        alpha = 1.0
        for _ls in range(8):
            trial = u.copy()
            trial[free] += alpha * step
            trial_forces, trial_matrix = model.assemble(trial)
            if trial_matrix is not None and np.linalg.norm(trial_forces[free]) < max(norm, 1e-6 * scale):
                break
            alpha *= 0.5
        else:
            return u, False
        u, forces, matrix = trial, trial_forces, trial_matrix
    return u, False


def _inflate(model: _Model, scale: float) -> np.ndarray:
    """Equilibrium under the lumen pressure alone (free surface, roller base), the pressure ramped in adaptive
    steps; mm."""
    u = np.zeros(2 * model.n_nodes)
    free = np.setdiff1d(np.arange(2 * model.n_nodes), model.base)
    level, step = 0.0, 0.25
    while level < 1.0 - 1e-12:
        step = min(step, 1.0 - level)
        model.pressure_factor = level + step
        solved, ok = _newton(model, u.copy(), free, scale)
        if ok:
            u, level, step = solved, level + step, step * 1.5
            continue
        step /= 2
        if step < 1e-3:
            model.pressure_factor = 1.0
            raise RuntimeError("the lumen pressure's inflation did not converge")
    model.pressure_factor = 1.0
    return u


def solve_phantom(
    phantom: Phantom, cache: Path | None, verbose: bool = False, model: _Model | None = None, key: str | None = None
) -> Solution:
    """Probe travel steps (lambda, mm, along the face's direction of travel) until the force along the probe axis
    (N) exceeds the cap or lambda its maximum; each step repeats its solve while new nodes touch the face (or, in
    sliding contact, reach its edge, or meet its side walls). A lumen pressure is applied first (before contact):
    the face then first touches the bulged surface's top, ``Solution.lift_mm`` above z = 0 (flat level faces only),
    and lambda 0 is the inflated state. Cached as npz. ``model``: an assembled model of the phantom's mesh whose
    materials or fixed nodes were changed (``clinical.section_model``), cached under ``key``."""
    path = cache / f"{key or phantom.key()}.npz" if cache is not None else None
    if path is not None and path.exists():
        data = np.load(path)
        lift = float(data["lift_mm"]) if "lift_mm" in data.files else 0.0
        return Solution(data["x"], data["z"], data["lambdas"], data["forces"], data["displacements"], lift)
    model = _Model(phantom) if model is None else model
    nz, nx = len(model.z), len(model.x)
    u = np.zeros(2 * model.n_nodes)
    scale = phantom.shear_modulus_kpa * 1e-3 * phantom.probe_width_mm
    lift = 0.0
    if phantom.lumen_pressure_kpa:
        if phantom.face_tilt_deg or phantom.face_radius_mm:
            raise ValueError("a lumen pressure is implemented under flat level faces only")
        u = _inflate(model, scale)
        under = np.abs(model.x[model.top % nx]) <= phantom.probe_width_mm / 2 + 1e-9
        lift = max(0.0, -float(u[2 * model.top[under] + 1].min()))
    contact = _Contact(
        model,
        Face.of(phantom, lift),
        phantom.frictionless,
        walls=bool(phantom.lumen_pressure_kpa or phantom.frictionless),
    )
    contact.touch(u, 0.0)
    previous = u.copy()
    lambdas, forces, fields = [0.0], [0.0], [u.reshape(nz, nx, 2).copy()]
    lam, step = 0.0, 0.6
    start = time.perf_counter()
    while lam < phantom.max_lambda_mm - 1e-9 and forces[-1] < phantom.force_cap_n:
        step = min(step, phantom.max_lambda_mm - lam)
        target = lam + step
        guess = u + (u - previous) * (step / max(lambdas[-1] - lambdas[-2], 1e-9) if len(lambdas) > 1 else 0.0)
        trial = contact.copy()
        for _ in range(20):
            guess[model.base] = 0.0
            trial.prescribe(guess, target)
            solved, ok = _newton(model, guess, trial.free(), scale)
            if not ok:
                break
            touched = trial.touch(solved, target)
            caught = trial.catch(solved, target)  # sliding contact only
            if not (touched or caught):
                break
            guess = solved
        else:
            ok = False
        if not ok:
            step /= 2
            if step < 0.05:
                break
            continue
        previous, u, lam, contact = u, solved, target, trial
        internal, _ = model.assemble(u)
        lambdas.append(lam)
        forces.append(contact.force(internal) * phantom.elevation_mm)
        fields.append(u.reshape(nz, nx, 2).copy())
        step = min(step * 1.5, 0.8)
        if verbose:
            print(f"  lambda {lam:6.2f} mm  force {forces[-1]:6.2f} N  ({time.perf_counter() - start:.1f} s)")
    solution = Solution(model.x, model.z, np.array(lambdas), np.array(forces), np.array(fields), lift)
    if path is not None:
        path.parent.mkdir(parents=True, exist_ok=True)
        arrays: dict[str, Any] = {
            "x": solution.x_nodes,
            "z": solution.z_nodes,
            "lambdas": solution.lambdas,
            "forces": solution.forces,
            "displacements": solution.displacements,
        }
        if phantom.lumen_pressure_kpa:
            arrays["lift_mm"] = np.array(lift)
        np.savez_compressed(path, **arrays)
    return solution
