"""Clinical sweeps of the independent generator: sections that change along the sweep (a vessel's depth and radius,
a branch), an artery beside a vein, a probe path over a curved surface, skin and fat over muscle with a rigid bone
below, at 2-15 N; each written as two palpations and a force-controlled sweep (PLUS sequence files) with the
zero-force lumen of every vessel in every frame's own plane (benches/clinical_independent.py is its command).

Mechanics: plane strain per section (``mechanics``' Q4 Demiray FEM, sticking flat probe), with per Gauss point
materials: layers (skin, fat, muscle as ratios of the muscle's shear modulus), lumens (their own stiffness ratio,
Poisson's ratio 0.3, no stiffening), a bone disc whose nodes are fixed (rigid, held by the skeleton). A sweep solves
its section at one to three places along it; a frame between two solved places takes their geometry, displacement
field and force curve blended linearly (the zero-force truth is the blended geometry, and the frame is rendered
from exactly that geometry moved by exactly that field, so image and truth agree; the field between places is an
interpolation, not an equilibrium).

Imaging: ``imaging.Renderer`` (RF pulse, PSF, attenuation, TGC, envelope, log compression) on a texture of this
module: skin bright, fat hypoechoic with septa, a bright fascia, muscle with perimysium striations, vessel walls,
anechoic lumens, the bone's bright cortex with a full acoustic shadow; speckle from independent scatterer layers
every 0.5 mm along the path, summed by a Gaussian elevation beam (sigma 0.6 mm).

Poses: the probe travels along the surface (the image normal); over a curved surface (radius R, centre of curvature
below) it turns about its lateral axis by arc / R, so each frame's probe axis is the surface normal there and the
force stays along it. ProbeDisplacement is the indentation along that axis; the zero-force pose is the pressed pose
moved back along it.
"""

from __future__ import annotations

import hashlib
import json
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np
from scipy.ndimage import gaussian_filter, zoom
from scipy.special import expit

from usdeform.io import write_sequence
from usdeform.recording import Recording

from .imaging import _TEXTURE_DX_MM, _TEXTURE_DZ_MM, Renderer, Scanner
from .mechanics import Face, Phantom, Solution, _Model, solve_phantom

SHAPES = ("depth_radius", "branch", "artery_vein", "curved", "layered_bone", "combined")
_GAUSS = np.array([[-1.0, -1.0], [1.0, -1.0], [1.0, 1.0], [-1.0, 1.0]]) / np.sqrt(3.0)


@dataclass(frozen=True)
class Circle:
    """One lumen disc of vessel ``vessel`` (a branching vessel has two), mm; ``ratio``: its shear modulus over the
    muscle's."""

    vessel: str
    x_mm: float
    depth_mm: float
    radius_mm: float
    ratio: float


@dataclass(frozen=True)
class Section:
    """A plane-strain section: lumens, layers ((bottom depth mm, modulus ratio), from the top), a bone disc (centre x,
    top depth, radius mm; radius 0: none)."""

    circles: tuple[Circle, ...]
    layers: tuple[tuple[float, float], ...] = ()
    bone: tuple[float, float, float] = (0.0, 0.0, 0.0)

    def blend(self, other: Section, weight: float) -> Section:
        """Geometry ``weight`` of the way to ``other`` (the same circles, layers and bone, in order)."""

        def mix(a: float, b: float) -> float:
            return (1 - weight) * a + weight * b

        circles = tuple(
            Circle(a.vessel, mix(a.x_mm, b.x_mm), mix(a.depth_mm, b.depth_mm), mix(a.radius_mm, b.radius_mm), a.ratio)
            for a, b in zip(self.circles, other.circles, strict=True)
        )
        layers = tuple((mix(a[0], b[0]), a[1]) for a, b in zip(self.layers, other.layers, strict=True))
        return Section(circles, layers, tuple(mix(a, b) for a, b in zip(self.bone, other.bone, strict=True)))  # type: ignore[arg-type]

    def vessels(self) -> list[str]:
        return sorted({c.vessel for c in self.circles})

    def lumen(self, x: np.ndarray, z: np.ndarray, vessel: str | None = None) -> np.ndarray:
        """True inside a lumen (of ``vessel``, or any) at tissue points (x, z), mm."""
        inside = np.zeros(np.broadcast(x, z).shape, dtype=bool)
        for c in self.circles:
            if vessel is None or c.vessel == vessel:
                inside |= (x - c.x_mm) ** 2 + (z - c.depth_mm) ** 2 < c.radius_mm**2
        return inside


