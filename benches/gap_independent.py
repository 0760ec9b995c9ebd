"""The gap diagnosis on palpations from an independent generator (its own FEM engine and B-mode model).

``usdeform.gap.benchmark`` draws its "real" cases from ``usdeform.sim``, the simulator the diagnosis itself
calibrates (scikit-fem P2 Yeoh sections, bonded base, point-scatterer IQ splat). This script writes palpation
recordings with mechanics and imaging written apart from it, diagnoses each from its PLUS sequence file alone
(``usdeform.gap.diagnose``) and scores the verdicts. Nothing from ``usdeform.sim`` or ``usdeform.gap`` is used
except ``diagnose``; the files are written with ``usdeform.recording`` and ``usdeform.io``.

Mechanics (:func:`solve_phantom`): a 2-D plane-strain total-Lagrangian finite-element model in NumPy/SciPy on
a structured, graded mesh of bilinear quadrilaterals (Q4; ~1-1.3 mm under the probe, coarser towards the
sides and the base). Material: a compressible Demiray (exponential, Fung-like) law
``W = mu / (2 b) (exp(b (I1 - 3 - 2 ln J)) - 1) + lambda / 2 (ln J)^2`` (strain stiffening b 0.3-3, initial
shear modulus mu 10-40 kPa, Poisson's ratio 0.45-0.49), the shear part integrated at 2x2 Gauss points and the
volumetric part at the element centre (selective reduced integration against locking). The vessel is a
circular, very soft (0.005-0.05 of mu) and compressible (nu 0.3) neo-Hookean inclusion assigned per Gauss
point. Boundary conditions: the probe face (37.5-48 mm) is a rigid flat punch whose nodes are bonded (lateral
fixed, vertical prescribed); the rest of the surface is free; the base is a roller (vertical fixed, one node
pinned laterally), where usdeform.sim bonds it. Newton-Raphson with line search in adaptive probe steps up
to a force cap. The force is the plane-strain reaction (N/mm) times an effective elevation width (20-30 mm,
more than the array's ~10 mm to stand for the 3-D spread of the load; gives 1-4 N/mm near 5 mm).

Imaging (:class:`Scanner`, :class:`Texture`): a reflectivity texture on a fine grid (0.05 mm lateral,
0.025 mm axial) in the *undeformed* tissue: Gaussian amplitudes with a smooth density variation, sparse bright
points, an anechoic lumen, a brighter ~1 mm wall ring and up to two bright fibres. For a frame, each sample of
a fine image grid (probe frame; depth 0 is the probe face, i.e. the tissue surface pressed down by lambda) is
mapped back to its reference position by a fixed-point inversion of the FEM displacement, jittered by a smooth
random field (0.01-0.02 mm rms, new for every frame), the texture is sampled there (``cv2.remap``), convolved
with an RF pulse (axially a Gaussian-windowed cosine at 5-7.5 MHz, c = 1540 m/s; laterally a Gaussian),
attenuated, given band-limited electronic noise, time-gain compensated, envelope-detected (Hilbert transform
along depth), log-compressed and area-resampled to the pixels. usdeform.sim instead splats point scatterers
with a Gaussian IQ PSF.

Timeline: force-controlled palpation from contact (0.2-0.5 N) up at 3-6 N/s to 8-20 N, hold 1.5-3 s, down;
lambda(t) by inverting the FEM force curve on a 1 kHz clock, with robot position ripple (0.01-0.05 mm) and
force-sensor noise (0.02-0.06 N); 20-30 fps (at most 120 frames kept), millisecond timestamp jitter.

Hidden effects (own implementations): ``null``; ``image_latency`` (frames show the tissue at t - delay);
``force_sensor_error`` (bias + drift on the logged force); ``viscoelasticity`` (a standard linear solid under
force control: F = F_e(lambda) + q, dq/dt = -q / tau + g dF_e/dt, so lambda creeps during the hold). Cases
cycle through null, image_latency, null, force_sensor_error, null, viscoelasticity.

    python benches/gap_independent.py --cases 12 --seed 1 --out gap-independent
    python benches/gap_independent.py --cases 2 --quick --no-diagnose --png   # generator check only

Seeds: ``SeedSequence(seed)`` spawns a generation and a diagnosis stream; case i takes child i of each, so the
same seed gives the same recordings whatever ``--cases``. FEM solves are cached in DIR/fem_cache. Rows already
in DIR/cases.jsonl (same seed and mode) are kept and their cases skipped unless ``--fresh``.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import sys
import time
from dataclasses import asdict, dataclass
from pathlib import Path

import cv2
import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla
from scipy.interpolate import RegularGridInterpolator
from scipy.ndimage import gaussian_filter, gaussian_filter1d
from scipy.signal import hilbert

from usdeform.gap import diagnose
from usdeform.io import write_sequence
from usdeform.recording import Recording, image_to_probe_from_geometry

KINDS = ("null", "image_latency", "null", "force_sensor_error", "null", "viscoelasticity")
SOUND_SPEED_MM_PER_US = 1.54  # c = 1540 m/s
GENERATOR_VERSION = 1

# --------------------------------------------------------------------------------------------------------------------
# Mechanics
# --------------------------------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class Phantom:
    """A tissue block with one vessel, mm, kPa; the force cap (N) ends the FEM load steps."""

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

    def key(self) -> str:
        """Cache key of the solve, hex."""
        text = json.dumps({**asdict(self), "version": GENERATOR_VERSION}, sort_keys=True)
        return hashlib.sha1(text.encode()).hexdigest()[:16]


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
        top = np.flatnonzero((zz.ravel() == 0.0) & (np.abs(xx.ravel()) <= phantom.probe_width_mm / 2 + 1e-9))
        bottom = np.flatnonzero(zz.ravel() == self.z[-1])
        pin = bottom[np.argmin(np.abs(xx.ravel()[bottom]))]
        self.probe_z = 2 * top + 1
        fixed = np.concatenate([2 * top, 2 * top + 1, 2 * bottom + 1, [2 * pin]])
        self.free = np.setdiff1d(np.arange(2 * self.n_nodes), fixed)
        self.fixed = fixed

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


def _newton(model: _Model, u: np.ndarray, scale: float) -> tuple[np.ndarray, bool]:
    """Equilibrium from the start ``u`` (boundary values set), mm; returns (u, converged)."""
    forces, matrix = model.assemble(u)
    if matrix is None:
        return u, False
    for _ in range(25):
        residual = forces[model.free]
        norm = float(np.linalg.norm(residual))
        if norm < 1e-7 * scale:
            return u, True
        reduced = matrix[model.free][:, model.free]
        step = spla.spsolve(reduced.tocsc(), -residual)
        alpha = 1.0
        for _ls in range(8):
            trial = u.copy()
            trial[model.free] += alpha * step
            trial_forces, trial_matrix = model.assemble(trial)
            if trial_matrix is not None and np.linalg.norm(trial_forces[model.free]) < max(norm, 1e-6 * scale):
                break
            alpha *= 0.5
        else:
            return u, False
        u, forces, matrix = trial, trial_forces, trial_matrix
    return u, False


def solve_phantom(phantom: Phantom, cache: Path | None, verbose: bool = False) -> Solution:
    """Probe indentation steps until the force (N) exceeds the cap or lambda its maximum; cached as npz."""
    path = cache / f"{phantom.key()}.npz" if cache is not None else None
    if path is not None and path.exists():
        data = np.load(path)
        return Solution(data["x"], data["z"], data["lambdas"], data["forces"], data["displacements"])
    model = _Model(phantom)
    nz, nx = len(model.z), len(model.x)
    u = np.zeros(2 * model.n_nodes)
    previous = u.copy()
    lambdas, forces, fields = [0.0], [0.0], [u.reshape(nz, nx, 2).copy()]
    scale = phantom.shear_modulus_kpa * 1e-3 * phantom.probe_width_mm
    lam, step = 0.0, 0.6
    start = time.perf_counter()
    while lam < phantom.max_lambda_mm - 1e-9 and forces[-1] < phantom.force_cap_n:
        step = min(step, phantom.max_lambda_mm - lam)
        target = lam + step
        guess = u + (u - previous) * (step / max(lambdas[-1] - lambdas[-2], 1e-9) if len(lambdas) > 1 else 0.0)
        guess[model.fixed] = 0.0
        guess[model.probe_z] = target
        solved, ok = _newton(model, guess, scale)
        if not ok:
            step /= 2
            if step < 0.05:
                break
            continue
        previous, u, lam = u, solved, target
        internal, _ = model.assemble(u)
        lambdas.append(lam)
        forces.append(float(internal[model.probe_z].sum() * phantom.elevation_mm))
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


# --------------------------------------------------------------------------------------------------------------------
# Imaging
# --------------------------------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class Scanner:
    """Linear-array B-mode scanner: geometry (mm), pulse (MHz, cycles), PSF (mm), gains (dB) and jitter (mm)."""

    rows: int
    cols: int
    depth_mm: float
    width_mm: float
    frequency_mhz: float
    pulse_cycles: float  # FWHM of the pulse envelope in carrier cycles
    lateral_fwhm_mm: float
    attenuation_db_cm_mhz: float
    tgc_db_per_cm: float
    noise_db: float  # electronic noise rms relative to the speckle rms at the top, before TGC
    gain_db: float  # speckle rms at the top relative to white
    dynamic_range_db: float
    wall_db: float
    jitter_mm: float  # rms of the per-frame smooth random perturbation of the sampling positions
    density_variation: float  # std of the log scatterer strength (smooth)
    fibres: int
    fine_rows: int = 8  # fine samples per pixel, axially
    fine_cols: int = 2  # ... laterally

    def image_to_probe(self) -> np.ndarray:
        return image_to_probe_from_geometry(self.rows, self.cols, self.depth_mm, self.width_mm)


_TEXTURE_DX_MM, _TEXTURE_DZ_MM = 0.05, 0.025


class Texture:
    """Reflectivity of the undeformed tissue on a fine grid (lateral x, depth z, mm), zero above the surface."""

    def __init__(self, phantom: Phantom, scanner: Scanner, rng: np.random.Generator):
        self.x0 = -scanner.width_mm / 2 - 12.0
        self.z0 = -1.0
        x1 = scanner.width_mm / 2 + 12.0
        z1 = min(scanner.depth_mm + phantom.max_lambda_mm + 6.0, phantom.depth_mm)
        nx = int(np.ceil((x1 - self.x0) / _TEXTURE_DX_MM)) + 1
        nz = int(np.ceil((z1 - self.z0) / _TEXTURE_DZ_MM)) + 1
        x = self.x0 + np.arange(nx) * _TEXTURE_DX_MM
        z = self.z0 + np.arange(nz) * _TEXTURE_DZ_MM
        zz, xx = np.meshgrid(z, x, indexing="ij")
        amplitude = rng.standard_normal((nz, nx)).astype(np.float32)
        density = gaussian_filter(rng.standard_normal((nz // 40 + 2, nx // 20 + 2)), 1.5)
        density = cv2.resize(density / max(density.std(), 1e-9), (nx, nz), interpolation=cv2.INTER_CUBIC)
        strength = np.exp(scanner.density_variation * density)
        bright = rng.random((nz, nx)) < 4e-4  # sparse strong reflectors: a heavier tail than Rayleigh
        strength = strength * np.where(bright, 4.0, 1.0)
        radius = np.hypot(xx - phantom.vessel_x_mm, zz - phantom.vessel_depth_mm)
        wall_thickness = 1.0
        wall = np.exp(-0.5 * ((radius - phantom.vessel_radius_mm - wall_thickness / 2) / (wall_thickness / 2.5)) ** 2)
        strength = strength * (1 + (10 ** (scanner.wall_db / 20) - 1) * wall)
        strength = np.where(radius < phantom.vessel_radius_mm, 0.02, strength)
        for _ in range(scanner.fibres):
            depth = float(rng.uniform(4.0, 35.0))
            if abs(depth - phantom.vessel_depth_mm) < phantom.vessel_radius_mm + 3:
                continue
            slope = np.tan(np.radians(rng.uniform(-5, 5)))
            centre, half = float(rng.uniform(-10, 10)), float(rng.uniform(8, 25))
            line = np.exp(-0.5 * ((zz - depth - slope * (xx - centre)) / 0.15) ** 2)
            line *= 1 / (1 + np.exp((np.abs(xx - centre) - half) / 1.5))
            strength = strength * (1 + (10 ** (rng.uniform(6, 10) / 20) - 1) * line)
        strength = np.where(zz < 0, 0.0, strength)
        self.values = (amplitude * strength).astype(np.float32)


def _interp_matrix(fine: np.ndarray, coarse: np.ndarray) -> np.ndarray:
    """(len(fine), len(coarse)) linear interpolation weights (clamped at the ends)."""
    return np.stack([np.interp(fine, coarse, column) for column in np.eye(len(coarse))], axis=1)


class Renderer:
    """Renders frames of one case: probe-frame fine grid -> reference texture -> RF -> envelope -> uint8."""

    def __init__(self, solution: Solution, texture: Texture, scanner: Scanner):
        self.solution, self.texture, self.scanner = solution, texture, scanner
        s = scanner
        dx, dz = s.width_mm / s.cols, s.depth_mm / s.rows
        nxf, nzf = s.cols * s.fine_cols, s.rows * s.fine_rows
        self.xf = -s.width_mm / 2 - dx / 2 + (np.arange(nxf) + 0.5) * dx / s.fine_cols
        self.zf = -dz / 2 + (np.arange(nzf) + 0.5) * dz / s.fine_rows
        self.dzf = dz / s.fine_rows
        self.xc = np.linspace(self.xf[0], self.xf[-1], int(np.ceil(s.width_mm / 0.25)) + 1)
        self.zc = np.linspace(self.zf[0], self.zf[-1], int(np.ceil(s.depth_mm / 0.25)) + 1)
        self.wx, self.wz = _interp_matrix(self.xf, self.xc), _interp_matrix(self.zf, self.zc)
        self.xj = np.linspace(self.xf[0], self.xf[-1], int(s.width_mm / 1.0) + 1)
        self.zj = np.linspace(self.zf[0], self.zf[-1], int(s.depth_mm / 1.0) + 1)
        self.wxj, self.wzj = _interp_matrix(self.xf, self.xj), _interp_matrix(self.zf, self.zj)
        spatial_frequency = 2 * s.frequency_mhz / SOUND_SPEED_MM_PER_US  # cycles per mm of depth (two-way)
        fwhm = s.pulse_cycles / spatial_frequency
        sigma = fwhm / 2.3548
        taps = np.arange(-int(np.ceil(3 * sigma / self.dzf)), int(np.ceil(3 * sigma / self.dzf)) + 1) * self.dzf
        self.axial = (np.exp(-0.5 * (taps / sigma) ** 2) * np.cos(2 * np.pi * spatial_frequency * taps)).astype(
            np.float32
        )
        lateral_sigma = s.lateral_fwhm_mm / 2.3548 / (dx / s.fine_cols)
        half = int(np.ceil(3 * lateral_sigma))
        lx = np.arange(-half, half + 1)
        self.lateral = np.exp(-0.5 * (lx / lateral_sigma) ** 2).astype(np.float32)
        depth_cm = np.clip(self.zf, 0, None)[:, None] / 10
        self.attenuation = (10 ** (-2 * s.attenuation_db_cm_mhz * s.frequency_mhz * depth_cm / 20)).astype(np.float32)
        self.tgc = (10 ** (s.tgc_db_per_cm * depth_cm / 20)).astype(np.float32)
        # rms of the RF of unit texture through the PSF: the envelope reference (speckle level before gains)
        probe = np.random.default_rng(0).standard_normal((400, 200)).astype(np.float32)
        self.reference = float(np.std(cv2.sepFilter2D(probe, -1, self.lateral, self.axial)[50:-50, 30:-30]))

    def reference_positions(self, lam: float) -> tuple[np.ndarray, np.ndarray]:
        """Reference (x, z) (mm) of the coarse probe-frame grid for tissue pressed ``lam`` mm, by fixed point."""
        sol = self.solution
        field = sol.displacement_at(lam)
        ux = RegularGridInterpolator((sol.z_nodes, sol.x_nodes), field[..., 0], bounds_error=False, fill_value=None)
        uz = RegularGridInterpolator((sol.z_nodes, sol.x_nodes), field[..., 1], bounds_error=False, fill_value=None)
        zz, xx = np.meshgrid(self.zc + lam, self.xc, indexing="ij")
        x_def, z_def = xx.ravel(), zz.ravel()
        x_ref, z_ref = x_def.copy(), z_def.copy()
        for _ in range(12):
            points = np.column_stack([np.clip(z_ref, sol.z_nodes[0], sol.z_nodes[-1]), x_ref])
            x_new, z_new = x_def - ux(points), z_def - uz(points)
            change = max(np.abs(x_new - x_ref).max(), np.abs(z_new - z_ref).max())
            x_ref, z_ref = x_new, z_new
            if change < 1e-4:
                break
        return x_ref.reshape(zz.shape), z_ref.reshape(zz.shape)

    def render(self, lam: float, rng: np.random.Generator) -> np.ndarray:
        """(rows, cols) uint8 frame of the tissue pressed ``lam`` mm; ``rng`` draws jitter and noise."""
        s, t = self.scanner, self.texture
        x_ref_c, z_ref_c = self.reference_positions(lam)
        x_ref = self.wz @ x_ref_c @ self.wx.T
        z_ref = self.wz @ z_ref_c @ self.wx.T
        for target in (x_ref, z_ref):  # smooth sub-resolution motion, new every frame
            jitter = gaussian_filter(rng.standard_normal((len(self.zj), len(self.xj))), 1.0)
            jitter *= s.jitter_mm / max(float(jitter.std()), 1e-12)
            target += self.wzj @ jitter @ self.wxj.T
        map_x = ((x_ref - t.x0) / _TEXTURE_DX_MM).astype(np.float32)
        map_y = ((z_ref - t.z0) / _TEXTURE_DZ_MM).astype(np.float32)
        reflectivity = cv2.remap(t.values, map_x, map_y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT)
        echo = cv2.sepFilter2D(reflectivity, -1, self.lateral, self.axial, borderType=cv2.BORDER_CONSTANT)
        rf: np.ndarray = np.asarray(echo, dtype=np.float32) * (self.attenuation / self.reference)
        white = rng.standard_normal(rf.shape).astype(np.float32)  # receiver noise, band-limited by the pulse
        band = cv2.sepFilter2D(white, -1, np.ones(1, np.float32), self.axial, borderType=cv2.BORDER_REFLECT)
        noise: np.ndarray = np.asarray(band, dtype=np.float32)
        noise = noise * (10 ** (s.noise_db / 20) / max(float(noise.std()), 1e-12))
        rf = (rf + noise) * self.tgc
        envelope = np.abs(hilbert(rf, axis=0)).astype(np.float32)
        level = 20 * np.log10(envelope + 1e-6) + s.gain_db
        grey = np.clip((level + s.dynamic_range_db) / s.dynamic_range_db, 0, 1) * 255
        pixels = cv2.resize(grey.astype(np.float32), (s.cols, s.rows), interpolation=cv2.INTER_AREA)
        return np.clip(np.rint(pixels), 0, 255).astype(np.uint8)


# --------------------------------------------------------------------------------------------------------------------
# Timeline, effects, recording
# --------------------------------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class Protocol:
    """Force-controlled palpation: contact force, peak (N), ramp rate (N/s), hold (s); noise (N, mm); rate (fps)."""

    contact_n: float
    max_force_n: float
    ramp_n_per_s: float
    hold_s: float
    force_noise_n: float
    ripple_mm: float
    frame_rate_hz: float
    max_frames: int

    @property
    def duration_s(self) -> float:
        return 2 * (self.max_force_n - self.contact_n) / self.ramp_n_per_s + self.hold_s

    def target(self, t: np.ndarray) -> np.ndarray:
        """Target force (N) at times ``t`` (s): contact before 0 and after the palpation."""
        up = self.contact_n + self.ramp_n_per_s * t
        down = self.contact_n + self.ramp_n_per_s * (self.duration_s - t)
        return np.clip(np.minimum(np.minimum(up, down), self.max_force_n), self.contact_n, None)


def _trajectory(
    solution: Solution, protocol: Protocol, hidden: dict[str, float], kind: str, rng: np.random.Generator
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Force control on a 1 kHz clock from -1 s: times (s), true lambda (mm), true contact force (N)."""
    dt = 1e-3
    t = np.arange(-1.0, protocol.duration_s + 0.5, dt)
    target = protocol.target(t)
    if kind == "viscoelasticity":
        g, tau = hidden["g"], hidden["tau_s"]
        decay = np.exp(-dt / tau)
        elastic = np.empty_like(t)
        q = 0.0
        elastic[0] = target[0]
        for i in range(1, len(t)):  # F_target = F_e + q, q' = -q / tau + g F_e'
            q = (q * decay + g * (target[i] - elastic[i - 1])) / (1 + g)
            elastic[i] = target[i] - q
        commanded = solution.lambda_at(elastic)
    else:
        commanded = solution.lambda_at(target)
    ripple = gaussian_filter1d(rng.standard_normal(len(t)), 1 / (2 * np.pi * 3.0 * dt))
    ripple *= protocol.ripple_mm / max(float(ripple.std()), 1e-12)
    lam = np.clip(commanded + ripple, 0.0, solution.lambdas[-1])
    elastic_true = solution.force_at(lam)
    force = elastic_true.copy()
    if kind == "viscoelasticity":
        g, tau = hidden["g"], hidden["tau_s"]
        decay = np.exp(-dt / tau)
        q = 0.0
        for i in range(1, len(t)):
            q = q * decay + g * (elastic_true[i] - elastic_true[i - 1])
            force[i] += q
    return t, lam, force


