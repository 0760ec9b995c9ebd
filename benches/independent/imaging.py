"""Imaging of the independent generator: a reflectivity texture of the undeformed tissue (optionally a stack of
elevation slices) and a linear-array RF B-mode model (pulse, attenuation, noise, TGC, envelope, log compression)."""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
from scipy.interpolate import RegularGridInterpolator
from scipy.ndimage import gaussian_filter
from scipy.signal import hilbert
from scipy.special import expit

from usdeform.recording import image_to_probe_from_geometry

from .mechanics import Face, Phantom, Solution

SOUND_SPEED_MM_PER_US = 1.54  # c = 1540 m/s, the speed the scanner assumes
ASSUMED_SPEED_M_PER_S = 1540.0


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
    """Reflectivity of the undeformed tissue on a fine grid (lateral x, depth z, mm), zero above the surface.

    ``elevation``: (beam sigma, lowest and highest beam position), mm, to add elevation slices: independent
    scatterer layers (amplitudes and bright points) at spacing sigma / 2 covering the beam's positions +- 3 sigma,
    the structure (density, wall, lumen, fibres) shared; slice 0 (elevation 0) is the texture drawn without them.
    ``shadow``: (x, z, radius mm, echo dB, loss dB) of a calcification: a disc whose reflectivity is raised by the
    echo and whose opacity (1 inside, a 0.2 mm soft edge) costs the loss (two-way, dB) across its diameter.
    ``inclusion``: (x, z, radius mm, echo dB) of a stiff inclusion: its scatterers are the tissue's, their strength
    raised by the echo (0 dB: isoechoic, the texture unchanged) inside the disc (a 0.2 mm soft edge)."""

    def __init__(
        self,
        phantom: Phantom,
        scanner: Scanner,
        rng: np.random.Generator,
        elevation: tuple[float, float, float] | None = None,
        shadow: tuple[float, float, float, float, float] | None = None,
        inclusion: tuple[float, float, float, float] | None = None,
    ):
        face = Face.of(phantom)  # margin for a tilted face's image and its sideways travel
        margin = (
            12.0 + scanner.depth_mm * abs(np.sin(face.tilt_rad)) + phantom.max_lambda_mm * abs(np.sin(face.travel_rad))
        )
        self.x0 = -scanner.width_mm / 2 - margin
        self.z0 = -1.0
        x1 = scanner.width_mm / 2 + margin
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
        if inclusion is not None and inclusion[3]:  # no draws: the other cases' textures are unchanged
            x_i, z_i, radius_i, echo_i = inclusion
            disc = expit((radius_i - np.hypot(xx - x_i, zz - z_i)) / 0.05)
            strength = strength * (1 + (10 ** (echo_i / 20) - 1) * disc)
        strength = np.where(zz < 0, 0.0, strength)
        self.values = (amplitude * strength).astype(np.float32)
        self.opacity: np.ndarray | None = None
        self.loss_db_per_mm = 0.0
        if shadow is not None:
            x_s, z_s, radius_s, echo_db, loss_db = shadow
            self.opacity = expit((radius_s - np.hypot(xx - x_s, zz - z_s)) / 0.05).astype(np.float32)
            self.values = self.values * (1 + (10 ** (echo_db / 20) - 1) * self.opacity)
            self.loss_db_per_mm = loss_db / (2 * radius_s)
        self.slices: list[tuple[float, np.ndarray]] = [(0.0, self.values)]
        self.sigma_mm = 0.0
        if elevation is not None:
            self.sigma_mm, low, high = elevation
            spacing = self.sigma_mm / 2
            plain = np.where(bright, strength / 4.0, strength)
            for k in range(
                int(np.floor((low - 3 * self.sigma_mm) / spacing)),
                int(np.ceil((high + 3 * self.sigma_mm) / spacing)) + 1,
            ):
                if k == 0:
                    continue
                points = np.where(rng.random((nz, nx)) < 4e-4, 4.0, 1.0)
                layer = np.where(radius < phantom.vessel_radius_mm, 0.02, plain * points)
                self.slices.append((k * spacing, (rng.standard_normal((nz, nx)) * layer).astype(np.float32)))

    def weights(self, elevation_mm: float) -> list[tuple[float, np.ndarray]]:
        """(weight, slice) of the slices a Gaussian elevation beam centred at ``elevation_mm`` sees (sum of squared
        weights 1: the speckle level is kept); the base texture alone without elevation slices."""
        if not self.sigma_mm:
            return [(1.0, self.values)]
        raw = np.array([np.exp(-0.5 * ((y - elevation_mm) / self.sigma_mm) ** 2) for y, _ in self.slices])
        raw /= np.sqrt(np.sum(raw**2))
        return [(float(w), values) for w, (_, values) in zip(raw, self.slices, strict=True) if w > 1e-3]


def _interp_matrix(fine: np.ndarray, coarse: np.ndarray) -> np.ndarray:
    """(len(fine), len(coarse)) linear interpolation weights (clamped at the ends)."""
    return np.stack([np.interp(fine, coarse, column) for column in np.eye(len(coarse))], axis=1)