@dataclass
class Spec:
    """One clinical sweep: its shape, target force (N), length along the surface (mm), surface radius along the path
    (mm, 0: flat), the sections solved at ``places`` (fractions of the length), the tissue, scanner and frames."""

    name: str
    shape: str
    force_n: float
    length_mm: float
    surface_radius_mm: float
    places: tuple[float, ...]
    sections: tuple[Section, ...]
    phantom: Phantom
    scanner: Scanner
    sweep_frames: int
    palpation_frames: int
    seed: int
    notes: list[str] = field(default_factory=list)

    def section_at(self, s: float) -> tuple[int, int, float]:
        """(lower place, upper place, weight) of fraction ``s`` of the length."""
        places = np.asarray(self.places)
        if len(places) == 1:
            return 0, 0, 0.0
        upper = int(np.clip(np.searchsorted(places, s), 1, len(places) - 1))
        weight = float(np.clip((s - places[upper - 1]) / (places[upper] - places[upper - 1]), 0.0, 1.0))
        return upper - 1, upper, weight

    def geometry(self, s: float) -> Section:
        lower, upper, weight = self.section_at(s)
        return self.sections[lower].blend(self.sections[upper], weight)


def _gauss_points(model: _Model) -> tuple[np.ndarray, np.ndarray]:
    """(x, z) of the model's Gauss points, (elements, 4) each, mm (element order of ``_Model``)."""
    iz, ix = np.meshgrid(np.arange(len(model.z) - 1), np.arange(len(model.x) - 1), indexing="ij")
    hx, hz = np.diff(model.x)[ix.ravel()], np.diff(model.z)[iz.ravel()]
    gx = model.x[ix.ravel()][:, None] + (1 + _GAUSS[None, :, 0]) * hx[:, None] / 2
    gz = model.z[iz.ravel()][:, None] + (1 + _GAUSS[None, :, 1]) * hz[:, None] / 2
    return gx, gz


def section_model(phantom: Phantom, section: Section) -> _Model:
    """The phantom's mesh with the section's materials per Gauss point and the bone's nodes fixed."""
    model = _Model(phantom)
    gx, gz = _gauss_points(model)
    ratio = np.ones_like(gx)
    top = 0.0
    for bottom, layer_ratio in section.layers:
        ratio = np.where((gz >= top) & (gz < bottom), layer_ratio, ratio)
        top = bottom
    bone_x, bone_top, bone_radius = section.bone
    nu = np.full_like(gx, phantom.poisson_ratio)
    stiffening = np.full_like(gx, phantom.stiffening_b)
    lumen = np.zeros_like(gx, dtype=bool)
    for c in section.circles:
        inside = (gx - c.x_mm) ** 2 + (gz - c.depth_mm) ** 2 < c.radius_mm**2
        ratio, lumen = np.where(inside, c.ratio, ratio), lumen | inside
    nu, stiffening = np.where(lumen, 0.3, nu), np.where(lumen, 0.0, stiffening)
    if bone_radius > 0:
        inside = (gx - bone_x) ** 2 + (gz - bone_top - bone_radius) ** 2 < bone_radius**2
        ratio = np.where(inside, 50.0, ratio)
        zz, xx = np.meshgrid(model.z, model.x, indexing="ij")
        nodes = np.flatnonzero(((xx - bone_x) ** 2 + (zz - bone_top - bone_radius) ** 2 < bone_radius**2).ravel())
        model.base = np.unique(np.concatenate([model.base, 2 * nodes, 2 * nodes + 1]))
    mu = phantom.shear_modulus_kpa * 1e-3 * ratio
    model.mu, model.b, model.lumen = mu, stiffening, lumen
    model.lam0 = (2 * mu * nu / (1 - 2 * nu)).mean(axis=1)
    model.pressure = np.zeros_like(mu)
    return model