def _frame_times(protocol: Protocol, rng: np.random.Generator) -> np.ndarray:
    """Frame timestamps (s) over the palpation: the scanner's clock, at most ``max_frames`` kept, 1 ms jitter."""
    period = 1 / protocol.frame_rate_hz
    ticks = np.arange(rng.uniform(0, period), protocol.duration_s, period)
    if len(ticks) > protocol.max_frames:
        ticks = ticks[np.rint(np.linspace(0, len(ticks) - 1, protocol.max_frames)).astype(int)]
    return np.sort(ticks + rng.uniform(-5e-4, 5e-4, len(ticks)))


def _probe_to_base(lam: np.ndarray, surface_to_base: np.ndarray) -> np.ndarray:
    """(n, 4, 4) probe poses: probe z into the tissue (surface z up), origin lambda (mm) below the surface."""
    poses = np.tile(np.eye(4), (len(lam), 1, 1))
    poses[:, :3, :3] = np.diag([1.0, -1.0, -1.0])
    poses[:, 2, 3] = -lam
    return surface_to_base[None] @ poses


def _draw_case(kind: str, rng: np.random.Generator, quick: bool) -> tuple[Phantom, Scanner, Protocol, dict]:
    """Random nuisance (phantom, scanner, protocol) and the hidden effect's parameters."""
    probe_width = float(rng.choice([37.5, 40.0, 42.0, 45.0, 48.0]))
    max_force = float(rng.uniform(8.0, 20.0))
    phantom = Phantom(
        width_mm=float(rng.uniform(100, 150)),
        depth_mm=float(rng.uniform(60, 80)),
        probe_width_mm=probe_width,
        vessel_x_mm=float(rng.uniform(-4, 4)),
        vessel_depth_mm=float(rng.uniform(14, 24)),
        vessel_radius_mm=float(rng.uniform(4, 7)),
        shear_modulus_kpa=float(rng.uniform(10, 40)),
        poisson_ratio=float(rng.uniform(0.45, 0.49)),
        stiffening_b=float(rng.uniform(0.3, 3.0)),
        lumen_ratio=float(np.exp(rng.uniform(np.log(0.005), np.log(0.05)))),
        elevation_mm=float(rng.uniform(20, 30)),  # plane-strain force per mm -> N (3-D spread)
        element_mm=1.6 if quick else float(rng.uniform(1.0, 1.3)),
        force_cap_n=round(1.15 * max_force + 1.0, 1),
    )
    widths = [w for w in (37.5, 40.0, 42.5, 45.0) if w <= probe_width]
    scanner = Scanner(
        rows=256,
        cols=int(rng.choice([192, 224, 256])),
        depth_mm=float(rng.choice([40.0, 42.5, 45.0])),
        width_mm=float(rng.choice(widths)),
        frequency_mhz=float(rng.uniform(5.0, 7.5)),
        pulse_cycles=float(rng.uniform(1.2, 2.0)),
        lateral_fwhm_mm=float(rng.uniform(0.4, 0.8)),
        attenuation_db_cm_mhz=float(rng.uniform(0.3, 0.7)),
        tgc_db_per_cm=float(rng.uniform(3.0, 8.0)),
        noise_db=float(rng.uniform(-45, -30)),
        gain_db=float(rng.uniform(-26, -16)),
        dynamic_range_db=float(rng.uniform(50, 60)),
        wall_db=float(rng.uniform(6, 12)),
        jitter_mm=float(rng.uniform(0.01, 0.02)),
        density_variation=float(rng.uniform(0.1, 0.3)),
        fibres=int(rng.integers(0, 3)),
        fine_rows=4 if quick else 8,
    )
    protocol = Protocol(
        contact_n=float(rng.uniform(0.2, 0.5)),
        max_force_n=max_force,
        ramp_n_per_s=float(rng.uniform(3, 6)),
        hold_s=float(rng.uniform(1.5, 3.0)),
        force_noise_n=float(rng.uniform(0.02, 0.06)),
        ripple_mm=float(rng.uniform(0.01, 0.05)),
        frame_rate_hz=float(rng.uniform(20, 30)),
        max_frames=40 if quick else int(rng.integers(80, 121)),
    )
    hidden: dict[str, float] = {}
    if kind == "image_latency":
        hidden = {"delay_s": float(rng.uniform(0.05, 0.15))}
    elif kind == "force_sensor_error":
        hidden = {
            "bias_n": float(rng.uniform(0.3, 1.0) * rng.choice([-1.0, 1.0])),
            "drift_n_per_s": float(rng.uniform(0.0, 0.02) * rng.choice([-1.0, 1.0])),
        }
    elif kind == "viscoelasticity":
        g = float(rng.uniform(0.15, 0.45))
        hidden = {
            "g": g,
            "tau_s": float(np.exp(rng.uniform(np.log(0.5), np.log(3.0)))),
            "g_prony_equivalent": g / (1 + g),
        }
    return phantom, scanner, protocol, hidden


