"""Mechanics of the independent generator: a 2-D plane-strain total-Lagrangian Q4 Demiray model with a rigid probe
face in sticking contact (flat, tilted or arc-shaped), solved by Newton-Raphson in probe-travel steps (mm, N)."""

from __future__ import annotations

import hashlib
import json
import time
from dataclasses import asdict, dataclass
from pathlib import Path

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

    def key(self) -> str:
        """Cache key of the solve, hex."""
        text = json.dumps({**asdict(self), "version": GENERATOR_VERSION}, sort_keys=True)
        return hashlib.sha1(text.encode()).hexdigest()[:16]


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

    @classmethod
    def of(cls, phantom: Phantom) -> Face:
        return cls(
            phantom.probe_width_mm,
            float(np.radians(phantom.face_tilt_deg)),
            float(np.radians(phantom.travel_deg)),
            phantom.face_radius_mm,
        )

    def axes(self) -> tuple[np.ndarray, np.ndarray]:
        """(e_x, e_z) of the probe frame in the tissue frame."""
        c, s = np.cos(self.tilt_rad), np.sin(self.tilt_rad)
        return np.array([c, s]), np.array([-s, c])

    def centre(self, travel: float | np.ndarray) -> np.ndarray:
        """Face centre (the arc's apex), mm, (..., 2), after ``travel`` mm: at first contact the lowest edge (or the
        apex) touches the undeformed surface z = 0."""
        start = np.array([0.0, -0.5 * self.width_mm * abs(np.sin(self.tilt_rad))])
        return start + np.multiply.outer(travel, np.array([np.sin(self.travel_rad), np.cos(self.travel_rad)]))

    def height(self, xi: np.ndarray) -> np.ndarray:
        """Height of the face above its centre line (mm, towards the probe) at ``xi`` mm along it: the sagitta."""
        if not self.radius_mm:
            return np.zeros_like(xi)
        return self.radius_mm - np.sqrt(self.radius_mm**2 - np.minimum(xi**2, self.radius_mm**2))


@dataclass
class Solution:
    """FEM solution: node grid (x lateral, z depth, mm), lambda steps (mm), force (N), nodal displacements (mm)."""

    x_nodes: np.ndarray
    z_nodes: np.ndarray
    lambdas: np.ndarray
    forces: np.ndarray
    displacements: np.ndarray  # (steps, nz, nx, 2) (u_x, u_z), u_z positive downwards

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
    z = np.concatenate([_uniform(0.0, z_fine, h), _graded(z_fine, phantom.depth_mm, h, 4 * h)[1:]])
    return x, z


class _Model:
    """Assembly of the Q4 plane-strain Demiray model (units: mm, N/mm^2 = MPa, forces per mm of thickness)."""

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
        self.mu = np.where(lumen, mu * phantom.lumen_ratio, mu)
        self.b = np.where(lumen, 0.0, phantom.stiffening_b)
        lam_tissue = 2 * mu * nu / (1 - 2 * nu)
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
        """2nd Piola-Kirchhoff stress (m, 2, 2) and Voigt tangent (m, 3, 3) of the shear or volumetric part."""
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
        forces = np.bincount(self.edof.ravel(), (f1 + f2).ravel(), minlength=2 * self.n_nodes)
        matrix = sp.csr_matrix((((k1 + k2).ravel()), (self.rows, self.cols)), shape=(2 * self.n_nodes,) * 2)
        return forces, matrix


class _Contact:
    """Sticking contact of the surface nodes with the rigid face: a node touches when it would cross the face and
    from then on moves with it (its position on the face at touch-down plus the face's travel since)."""

    def __init__(self, model: _Model, face: Face):
        self.model, self.face = model, face
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
        return other

    def touch(self, u: np.ndarray, travel: float) -> bool:
        """Adds the free surface nodes on or beyond the face at ``travel`` mm (placed on it); True if any."""
        nodes = self.model.top
        position = self.reference + u.reshape(-1, 2)[nodes]
        relative = position - self.face.centre(travel)
        xi, eta = relative @ self.e_x, relative @ self.e_z
        gap = eta + self.face.height(xi)  # the face is at eta = -height
        new = ~self.active & (np.abs(xi) <= self.face.width_mm / 2 + 1e-9) & (gap < 1e-9)
        self.anchor[new] = u.reshape(-1, 2)[nodes[new]] - gap[new, None] * self.e_z
        self.since[new] = travel
        self.active |= new
        return bool(new.any())

    def prescribe(self, u: np.ndarray, travel: float) -> None:
        """Sets the contact nodes' displacements (in place) for the face at ``travel`` mm."""
        nodes = self.model.top[self.active]
        values = self.anchor[self.active] + (travel - self.since[self.active])[:, None] * self.direction
        u[2 * nodes], u[2 * nodes + 1] = values[:, 0], values[:, 1]

    def free(self) -> np.ndarray:
        nodes = self.model.top[self.active]
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


def solve_phantom(phantom: Phantom, cache: Path | None, verbose: bool = False) -> Solution:
    """Probe travel steps (lambda, mm, along the face's direction of travel) until the force along the probe axis
    (N) exceeds the cap or lambda its maximum; each step repeats its solve while new nodes touch the face. Cached as
    npz."""
    path = cache / f"{phantom.key()}.npz" if cache is not None else None
    if path is not None and path.exists():
        data = np.load(path)
        return Solution(data["x"], data["z"], data["lambdas"], data["forces"], data["displacements"])
    model = _Model(phantom)
    nz, nx = len(model.z), len(model.x)
    u = np.zeros(2 * model.n_nodes)
    contact = _Contact(model, Face.of(phantom))
    contact.touch(u, 0.0)
    previous = u.copy()
    lambdas, forces, fields = [0.0], [0.0], [u.reshape(nz, nx, 2).copy()]
    scale = phantom.shear_modulus_kpa * 1e-3 * phantom.probe_width_mm
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
            if not ok or not trial.touch(solved, target):
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
    solution = Solution(model.x, model.z, np.array(lambdas), np.array(forces), np.array(fields))
    if path is not None:
        path.parent.mkdir(parents=True, exist_ok=True)
        np.savez_compressed(
            path,
            x=solution.x_nodes,
            z=solution.z_nodes,
            lambdas=solution.lambdas,
            forces=solution.forces,
            displacements=solution.displacements,
        )
    return solution