def solve_section(spec: Spec, index: int, cache: Path) -> Solution:
    section = spec.sections[index]
    text = json.dumps({"phantom": asdict(spec.phantom), "section": asdict(section)}, sort_keys=True)
    key = "clinical-" + hashlib.sha1(text.encode()).hexdigest()[:16]
    return solve_phantom(spec.phantom, cache, model=section_model(spec.phantom, section), key=key)


class Blended:
    """The displacement field and force curve ``weight`` of the way between two section solutions on the same
    mesh; duck-types ``Solution`` for ``imaging.Renderer``."""

    def __init__(self, a: Solution, b: Solution, weight: float):
        self.a, self.b, self.weight = a, b, weight
        self.x_nodes, self.z_nodes = a.x_nodes, a.z_nodes
        top = min(a.lambdas[-1], b.lambdas[-1])
        self.lambdas = np.linspace(0.0, top, 200)
        self.forces = np.maximum.accumulate((1 - weight) * a.force_at(self.lambdas) + weight * b.force_at(self.lambdas))

    def displacement_at(self, lam: float) -> np.ndarray:
        return (1 - self.weight) * self.a.displacement_at(lam) + self.weight * self.b.displacement_at(lam)

    def force_at(self, lam: np.ndarray) -> np.ndarray:
        return np.interp(lam, self.lambdas, self.forces)

    def lambda_at(self, force: np.ndarray) -> np.ndarray:
        return np.interp(force, self.forces, self.lambdas)


class SectionTexture:
    """Reflectivity of one section (undeformed tissue frame, mm) on the fine grid of ``imaging``: structure from the
    section's geometry and the sweep's shared draws (``structure``), speckle from ``speckle`` (the elevation-beam
    sum of scatterer layers). Duck-types ``imaging.Texture`` for ``Renderer``."""

    def __init__(self, section: Section, structure: dict, speckle: np.ndarray, wall_db: float):
        self.x0, self.z0 = structure["x0"], structure["z0"]
        nz, nx = speckle.shape
        x = self.x0 + np.arange(nx) * _TEXTURE_DX_MM
        z = self.z0 + np.arange(nz) * _TEXTURE_DZ_MM
        zz, xx = np.meshgrid(z, x, indexing="ij")
        strength = structure["density"].copy()
        top = 0.0
        for (bottom, _ratio), echo in zip(section.layers, structure["layer_echo"], strict=False):
            strength *= np.where((zz >= top) & (zz < bottom), echo, 1.0)
            top = bottom
        if section.layers:
            fascia = np.exp(-0.5 * ((zz - section.layers[-1][0]) / 0.12) ** 2)
            strength *= 1 + 5.0 * fascia
            for depth, slope in structure["septa"]:  # fat septa: thin bright lines inside the fat
                if section.layers[0][0] < depth < section.layers[-1][0]:
                    strength *= 1 + 3.0 * np.exp(-0.5 * ((zz - depth - slope * xx) / 0.1) ** 2)
            for depth in structure["striations"]:  # perimysium in the muscle
                if depth > section.layers[-1][0] + 1.0:
                    strength *= 1 + 1.5 * np.exp(-0.5 * ((zz - depth) / 0.12) ** 2)
        for c in section.circles:
            radius = np.hypot(xx - c.x_mm, zz - c.depth_mm)
            wall = np.exp(-0.5 * ((radius - c.radius_mm - 0.7) / 0.3) ** 2)  # the intima-media outside the lumen
            strength *= 1 + (10 ** (wall_db / 20) - 1) * wall
        strength = np.where(section.lumen(xx, zz), 0.02, strength)
        self.opacity: np.ndarray | None = None
        self.loss_db_per_mm = 0.0
        bone_x, bone_top, bone_radius = section.bone
        if bone_radius > 0:
            distance = np.hypot(xx - bone_x, zz - bone_top - bone_radius)
            cortex = np.exp(-0.5 * ((distance - bone_radius + 0.3) / 0.25) ** 2)
            strength = strength * (1 + 30.0 * cortex)
            self.opacity = expit((bone_radius - 0.5 - distance) / 0.05).astype(np.float32)
            self.loss_db_per_mm = 60.0
        self.values = (np.where(zz < 0, 0.0, strength) * speckle).astype(np.float32)

    def weights(self, elevation_mm: float) -> list[tuple[float, np.ndarray]]:
        return [(1.0, self.values)]