def generate_case(
    kind: str, rng: np.random.Generator, directory: Path, cache: Path, quick: bool = False, png: bool = False
) -> dict[str, object]:
    """Simulate one palpation into ``directory / palpation.seq.nrrd``; returns what was hidden and drawn."""
    phantom, scanner, protocol, hidden = _draw_case(kind, rng, quick)
    solution = solve_phantom(phantom, cache)
    reached = float(solution.forces[-1])
    if protocol.max_force_n > 0.85 * reached:  # soft phantom: press less than the FEM reached
        protocol = Protocol(**{**asdict(protocol), "max_force_n": 0.85 * reached})
    texture = Texture(phantom, scanner, np.random.default_rng(rng.integers(2**63)))
    renderer = Renderer(solution, texture, scanner)
    t, lam, force = _trajectory(solution, protocol, hidden, kind, np.random.default_rng(rng.integers(2**63)))
    times = _frame_times(protocol, rng)
    frame_lambda = np.interp(times, t, lam)
    frame_force = np.interp(times, t, force) + rng.normal(0.0, protocol.force_noise_n, len(times))
    if kind == "force_sensor_error":
        frame_force = frame_force + hidden["bias_n"] + hidden["drift_n_per_s"] * times
    delay = hidden.get("delay_s", 0.0)
    imaged_lambda = np.interp(times - delay, t, lam)
    frame_rng = np.random.default_rng(rng.integers(2**63))
    frames = np.stack([renderer.render(float(v), frame_rng) for v in imaged_lambda])
    yaw = np.radians(rng.uniform(-30, 30))
    surface_to_base = np.array(
        [
            [np.cos(yaw), -np.sin(yaw), 0.0, float(rng.uniform(400, 600))],
            [np.sin(yaw), np.cos(yaw), 0.0, float(rng.uniform(-100, 100))],
            [0.0, 0.0, 1.0, float(rng.uniform(50, 150))],
            [0.0, 0.0, 0.0, 1.0],
        ]
    )
    recording = Recording(
        frames=frames,
        timestamps=times,
        probe_to_base=_probe_to_base(frame_lambda, surface_to_base),
        pose_valid=np.ones(len(times), dtype=bool),
        image_to_probe=scanner.image_to_probe(),
        force=frame_force,
        probe_displacement=frame_lambda,
    )
    directory.mkdir(parents=True, exist_ok=True)
    write_sequence(directory / "palpation.seq.nrrd", recording)
    if png:
        for index in np.linspace(0, len(frames) - 1, 5).astype(int):
            cv2.imwrite(str(directory / f"frame_{index:03d}.png"), frames[index])
    return {
        "hidden_parameters": hidden,
        "phantom": asdict(phantom),
        "scanner": asdict(scanner),
        "protocol": asdict(protocol),
        "fem_max_force_n": reached,
        "fem_max_lambda_mm": float(solution.lambdas[-1]),
        "peak_lambda_mm": float(frame_lambda.max()),
        "n_frames": len(times),
    }