class Renderer:
    """Renders frames of one case: probe-frame fine grid -> reference texture -> RF -> envelope -> uint8.

    ``face``: the probe face (the image's depth 0 is its centre line, its axes the probe frame's); ``axial_scale``:
    true depth per displayed depth, c_tissue / c_assumed (the scanner converts echo times with 1540 m/s; the pulse
    keeps its displayed length, i.e. it is c_tissue / 1540 as long in the tissue), attenuation on the true depth."""

    def __init__(self, solution: Solution, texture: Texture, scanner: Scanner, face: Face, axial_scale: float = 1.0):
        self.solution, self.texture, self.scanner = solution, texture, scanner
        self.face, self.axial_scale = face, axial_scale
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
        true_cm = depth_cm * axial_scale
        self.attenuation = (10 ** (-2 * s.attenuation_db_cm_mhz * s.frequency_mhz * true_cm / 20)).astype(np.float32)
        self.tgc = (10 ** (s.tgc_db_per_cm * depth_cm / 20)).astype(np.float32)
        # rms of the RF of unit texture through the PSF: the envelope reference (speckle level before gains)
        probe = np.random.default_rng(0).standard_normal((400, 200)).astype(np.float32)
        self.reference = float(np.std(cv2.sepFilter2D(probe, -1, self.lateral, self.axial)[50:-50, 30:-30]))

    def reference_positions(self, lam: float) -> tuple[np.ndarray, np.ndarray]:
        """Reference (x, z) (mm) of the coarse probe-frame grid with the face ``lam`` mm past first contact, by fixed
        point."""
        sol = self.solution
        field = sol.displacement_at(lam)
        ux = RegularGridInterpolator((sol.z_nodes, sol.x_nodes), field[..., 0], bounds_error=False, fill_value=None)
        uz = RegularGridInterpolator((sol.z_nodes, sol.x_nodes), field[..., 1], bounds_error=False, fill_value=None)
        zz, xx = np.meshgrid(self.zc * self.axial_scale, self.xc, indexing="ij")
        centre = self.face.centre(lam)
        e_x, e_z = self.face.axes()
        x_def = (centre[0] + xx * e_x[0] + zz * e_z[0]).ravel()
        z_def = (centre[1] + xx * e_x[1] + zz * e_z[1]).ravel()
        x_ref, z_ref = x_def.copy(), z_def.copy()
        for _ in range(12):
            points = np.column_stack([np.clip(z_ref, sol.z_nodes[0], sol.z_nodes[-1]), x_ref])
            x_new, z_new = x_def - ux(points), z_def - uz(points)
            change = max(np.abs(x_new - x_ref).max(), np.abs(z_new - z_ref).max())
            x_ref, z_ref = x_new, z_new
            if change < 1e-4:
                break
        return x_ref.reshape(zz.shape), z_ref.reshape(zz.shape)

    def render(
        self, lam: float, rng: np.random.Generator, gain_db: float = 0.0, elevation_mm: float = 0.0
    ) -> np.ndarray:
        """(rows, cols) uint8 frame with the face ``lam`` mm past first contact; ``rng`` draws jitter and noise;
        ``gain_db`` adds to the scanner's gain; ``elevation_mm`` is the beam's position in the elevation slices."""
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
        reflectivity = sum(
            weight * cv2.remap(values, map_x, map_y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT)
            for weight, values in t.weights(elevation_mm)
        )
        echo = cv2.sepFilter2D(reflectivity, -1, self.lateral, self.axial, borderType=cv2.BORDER_CONSTANT)
        rf: np.ndarray = np.asarray(echo, dtype=np.float32) * (self.attenuation / self.reference)
        if t.opacity is not None:  # loss below an opaque object, two-way, along each scan line
            opacity = cv2.remap(t.opacity, map_x, map_y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT)
            rf = rf * 10 ** (-np.cumsum(opacity, axis=0) * (t.loss_db_per_mm * self.dzf) / 20)
        white = rng.standard_normal(rf.shape).astype(np.float32)  # receiver noise, band-limited by the pulse
        band = cv2.sepFilter2D(white, -1, np.ones(1, np.float32), self.axial, borderType=cv2.BORDER_REFLECT)
        noise: np.ndarray = np.asarray(band, dtype=np.float32)
        noise = noise * (10 ** (s.noise_db / 20) / max(float(noise.std()), 1e-12))
        rf = (rf + noise) * self.tgc
        envelope = np.abs(hilbert(rf, axis=0)).astype(np.float32)
        level = 20 * np.log10(envelope + 1e-6) + (s.gain_db + gain_db)
        grey = np.clip((level + s.dynamic_range_db) / s.dynamic_range_db, 0, 1) * 255
        pixels = cv2.resize(grey.astype(np.float32), (s.cols, s.rows), interpolation=cv2.INTER_AREA)
        return np.clip(np.rint(pixels), 0, 255).astype(np.uint8)