class Speckle:
    """Scatterer layers every 0.5 mm along the path (standard normal amplitudes, 0.04 % bright points x4), each from
    its own seed; ``at(y)`` sums them with a Gaussian elevation beam of sigma 0.6 mm (squared weights sum to 1)."""

    def __init__(self, shape: tuple[int, int], seed: int, sigma_mm: float = 0.6):
        self.shape, self.seed, self.sigma, self.spacing = shape, seed, sigma_mm, 0.5
        self.layers: dict[int, np.ndarray] = {}

    def _layer(self, k: int) -> np.ndarray:
        if k not in self.layers:
            rng = np.random.default_rng([self.seed, k + 10**6])
            points = np.where(rng.random(self.shape) < 4e-4, 4.0, 1.0).astype(np.float32)
            self.layers[k] = rng.standard_normal(self.shape, dtype=np.float32) * points
        return self.layers[k]

    def at(self, y: float) -> np.ndarray:
        ks = np.arange(
            int(np.floor((y - 3 * self.sigma) / self.spacing)), int(np.ceil((y + 3 * self.sigma) / self.spacing)) + 1
        )
        raw = np.exp(-0.5 * ((ks * self.spacing - y) / self.sigma) ** 2)
        raw /= np.sqrt(np.sum(raw**2))
        for k in [k for k in self.layers if k < ks[0] - 1 or k > ks[-1] + 1]:
            del self.layers[k]
        return sum(float(w) * self._layer(int(k)) for w, k in zip(raw, ks, strict=True))  # type: ignore[return-value]