# --------------------------------------------------------------------------------------------------------------------
# Evaluation
# --------------------------------------------------------------------------------------------------------------------


ATTRIBUTING = ("explained", "explained_in_part", "ambiguous")
"""Verdicts that name an effect as the cause (as diagnosis.json's ``verdict``; ``named`` lists the effects, two
when ambiguous); ``at_edge_of_library``, ``unexplained`` and ``no_significant_gap`` name none."""


def _score(kind: str, result: dict) -> dict[str, object]:
    """Verdict, the effects it names, top candidate, whether the hidden effect was named (a verdict in
    ATTRIBUTING naming it; an ambiguous verdict names two), its fitted entry."""
    effects = result.get("effects", [])
    top = effects[0] if effects else None
    entry = next((e for e in effects if e["effect"] == kind), None)
    named = list(result.get("named", []))
    return {
        "verdict": result["verdict"],
        "named": named,
        "top": top["effect"] if top else None,
        "top_shrink": top["shrink"] if top else None,
        "top_parameters": top["parameters"] if top else None,
        "named_first": kind != "null" and result["verdict"] in ATTRIBUTING and kind in named,
        "true_entry_parameters": entry["parameters"] if entry else None,
        "true_entry_shrink": entry["shrink"] if entry else None,
        "significant_measures": [
            {k: m.get(k) for k in ("name", "region", "phase", "value", "uncertainty")}
            for m in result.get("measures", [])
            if m.get("significant")
        ],
        "calibration": result.get("calibration"),
    }