def structure(spec: Spec, rng: np.random.Generator) -> dict:
    """The sweep's shared tissue structure on the fine grid: smooth scatterer density, layer echoes (skin bright, fat
    dark), fat septa and muscle striations."""
    scanner, phantom = spec.scanner, spec.phantom
    x0, z0 = -scanner.width_mm / 2 - 12.0, -1.0
    z1 = min(scanner.depth_mm + phantom.max_lambda_mm + 6.0, phantom.depth_mm)
    nx = int(np.ceil((scanner.width_mm + 24.0) / _TEXTURE_DX_MM)) + 1
    nz = int(np.ceil((z1 - z0) / _TEXTURE_DZ_MM)) + 1
    coarse = gaussian_filter(rng.standard_normal((nz // 40 + 2, nx // 20 + 2)), 1.5)
    density = zoom(coarse / max(float(coarse.std()), 1e-9), (nz / coarse.shape[0], nx / coarse.shape[1]), order=1)
    density = np.exp(scanner.density_variation * density[:nz, :nx]).astype(np.float32)
    return {
        "x0": x0,
        "z0": z0,
        "shape": (nz, nx),
        "density": density,
        "layer_echo": [float(rng.uniform(2.0, 3.0)), float(rng.uniform(0.35, 0.55))],
        "septa": [(float(rng.uniform(1.0, 14.0)), float(np.tan(np.radians(rng.uniform(-8, 8))))) for _ in range(6)],
        "striations": list(np.cumsum(rng.uniform(1.5, 3.0, 30))),
    }


def zero_force_pose(spec: Spec, arc_mm: np.ndarray, surface_to_base: np.ndarray) -> np.ndarray:
    """(n, 4, 4) probe poses at first contact ``arc_mm`` along the surface: probe z into the tissue along the surface
    normal, x lateral; over a curved surface turned by arc / R about the lateral axis."""
    poses = np.tile(np.eye(4), (len(arc_mm), 1, 1))
    radius = spec.surface_radius_mm
    phi = arc_mm / radius if radius else np.zeros(len(arc_mm))
    c, s = np.cos(-phi), np.sin(-phi)
    rotation = np.zeros((len(arc_mm), 3, 3))
    rotation[:, 0, 0] = 1.0
    rotation[:, 1, 1], rotation[:, 1, 2], rotation[:, 2, 1], rotation[:, 2, 2] = c, -s, s, c
    poses[:, :3, :3] = rotation @ np.diag([1.0, -1.0, -1.0])
    if radius:
        poses[:, 1, 3], poses[:, 2, 3] = radius * np.sin(phi), radius * np.cos(phi) - radius
    else:
        poses[:, 1, 3] = arc_mm
    return surface_to_base[None] @ poses


def _pressed(zero_pose: np.ndarray, lam: np.ndarray) -> np.ndarray:
    """The poses moved ``lam`` mm along their probe z axis (into the tissue)."""
    poses = zero_pose.copy()
    poses[:, :3, 3] += lam[:, None] * zero_pose[:, :3, 2]
    return poses


def record(
    spec: Spec,
    solutions: list[Solution],
    shared: dict,
    speckle: Speckle,
    fractions: np.ndarray,
    lam: np.ndarray,
    rng: np.random.Generator,
) -> list[np.ndarray]:
    """Frames (uint8) at ``fractions`` of the length with indentations ``lam`` (mm); renderers are reused while the
    place along the sweep does not change (a palpation)."""
    frames = []
    cache: tuple[float, Renderer] | None = None
    face = Face.of(spec.phantom)
    for s, v in zip(fractions, lam, strict=True):
        if cache is None or cache[0] != s:
            lower, upper, weight = spec.section_at(float(s))
            texture = SectionTexture(
                spec.geometry(float(s)), shared, speckle.at(float(s) * spec.length_mm), spec.scanner.wall_db
            )
            blended = Blended(solutions[lower], solutions[upper], weight)
            cache = (float(s), Renderer(blended, texture, spec.scanner, face))  # type: ignore[arg-type]
        frames.append(cache[1].render(float(v), rng))
    return frames


def truth_masks(spec: Spec, fractions: np.ndarray) -> dict[str, np.ndarray]:
    """Zero-force lumen of every vessel in each frame's own pixel grid, (frames, rows, cols) bool per vessel (the
    flat level face at first contact: a pixel's tissue point is its probe-frame position)."""
    from .sweep import pixel_grid

    x, z = pixel_grid((spec.scanner.rows, spec.scanner.cols), spec.scanner.image_to_probe())
    masks: dict[str, list[np.ndarray]] = {}
    for s in fractions:
        geometry = spec.geometry(float(s))
        for vessel in geometry.vessels():
            masks.setdefault(vessel, []).append(geometry.lumen(x, z, vessel))
    return {k: np.stack(v) for k, v in masks.items()}


def generate(spec: Spec, directory: Path, cache: Path) -> dict:
    """Writes palpation_1/2.seq.nrrd (at 10 % and 90 % of the length), sweep.seq.nrrd and truth.npz (per vessel
    zero-force masks, zero-force poses, fractions, true force and indentation) into ``directory``; returns what was
    made (forces reached, frames, notes)."""
    solutions = [solve_section(spec, i, cache) for i in range(len(spec.sections))]
    reached = min(float(sol.forces[-1]) for sol in solutions)
    force = spec.force_n
    if force > 0.8 * reached / 1.2:
        force = 0.8 * reached / 1.2
        spec.notes.append(
            f"the FEM reached {reached:.1f} N only: the sweep holds {force:.1f} N, not {spec.force_n:.1f} N"
        )
    rng = np.random.default_rng(spec.seed)
    shared = structure(spec, rng)
    speckle = Speckle(shared["shape"], int(rng.integers(2**63)))
    yaw = np.radians(rng.uniform(-30, 30))
    surface_to_base = np.array(
        [[np.cos(yaw), -np.sin(yaw), 0, 500.0], [np.sin(yaw), np.cos(yaw), 0, 20.0], [0, 0, 1, 100.0], [0, 0, 0, 1.0]]
    )
    directory.mkdir(parents=True, exist_ok=True)
    image_to_probe = spec.scanner.image_to_probe()

    def write(path: Path, times: np.ndarray, fractions: np.ndarray, lam: np.ndarray, true_n: np.ndarray) -> np.ndarray:
        """Renders and writes one recording (the force read with 0.03 N of noise); returns its zero-force poses."""
        frames = record(spec, solutions, shared, speckle, fractions, lam, rng)
        zero = zero_force_pose(spec, fractions * spec.length_mm, surface_to_base)
        recording = Recording(
            frames=np.stack(frames),
            timestamps=times,
            probe_to_base=_pressed(zero, lam),
            pose_valid=np.ones(len(times), dtype=bool),
            image_to_probe=image_to_probe,
            force=true_n + rng.normal(0, 0.03, len(times)),
            probe_displacement=lam,
        )
        write_sequence(path, recording)
        return zero

    peak = 1.2 * force
    for index, s in enumerate((0.1, 0.9)):  # load-unload palpations at 4 N/s from 0.3 N
        times = np.linspace(0.0, 2 * (peak - 0.3) / 4.0, spec.palpation_frames)
        target = 0.3 + 4.0 * np.minimum(times, times[-1] - times)
        lower, upper, weight = spec.section_at(s)
        curve = Blended(solutions[lower], solutions[upper], weight)
        lam = np.clip(curve.lambda_at(target) + rng.normal(0, 0.01, len(times)), 0.0, curve.lambdas[-1])
        path = directory / f"palpation_{index + 1}.seq.nrrd"
        write(path, times, np.full(len(times), s), lam, curve.force_at(lam))
    duration = spec.length_mm / 8.0  # 8 mm/s
    times = np.linspace(0.0, duration, spec.sweep_frames)
    fractions = times / duration
    phase = rng.uniform(0, 2 * np.pi, 4)
    wobble = 0.03 * force * np.sin(2 * np.pi * 0.3 * times + phase[0])
    ripple = sum(np.sin(2 * np.pi * f * times + p) for f, p in zip((2.3, 3.1, 4.4), phase[1:], strict=True))
    true_force = force + wobble + 0.01 * force * ripple
    lam = np.empty(len(times))
    for k, s in enumerate(fractions):
        lower, upper, weight = spec.section_at(float(s))
        lam[k] = Blended(solutions[lower], solutions[upper], weight).lambda_at(true_force[k])
    lam = lam + rng.normal(0, 0.01, len(times))
    logged = np.array(
        [
            Blended(solutions[a], solutions[b], w).force_at(v)
            for (a, b, w), v in zip(map(spec.section_at, fractions), lam, strict=True)
        ]
    )
    zero = write(directory / "sweep.seq.nrrd", times, fractions, lam, logged)
    masks = truth_masks(spec, fractions)
    np.savez_compressed(
        directory / "truth.npz",
        **{f"zero_force_{k}": v for k, v in masks.items()},
        zero_force_pose=zero,
        fractions=fractions,
        arc_mm=fractions * spec.length_mm,
        true_force=logged,
        indentation=lam,
    )
    return {
        "fem_reached_n": reached,
        "sweep_force_n": force,
        "sweep_force_range_n": [float(logged.min()), float(logged.max())],
        "indentation_range_mm": [float(lam.min()), float(lam.max())],
        "vessels": sorted(masks),
        "notes": spec.notes,
    }


def _scanner(rng: np.random.Generator, quick: bool) -> Scanner:
    return Scanner(
        rows=192 if quick else 256,
        cols=150 if quick else 200,
        depth_mm=45.0,
        width_mm=38.0,
        frequency_mhz=float(rng.uniform(6.0, 7.5)),
        pulse_cycles=float(rng.uniform(1.2, 1.8)),
        lateral_fwhm_mm=float(rng.uniform(0.4, 0.7)),
        attenuation_db_cm_mhz=float(rng.uniform(0.3, 0.6)),
        tgc_db_per_cm=float(rng.uniform(4.0, 8.0)),
        noise_db=float(rng.uniform(-45, -35)),
        gain_db=float(rng.uniform(-24, -18)),
        dynamic_range_db=float(rng.uniform(50, 60)),
        wall_db=float(rng.uniform(8, 12)),
        jitter_mm=float(rng.uniform(0.01, 0.02)),
        density_variation=float(rng.uniform(0.1, 0.3)),
        fibres=0,
        fine_rows=4,
    )


def draw_specs(seed: int, quick: bool = False) -> list[Spec]:
    """The sweeps of one run: every shape of ``SHAPES`` once, then ``artery_vein`` and ``layered_bone`` again at a
    low force (2-6 N); forces 15 N or 2-10 N as listed. One stream per sweep (child i of ``seed``)."""
    plan = [
        ("depth_radius", 15.0),
        ("branch", None),
        ("artery_vein", 15.0),
        ("curved", None),
        ("layered_bone", 15.0),
        ("combined", None),
        ("artery_vein", "low"),
        ("layered_bone", "low"),
    ]
    specs = []
    for index, ((shape, force), stream) in enumerate(
        zip(plan, np.random.SeedSequence(seed).spawn(len(plan)), strict=True)
    ):
        rng = np.random.default_rng(stream)
        force_n = (
            float(rng.uniform(6.0, 10.0))
            if force is None
            else float(rng.uniform(2.0, 6.0))
            if force == "low"
            else force
        )
        artery_ratio, vein_ratio = float(rng.uniform(0.25, 0.5)), float(rng.uniform(0.02, 0.04))
        layers: tuple[tuple[float, float], ...] = ()
        bone = (0.0, 0.0, 0.0)
        radius_mm = 0.0
        if shape == "depth_radius":  # deeper and narrower along the sweep, 10-30 mm
            d0, d1 = float(rng.uniform(10, 14)), float(rng.uniform(24, 28))
            r0, r1 = float(rng.uniform(3.5, 4.2)), float(rng.uniform(2.4, 3.0))
            x = float(rng.uniform(-3, 3))
            sections = tuple(
                Section((Circle("vessel", x + 2 * f, d0 + (d1 - d0) * f, r0 + (r1 - r0) * f, vein_ratio * 4),))
                for f in (0.0, 0.5, 1.0)
            )
            places: tuple[float, ...] = (0.0, 0.5, 1.0)
        elif shape == "branch":  # a branch leaving the main vessel: inside it at the start, 9-12 mm beside at the end
            x, depth, r = float(rng.uniform(-5, -2)), float(rng.uniform(14, 18)), float(rng.uniform(3.2, 3.8))
            shift, rb = float(rng.uniform(9, 12)), float(rng.uniform(2.0, 2.6))
            sections = tuple(
                Section(
                    (
                        Circle("vessel", x, depth, r, artery_ratio),
                        Circle("vessel", x + shift * f, depth + 2.0 * f, r - (r - rb) * min(1.0, 2 * f), artery_ratio),
                    )
                )
                for f in (0.0, 0.5, 1.0)
            )
            places = (0.0, 0.5, 1.0)
        else:
            circles: tuple[Circle, ...]
            if shape in ("artery_vein", "combined"):  # vein 9-12 mm beside the artery, a little shallower
                xa, da = float(rng.uniform(-7, -4)), float(rng.uniform(14, 18))
                gap = float(rng.uniform(9, 12))
                circles = (
                    Circle("artery", xa, da, float(rng.uniform(3.0, 3.6)), artery_ratio),
                    Circle("vein", xa + gap, da - float(rng.uniform(1, 4)), float(rng.uniform(2.6, 3.2)), vein_ratio),
                )
            else:
                circles = (
                    Circle(
                        "vessel",
                        float(rng.uniform(-3, 3)),
                        float(rng.uniform(14, 20)),
                        float(rng.uniform(3.0, 4.0)),
                        artery_ratio,
                    ),
                )
            if shape in ("layered_bone", "combined"):  # skin, fat over muscle; a bone 5+ mm below the vessels
                skin, fat = float(rng.uniform(1.5, 2.5)), float(rng.uniform(4.0, 9.0))
                layers = ((skin, float(rng.uniform(2.0, 3.0))), (skin + fat, float(rng.uniform(0.25, 0.5))))
                lowest = max(c.depth_mm + c.radius_mm for c in circles)
                bone = (
                    float(rng.uniform(-6, 6)),
                    float(np.clip(lowest + rng.uniform(6, 14), 25, 40)),
                    float(rng.uniform(10, 15)),
                )
            if shape in ("curved", "combined"):
                radius_mm = float(rng.uniform(40, 100))
            sections = (Section(circles, layers, bone),)  # type: ignore[arg-type]
            places = (0.0,)
        deepest = max((c for sec in sections for c in sec.circles), key=lambda c: c.depth_mm + c.radius_mm)
        phantom = Phantom(
            width_mm=float(rng.uniform(110, 130)),
            depth_mm=float(rng.uniform(70, 80)),
            probe_width_mm=40.0,
            vessel_x_mm=deepest.x_mm,
            vessel_depth_mm=deepest.depth_mm,
            vessel_radius_mm=deepest.radius_mm,
            shear_modulus_kpa=float(rng.uniform(15, 30)),
            poisson_ratio=float(rng.uniform(0.46, 0.49)),
            stiffening_b=float(rng.uniform(0.5, 2.0)),
            lumen_ratio=0.5,
            elevation_mm=float(rng.uniform(20, 25)),
            element_mm=1.6 if quick else 1.3,
            force_cap_n=round(1.5 * force_n + 1.0, 1),
            max_lambda_mm=18.0,
        )
        length = float(rng.uniform(30, 45))
        if radius_mm:
            length = min(length, 0.6 * radius_mm)  # at most 0.6 rad of turn
        specs.append(
            Spec(
                name=f"{index:02d}_{shape}",
                shape=shape,
                force_n=force_n,
                length_mm=length,
                surface_radius_mm=radius_mm,
                places=places,
                sections=sections,
                phantom=phantom,
                scanner=_scanner(rng, quick),
                sweep_frames=30 if quick else 40,
                palpation_frames=24 if quick else 32,
                seed=int(rng.integers(2**63)),
            )
        )
    return specs


def describe(spec: Spec) -> dict:
    """The spec as JSON-ready values."""
    return {
        **{k: v for k, v in asdict(spec).items() if k not in ("phantom", "scanner", "sections")},
        "phantom": asdict(spec.phantom),
        "sections": [asdict(s) for s in spec.sections],
    }