def _fmt(value: object, digits: int = 3) -> str:
    if value is None:
        return "-"
    if isinstance(value, float):
        return f"{value:.{digits}g}"
    if isinstance(value, dict):
        return ", ".join(f"{k}={_fmt(v)}" for k, v in value.items() if k != "g_prony_equivalent")
    return str(value)


def _rate(flags: list[bool]) -> str:
    return f"{sum(flags)}/{len(flags)}" + (f" ({100 * sum(flags) / len(flags):.0f} %)" if flags else "")


def _in_top(row: dict) -> bool:
    """The hidden effect is among the named effects or in a named pair, with a verdict that attributes."""
    named = [part for name in row.get("named", []) for part in str(name).split("+")]
    return row["verdict"] in ATTRIBUTING and row["kind"] in named


def summary_markdown(rows: list[dict], command: str) -> str:
    """Per-case table and rates."""
    lines = [
        "# Gap diagnosis on the independent generator",
        "",
        f"Command: `{command}`",
        "",
        "| case | kind | hidden parameters | verdict | top effect | top shrink | named | gen s | diag s |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for row in rows:
        lines.append(
            f"| {row['case']} | {row['kind']} | {_fmt(row['hidden_parameters']) or '-'} | {row['verdict']} | "
            f"{row['top']} | {_fmt(row['top_shrink'], 2)} | {row['named_first'] if row['kind'] != 'null' else '-'} | "
            f"{row['generation_s']:.0f} | {row['diagnosis_s']:.0f} |"
        )
    lines += [
        "",
        "Calibration against the generator's truth (the diagnosis's library is a Yeoh section with a fixed"
        " base; its modulus absorbs the force scale, so only the ratios across cases compare):",
        "",
        "| case | modulus kPa true / fitted | depth mm true / fitted | probe face mm true / fitted | vessel depth mm "
        "true / fitted | vessel radius mm true / fitted | peak lambda mm | significant measures |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for row in rows:
        phantom = row["phantom"]
        fitted = (row.get("calibration") or [{}])[0]
        lines.append(
            f"| {row['case']} | {phantom['shear_modulus_kpa']:.1f} / {_fmt(fitted.get('shear_modulus_kpa'))} | "
            f"{phantom['depth_mm']:.1f} / {_fmt(fitted.get('section_depth_mm'))} | "
            f"{phantom['probe_width_mm']:.1f} / {_fmt(fitted.get('section_probe_width_mm'))} | "
            f"{phantom['vessel_depth_mm']:.1f} / {_fmt(fitted.get('vessel_depth_mm'))} | "
            f"{phantom['vessel_radius_mm']:.1f} / {_fmt(fitted.get('vessel_radius_mm'))} | "
            f"{row['peak_lambda_mm']:.1f} | {len(row['significant_measures'])} |"
        )
    nulls = [r for r in rows if r["kind"] == "null"]
    singles = [r for r in rows if r["kind"] != "null"]
    seconds = [r["generation_s"] + r["diagnosis_s"] for r in rows]
    lines += [
        "",
        "| rate | value |",
        "|---|---|",
        f"| nulls not attributed (verdict not in {', '.join(ATTRIBUTING)}; errors included) | "
        f"{_rate([r['verdict'] not in ATTRIBUTING for r in nulls])} |",
        f"| diagnosis errors (all kinds) | {_rate([r['verdict'].startswith('error') for r in rows])} |",
        f"| nulls called no_significant_gap | {_rate([r['verdict'] == 'no_significant_gap' for r in nulls])} |",
        f"| nulls called unexplained | {_rate([r['verdict'] == 'unexplained' for r in nulls])} |",
        f"| single effects named (an attributing verdict naming them) | "
        f"{_rate([bool(r['named_first']) for r in singles])} |",
        f"| single effects in the top candidate, pairs included (explained) | {_rate([_in_top(r) for r in singles])} |",
    ]
    for effect in sorted({r["kind"] for r in singles}):
        chosen = [bool(r["named_first"]) for r in singles if r["kind"] == effect]
        lines.append(f"| ... {effect} | {_rate(chosen)} |")
    if seconds:
        lines.append(
            f"| time per case, median / max (s) | {np.median(seconds):.0f} / {np.max(seconds):.0f} "
            f"(diagnosis median {np.median([r['diagnosis_s'] for r in rows]):.0f}) |"
        )
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0] if __doc__ else None)
    parser.add_argument("--cases", type=int, default=6)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", type=Path, default=Path("gap-independent"))
    parser.add_argument("--quick", action="store_true", help="coarse mesh, 40 frames, 4 fine samples per pixel")
    parser.add_argument("--no-diagnose", action="store_true", help="generate the recordings only")
    parser.add_argument("--png", action="store_true", help="write 5 frames per case as PNG")
    parser.add_argument("--fresh", action="store_true", help="rerun cases already in DIR/cases.jsonl")
    parser.add_argument("--workers", type=int, default=None, help="processes for the diagnosis's FEM solves")
    args = parser.parse_args(argv)
    out: Path = args.out
    out.mkdir(parents=True, exist_ok=True)
    command = "python benches/gap_independent.py " + " ".join(sys.argv[1:] if argv is None else argv)
    generation_root, diagnosis_root = np.random.SeedSequence(args.seed).spawn(2)
    generation = generation_root.spawn(args.cases)
    diagnosis_seeds = [int(s.generate_state(1)[0]) for s in diagnosis_root.spawn(args.cases)]
    log = out / "cases.jsonl"
    rows: list[dict] = []
    if log.exists() and not args.fresh and not args.no_diagnose:
        for line in log.read_text().splitlines():
            try:
                row = json.loads(line)
            except json.JSONDecodeError:
                continue
            same = row.get("seed") == args.seed and row.get("quick") == args.quick
            if same and row.get("version") == GENERATOR_VERSION and row["case"] < args.cases:
                rows.append(row)
    done = {row["case"] for row in rows}
    if not args.no_diagnose:
        log.write_text("".join(json.dumps(row) + "\n" for row in rows))
    for index in range(args.cases):
        if index in done:
            continue
        kind = KINDS[index % len(KINDS)]
        directory = out / f"case_{index:03d}"
        start = time.perf_counter()
        drawn = generate_case(
            kind, np.random.default_rng(generation[index]), directory, out / "fem_cache", args.quick, args.png
        )
        generation_s = time.perf_counter() - start
        print(
            f"case {index} ({kind}): generated in {generation_s:.0f} s {_fmt(drawn['hidden_parameters'])}", flush=True
        )
        if args.no_diagnose:
            continue
        start = time.perf_counter()
        try:
            result = diagnose(
                [directory / "palpation.seq.nrrd"], seed=diagnosis_seeds[index], progress=False, workers=args.workers
            ).to_json()
        except Exception as exc:  # a failed diagnosis is an outcome to report
            result = {"verdict": f"error: {type(exc).__name__}: {exc}", "effects": [], "measures": []}
        diagnosis_s = time.perf_counter() - start
        (directory / "diagnosis.json").write_text(json.dumps(result, indent=1))
        row = {
            "case": index,
            "seed": args.seed,
            "quick": args.quick,
            "version": GENERATOR_VERSION,
            "kind": kind,
            "hidden": None if kind == "null" else kind,
            **drawn,
            **_score(kind, result),
            "generation_s": generation_s,
            "diagnosis_s": diagnosis_s,
        }
        rows.append(row)
        with log.open("a") as handle:
            handle.write(json.dumps(row) + "\n")
        print(
            f"case {index} ({kind}): {row['verdict']}, top {row['top']} (shrink {_fmt(row['top_shrink'], 2)}), "
            f"diagnosed in {diagnosis_s:.0f} s",
            flush=True,
        )
    if args.no_diagnose:
        return
    rows.sort(key=lambda r: r["case"])
    text = summary_markdown(rows, command)
    (out / "summary.md").write_text(text)
    print(text)


if __name__ == "__main__":
    main()
