"""A pre-/post-compression pair of B-mode frames made from simulated RF, the way a scanner makes them.

Written apart from the simulator's image formation (:mod:`usdeform.sim.imaging`) to judge the tracker
on speckle made as real B-mode speckle is: point scatterers (Gaussian amplitudes, many per resolution
cell, a few bright fibre-like structures) imaged as RF A-lines by a Gaussian-modulated sinusoid pulse
(two-way spectrum Gaussian around the centre frequency, -6 dB fractional bandwidth) and a Gaussian
lateral beam profile that narrows at the transmit focus; frequency-dependent attenuation (which also
shifts the spectrum down with depth); additive band-limited electronic noise drawn anew for each frame
before a time-gain compensation that makes up only part of the loss, so the deep speckle is dim and
noisy; envelope by Hilbert transform, log compression to uint8 and resampling to the pixel grid.

The second frame images the same scatterers moved by one compression step (:class:`CompressionMotion`):
axial strain, optionally varying with depth and lower in a stiffer inclusion, and a lateral spread from
the probe centre that keeps the section incompressible (plane strain). The point-spread function does
not deform with the tissue, so the speckle decorrelates as it does on a real scanner.

Coordinates: ``x`` lateral from the probe centre, ``z`` depth from the probe face, mm; image column
``c`` is centred at ``x = (c - (cols - 1) / 2) * pixel_mm[1]``, row ``r`` at ``z = (r + 0.5) * pixel_mm[0]``.
Compression moves the tissue towards the probe: the axial displacement is negative (up in the image).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy.ndimage import map_coordinates, uniform_filter1d
from scipy.signal import hilbert
from scipy.special import erf

from ..errors import InputError

__all__ = [
    "SOUND_SPEED_MM_US",
    "CompressionMotion",
    "RfCompressionPair",
    "b_mode_from_rf",
    "rf_compression_pair",
]

SOUND_SPEED_MM_US = 1.54
"""Speed of sound, mm per microsecond (1540 m/s)."""

_FWHM_PER_SIGMA = 2.0 * math.sqrt(2.0 * math.log(2.0))
_NODE_SPACING_MM = 2.0  # depth nodes between which the attenuated pulse spectrum is interpolated
_FINE_FACTOR = 4  # scatterers are placed on a grid this many times finer than the RF samples


@dataclass(frozen=True)
class CompressionMotion:
    """One compression step: the displacement of every tissue point of the first frame, mm.

    The local axial strain (positive = compression) is
    ``strain * (1 + strain_depth_gradient * (z / depth_mm - 1/2)) - strain * inclusion_contrast * G(x, z)``
    with ``G`` a Gaussian bump of standard deviation ``inclusion_radius_mm`` at ``inclusion_centre_mm``
    (x, z); a stiffer inclusion has ``inclusion_contrast`` in (0, 1). The tissue at the probe face does
    not move axially; deeper tissue moves towards the probe by the strain integrated over depth. The
    lateral displacement is ``lateral_ratio`` times the same strain integrated from the probe centre, so
    that ``lateral_ratio = 1`` keeps every area (plane strain, incompressible).
    """

    strain: float
    depth_mm: float
    lateral_ratio: float = 1.0
    strain_depth_gradient: float = 0.0
    inclusion_contrast: float = 0.0
    inclusion_radius_mm: float = 3.0
    inclusion_centre_mm: tuple[float, float] = (0.0, 15.0)

    def axial_strain(self, x_mm: np.ndarray, z_mm: np.ndarray) -> np.ndarray:
        """Local axial strain (dimensionless, compression positive) at (x, z) mm."""
        x, z = np.asarray(x_mm, dtype=np.float64), np.asarray(z_mm, dtype=np.float64)
        xi, zi = self.inclusion_centre_mm
        bump = np.exp(-((x - xi) ** 2 + (z - zi) ** 2) / (2.0 * self.inclusion_radius_mm**2))
        return self.strain * (
            1.0 + self.strain_depth_gradient * (z / self.depth_mm - 0.5) - self.inclusion_contrast * bump
        )

    def displacement_mm(self, x_mm: np.ndarray, z_mm: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(dx, dz) mm of the tissue point at (x, z) mm of the first frame; dz < 0 is towards the probe."""
        x, z = np.asarray(x_mm, dtype=np.float64), np.asarray(z_mm, dtype=np.float64)
        depth, gradient, radius = self.depth_mm, self.strain_depth_gradient, self.inclusion_radius_mm
        xi, zi = self.inclusion_centre_mm
        scale = radius * math.sqrt(math.pi / 2.0)
        root2r = radius * math.sqrt(2.0)
        smooth_z = z + gradient * (z**2 / (2.0 * depth) - z / 2.0)  # integral of the smooth strain over depth
        bump_x = np.exp(-((x - xi) ** 2) / (2.0 * radius**2))
        bump_z = np.exp(-((z - zi) ** 2) / (2.0 * radius**2))
        integral_z = scale * (erf((z - zi) / root2r) - erf(-zi / root2r))
        integral_x = scale * (erf((x - xi) / root2r) - erf(-xi / root2r))
        dz = -self.strain * (smooth_z - self.inclusion_contrast * bump_x * integral_z)
        smooth_strain = 1.0 + gradient * (z / depth - 0.5)
        dx = self.lateral_ratio * self.strain * (smooth_strain * x - self.inclusion_contrast * bump_z * integral_x)
        return dx, dz


@dataclass(frozen=True, eq=False)
class RfCompressionPair:
    """Two B-mode frames made from simulated RF, their RF and the true motion between them.

    Attributes:
        pre, post: (rows, cols) uint8 B-mode frames before and after the compression step.
        displacement_px: (rows, cols, 2) float64 true displacement (dx lateral, dy axial), pixels, of the
            tissue shown at each pixel of ``pre`` into ``post`` (forward mapping; dy < 0 towards the probe).
        pixel_mm: (axial, lateral) pixel size, mm.
        rf_pre, rf_post: (samples, lines) float32 beamformed RF after time-gain compensation (arbitrary
            units: the unattenuated speckle at the focus has rms 1); sample ``m`` is at depth
            ``m * rf_sample_mm``.
        rf_sample_mm: depth step of the RF samples, mm.
        line_x_mm: (lines,) lateral position of each A-line, mm from the probe centre.
        tgc_db: (samples,) the time-gain compensation applied to the RF, dB.
        noise_floor_db: rms of the electronic noise before TGC, dB re the speckle rms at the focus.
        white_level_db, dynamic_range_db: the log compression (levels in dB re the speckle rms at the focus).
        motion: the compression step.
        centre_frequency_mhz, fractional_bandwidth, attenuation_db_cm_mhz: the pulse and the tissue.
    """

    pre: np.ndarray
    post: np.ndarray
    displacement_px: np.ndarray
    pixel_mm: tuple[float, float]
    rf_pre: np.ndarray
    rf_post: np.ndarray
    rf_sample_mm: float
    line_x_mm: np.ndarray
    tgc_db: np.ndarray
    noise_floor_db: float
    white_level_db: float
    dynamic_range_db: float
    motion: CompressionMotion
    centre_frequency_mhz: float
    fractional_bandwidth: float
    attenuation_db_cm_mhz: float

    @property
    def frames(self) -> np.ndarray:
        """(2, rows, cols) uint8: ``pre`` and ``post`` stacked as a two-frame palpation."""
        return np.stack([self.pre, self.post])

    @property
    def noise_grey(self) -> np.ndarray:
        """(rows,) mean grey level the electronic noise alone would show on each row (its log envelope,
        after TGC): texture darker than this is not tissue."""
        depth = (np.arange(self.pre.shape[0]) + 0.5) * self.pixel_mm[0]
        tgc = np.interp(depth, self.rf_depth_mm, self.tgc_db)
        # the envelope of band-limited Gaussian noise is Rayleigh: mean power twice the RF's, mean log -2.51 dB
        level = self.noise_floor_db + tgc + 10.0 * math.log10(2.0) - 2.51
        return 255.0 * (level - (self.white_level_db - self.dynamic_range_db)) / self.dynamic_range_db

    @property
    def rf_depth_mm(self) -> np.ndarray:
        """(samples,) depth of each RF sample, mm."""
        return np.arange(self.rf_pre.shape[0]) * self.rf_sample_mm


def _check(condition: bool, name: str, expected: str, value: object) -> None:
    if not condition:
        raise InputError(f"{name}: expected {expected}, got {value!r}")


def _finite(value: object) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)


def rf_compression_pair(
    *,
    strain: float = 0.05,
    lateral_ratio: float = 1.0,
    strain_depth_gradient: float = 0.0,
    inclusion_contrast: float = 0.0,
    inclusion_radius_mm: float = 3.0,
    inclusion_centre_mm: tuple[float, float] = (0.0, 15.0),
    rows: int = 456,
    cols: int = 256,
    pixel_mm: tuple[float, float] = (0.077, 0.0745),
    line_pitch_mm: float = 0.149,
    centre_frequency_mhz: float = 7.5,
    fractional_bandwidth: float = 0.5,
    rf_sampling_mhz: float = 40.0,
    lateral_fwhm_mm: float = 0.5,
    focus_depth_mm: float = 20.0,
    focal_zone_mm: float = 10.0,
    elevation_focus_mm: float = 15.0,
    elevation_zone_mm: float = 5.0,
    attenuation_db_cm_mhz: float = 0.7,
    tgc_fraction: float = 0.1,
    noise_db: float = -40.0,
    dynamic_range_db: float = 50.0,
    white_level_db: float = -3.0,
    scatterers_per_mm2: float = 80.0,
    n_bright_structures: int = 3,
    out_of_plane_decorrelation: float = 0.0,
    seed: int = 0,
) -> RfCompressionPair:
    """A pre-/post-compression pair of B-mode frames made from simulated RF, with the true motion.

    The defaults put the frames in the regime of a real phantom pair (5 % axial strain in one step,
    0.077 x 0.0745 mm pixels, 456 x 256 pixels = 35.1 mm deep, so the bottom moves 23 pixels, 1.8 mm;
    mean grey about 180 at mid-depth falling to about 100 at the bottom, where the echo sinks to the level of
    the electronic noise). The real pair falls further, to 55: attenuation within 0.5-0.7 dB/cm/MHz at
    5-7.5 MHz (with its spectral downshift) does not darken 35 mm of speckle more than this.

    Parameters (keyword only)
    ----------
    strain : axial compression strain of the step (dimensionless), in (0, 0.2].
    lateral_ratio : lateral spread per unit axial strain, in [0, 1.5] (1 = incompressible, plane strain).
    strain_depth_gradient : strain at the bottom minus at the top, relative to ``strain``, in (-1, 1).
    inclusion_contrast, inclusion_radius_mm, inclusion_centre_mm : a stiffer inclusion (strain lowered by
        the contrast, in [0, 1), at its centre (x, z) mm, Gaussian radius mm); contrast 0 leaves none.
    rows, cols : frame size, pixels (>= 16).
    pixel_mm : (axial, lateral) pixel size, mm.
    line_pitch_mm : lateral spacing of the RF A-lines, mm (the B-mode interpolates between lines).
    centre_frequency_mhz : pulse centre frequency, MHz, in [1, 20].
    fractional_bandwidth : -6 dB bandwidth of the pulse-echo spectrum over the centre frequency, in [0.2, 1.2].
    rf_sampling_mhz : RF sampling rate, MHz (at least 2.5 times the centre frequency).
    lateral_fwhm_mm, focus_depth_mm, focal_zone_mm : two-way lateral beam width (FWHM) at the focus, mm;
        focus depth, mm; depth from the focus at which the width has grown by sqrt(2), mm.
    elevation_focus_mm, elevation_zone_mm : the same for the elevation (slice) beam of the probe's lens: the
        echo power of the speckle falls as the slice widens beyond its focus (and before it).
    attenuation_db_cm_mhz : attenuation, dB/cm/MHz (one way; the echo travels twice), in [0, 2].
    tgc_fraction : fraction of the centre-frequency attenuation the time-gain compensation restores, [0, 1.5].
    noise_db : rms of the electronic noise (added before TGC), dB re the unattenuated speckle rms at the focus.
    dynamic_range_db : log-compression range shown from black to white, dB.
    white_level_db : echo level shown white, dB re the unattenuated speckle rms at the focus.
    scatterers_per_mm2 : scatterer density in the imaged plane, per mm^2 (tens per resolution cell).
    n_bright_structures : number of bright fibre-like segments (strong scatterers) in the tissue, >= 0.
    out_of_plane_decorrelation : fraction, in [0, 1), of each scatterer's amplitude replaced anew in the
        second frame (elevational motion out of the imaged plane); 0 leaves the scatterers unchanged.
    seed : seed of the numpy Generator (scatterers, noise).
    """
    _check(_finite(strain) and 0.0 < strain <= 0.2, "strain", "a number in (0, 0.2]", strain)
    _check(
        _finite(lateral_ratio) and 0.0 <= lateral_ratio <= 1.5, "lateral_ratio", "a number in [0, 1.5]", lateral_ratio
    )
    _check(
        _finite(strain_depth_gradient) and abs(strain_depth_gradient) < 1.0,
        "strain_depth_gradient",
        "a number in (-1, 1)",
        strain_depth_gradient,
    )
    _check(
        _finite(inclusion_contrast) and 0.0 <= inclusion_contrast < 1.0,
        "inclusion_contrast",
        "a number in [0, 1)",
        inclusion_contrast,
    )
    _check(
        _finite(inclusion_radius_mm) and inclusion_radius_mm > 0,
        "inclusion_radius_mm",
        "a positive mm",
        inclusion_radius_mm,
    )
    _check(
        len(inclusion_centre_mm) == 2 and all(_finite(float(v)) for v in inclusion_centre_mm),
        "inclusion_centre_mm",
        "two finite numbers (x, z) mm",
        inclusion_centre_mm,
    )
    for name, count in (("rows", rows), ("cols", cols)):
        _check(isinstance(count, (int, np.integer)) and 16 <= count <= 4096, name, "an integer in [16, 4096]", count)
    _check(
        len(pixel_mm) == 2 and all(_finite(float(v)) and 0.005 <= v <= 2.0 for v in pixel_mm),
        "pixel_mm",
        "(axial, lateral) sizes in [0.005, 2] mm",
        pixel_mm,
    )
    _check(
        _finite(line_pitch_mm) and 0.01 <= line_pitch_mm <= 2.0,
        "line_pitch_mm",
        "a size in [0.01, 2] mm",
        line_pitch_mm,
    )
    _check(
        _finite(centre_frequency_mhz) and 1.0 <= centre_frequency_mhz <= 20.0,
        "centre_frequency_mhz",
        "a frequency in [1, 20] MHz",
        centre_frequency_mhz,
    )
    _check(
        _finite(fractional_bandwidth) and 0.2 <= fractional_bandwidth <= 1.2,
        "fractional_bandwidth",
        "a number in [0.2, 1.2]",
        fractional_bandwidth,
    )
    _check(
        _finite(rf_sampling_mhz) and 2.5 * centre_frequency_mhz <= rf_sampling_mhz <= 400.0,
        "rf_sampling_mhz",
        "a rate in [2.5 x centre frequency, 400] MHz",
        rf_sampling_mhz,
    )
    for name, size in (
        ("lateral_fwhm_mm", lateral_fwhm_mm),
        ("focal_zone_mm", focal_zone_mm),
        ("elevation_zone_mm", elevation_zone_mm),
    ):
        _check(_finite(size) and size > 0, name, "a positive size in mm", size)
    for name, size in (("focus_depth_mm", focus_depth_mm), ("elevation_focus_mm", elevation_focus_mm)):
        _check(_finite(size) and size >= 0, name, "a depth >= 0 mm", size)
    _check(
        _finite(attenuation_db_cm_mhz) and 0.0 <= attenuation_db_cm_mhz <= 2.0,
        "attenuation_db_cm_mhz",
        "a number in [0, 2] dB/cm/MHz",
        attenuation_db_cm_mhz,
    )
    _check(_finite(tgc_fraction) and 0.0 <= tgc_fraction <= 1.5, "tgc_fraction", "a number in [0, 1.5]", tgc_fraction)
    _check(_finite(noise_db) and -120.0 <= noise_db <= 20.0, "noise_db", "a level in [-120, 20] dB", noise_db)
    _check(
        _finite(dynamic_range_db) and 10.0 <= dynamic_range_db <= 120.0,
        "dynamic_range_db",
        "a range in [10, 120] dB",
        dynamic_range_db,
    )
    _check(
        _finite(white_level_db) and abs(white_level_db) <= 60.0,
        "white_level_db",
        "a level in [-60, 60] dB",
        white_level_db,
    )
    _check(
        _finite(scatterers_per_mm2) and 1.0 <= scatterers_per_mm2 <= 2000.0,
        "scatterers_per_mm2",
        "a density in [1, 2000] per mm^2",
        scatterers_per_mm2,
    )
    _check(
        isinstance(n_bright_structures, (int, np.integer)) and 0 <= n_bright_structures <= 100,
        "n_bright_structures",
        "an integer in [0, 100]",
        n_bright_structures,
    )
    _check(
        _finite(out_of_plane_decorrelation) and 0.0 <= out_of_plane_decorrelation < 1.0,
        "out_of_plane_decorrelation",
        "a number in [0, 1)",
        out_of_plane_decorrelation,
    )
    _check(isinstance(seed, (int, np.integer)) and seed >= 0, "seed", "a non-negative integer", seed)

    rng = np.random.default_rng(int(seed))
    pixel_axial, pixel_lateral = float(pixel_mm[0]), float(pixel_mm[1])
    depth_mm = rows * pixel_axial
    half_width = (cols - 1) / 2.0 * pixel_lateral
    motion = CompressionMotion(
        strain=float(strain),
        depth_mm=depth_mm,
        lateral_ratio=float(lateral_ratio),
        strain_depth_gradient=float(strain_depth_gradient),
        inclusion_contrast=float(inclusion_contrast),
        inclusion_radius_mm=float(inclusion_radius_mm),
        inclusion_centre_mm=(float(inclusion_centre_mm[0]), float(inclusion_centre_mm[1])),
    )
    beam = _Beam(
        centre_frequency_mhz,
        fractional_bandwidth,
        rf_sampling_mhz,
        (lateral_fwhm_mm, focus_depth_mm, focal_zone_mm),
        (elevation_focus_mm, elevation_zone_mm),
    )

    # A-lines covering the image columns, one beyond each edge so every column lies between two lines.
    n_half = math.ceil(half_width / line_pitch_mm) + 1
    line_x = np.arange(-n_half, n_half + 1) * line_pitch_mm
    rf_sample_mm = SOUND_SPEED_MM_US / (2.0 * rf_sampling_mhz)
    n_samples = 2 * math.ceil((depth_mm + 2 * pixel_axial) / rf_sample_mm / 2)

    # Scatterers of the first frame, reaching below the image by the largest step and a pulse length.
    max_step = strain * (1.0 + abs(strain_depth_gradient)) * depth_mm
    reach_x = half_width + line_pitch_mm + 3.0 * beam.sigma_mm(0.0).max() + lateral_ratio * max_step
    reach_z = depth_mm + max_step + 2.0
    count = rng.poisson(scatterers_per_mm2 * 2 * reach_x * reach_z)
    x = rng.uniform(-reach_x, reach_x, count)
    z = rng.uniform(0.0, reach_z, count)
    amplitude = rng.standard_normal(count)
    bright = [_bright_structure(rng, reach_x, depth_mm) for _ in range(n_bright_structures)]
    if bright:
        x = np.concatenate([x, *(b[0] for b in bright)])
        z = np.concatenate([z, *(b[1] for b in bright)])
        amplitude = np.concatenate([amplitude, *(b[2] for b in bright)])

    dx, dz = motion.displacement_mm(x, z)
    post_amplitude = amplitude
    if out_of_plane_decorrelation > 0:
        kept = math.sqrt(1.0 - out_of_plane_decorrelation**2)
        post_amplitude = kept * amplitude + out_of_plane_decorrelation * rng.standard_normal(amplitude.size)

    depth = np.arange(n_samples) * rf_sample_mm
    tgc_db = tgc_fraction * attenuation_db_cm_mhz * centre_frequency_mhz * depth / 5.0
    reference_rms = beam.speckle_rms(scatterers_per_mm2, rf_sample_mm)
    noise_rms = 10.0 ** (noise_db / 20.0)
    images, rfs = [], []
    for sx, sz, sa in ((x, z, amplitude), (x + dx, z + dz, post_amplitude)):
        rf = beam.rf_lines(sx, sz, sa, line_x, n_samples, attenuation_db_cm_mhz) / reference_rms
        rf += noise_rms * beam.band_limited_noise(rng, rf.shape)
        rf *= 10.0 ** (tgc_db[:, None] / 20.0)
        rfs.append(rf.astype(np.float32))
        shape, pixel = (rows, cols), (pixel_axial, pixel_lateral)
        images.append(
            b_mode_from_rf(
                rf, rf_sample_mm, line_x, shape, pixel, dynamic_range_db=dynamic_range_db, white_level_db=white_level_db
            )
        )

    col_x = (np.arange(cols) - (cols - 1) / 2.0) * pixel_lateral
    row_z = (np.arange(rows) + 0.5) * pixel_axial
    grid_x, grid_z = np.meshgrid(col_x, row_z)
    true_dx, true_dz = motion.displacement_mm(grid_x, grid_z)
    displacement_px = np.stack([true_dx / pixel_lateral, true_dz / pixel_axial], axis=-1)
    return RfCompressionPair(
        pre=images[0],
        post=images[1],
        displacement_px=displacement_px,
        pixel_mm=(pixel_axial, pixel_lateral),
        rf_pre=rfs[0],
        rf_post=rfs[1],
        rf_sample_mm=rf_sample_mm,
        line_x_mm=line_x,
        tgc_db=tgc_db,
        noise_floor_db=float(noise_db),
        white_level_db=float(white_level_db),
        dynamic_range_db=float(dynamic_range_db),
        motion=motion,
        centre_frequency_mhz=float(centre_frequency_mhz),
        fractional_bandwidth=float(fractional_bandwidth),
        attenuation_db_cm_mhz=float(attenuation_db_cm_mhz),
    )


def _bright_structure(rng: np.random.Generator, reach_x: float, depth_mm: float) -> tuple[np.ndarray, ...]:
    """A bright fibre: strong scatterers along a short, slightly sloped segment (x, z, amplitude)."""
    length = rng.uniform(2.0, 6.0)
    angle = rng.uniform(-0.25, 0.25)
    centre_x = rng.uniform(-0.8 * reach_x, 0.8 * reach_x)
    centre_z = rng.uniform(0.1, 0.9) * depth_mm
    along = rng.uniform(-length / 2, length / 2, max(int(length / 0.03), 2))
    x = centre_x + along * math.cos(angle)
    z = centre_z + along * math.sin(angle) + rng.normal(0.0, 0.03, along.size)
    return x, z, 3.0 * rng.standard_normal(along.size)


class _Beam:
    """The pulse-echo point-spread function: a Gaussian lateral profile times an RF pulse."""

    def __init__(
        self,
        centre_frequency_mhz: float,
        fractional_bandwidth: float,
        rf_sampling_mhz: float,
        lateral: tuple[float, float, float],
        elevation: tuple[float, float],
    ):
        self.f0, self.fs = centre_frequency_mhz, rf_sampling_mhz
        # Two-way amplitude spectrum exp(-(f - f0)^2 / (2 sigma_f^2)), -6 dB at f0 +- bandwidth/2.
        self.sigma_f = fractional_bandwidth * centre_frequency_mhz / (2.0 * math.sqrt(2.0 * math.log(2.0)))
        self.fwhm, self.focus, self.zone = lateral  # FWHM at the focus, focus depth, focal zone (mm)
        self.elevation_focus, self.elevation_zone = elevation

    def width_mm(self, z_mm: np.ndarray | float) -> np.ndarray:
        """Two-way lateral FWHM at depth z, mm."""
        return self.fwhm * np.sqrt(1.0 + ((np.asarray(z_mm, dtype=np.float64) - self.focus) / self.zone) ** 2)

    def sigma_mm(self, z_mm: np.ndarray | float) -> np.ndarray:
        return self.width_mm(z_mm) / _FWHM_PER_SIGMA

    def amplitude(self, z_mm: np.ndarray) -> np.ndarray:
        """Peak two-way amplitude at depth z relative to the foci: a beam (in plane or in elevation) that is
        wider spreads the same energy thinner, so the mean speckle power goes as 1 / (width x slice width)."""
        slice_growth = np.sqrt(1.0 + ((z_mm - self.elevation_focus) / self.elevation_zone) ** 2)
        return self.fwhm / self.width_mm(z_mm) / np.sqrt(slice_growth)

    def spectrum(self, n_fine: int, depth_mm: float, attenuation_db_cm_mhz: float) -> np.ndarray:
        """The pulse-echo spectrum at the rfft bins of the RF rate, attenuated over the round trip to depth."""
        n_bins = n_fine // (2 * _FINE_FACTOR) + 1
        f = np.arange(n_bins) * (self.fs * _FINE_FACTOR / n_fine)
        loss_db = attenuation_db_cm_mhz * f * depth_mm / 5.0  # two-way path 2 * depth, in cm
        return np.exp(-((f - self.f0) ** 2) / (2.0 * self.sigma_f**2)) * 10.0 ** (-loss_db / 20.0)

    def rf_lines(
        self,
        x: np.ndarray,
        z: np.ndarray,
        amplitude: np.ndarray,
        line_x: np.ndarray,
        n_samples: int,
        attenuation_db_cm_mhz: float,
    ) -> np.ndarray:
        """(n_samples, lines) RF of point scatterers at (x, z) mm with the given amplitudes.

        Each scatterer is placed at its exact depth on a grid four times finer than the RF samples
        (linear split between neighbours), weighted by the lateral beam profile of every line it reaches
        and by the depth nodes of the attenuated spectrum (hat functions); each node's impulse trains are
        filtered by its spectrum in the frequency domain and decimated to the RF rate without aliasing.
        """
        n_lines, pitch = line_x.size, float(line_x[1] - line_x[0])
        n_fine = n_samples * _FINE_FACTOR
        fine_mm = SOUND_SPEED_MM_US / (2.0 * self.fs * _FINE_FACTOR)
        keep = (z >= 0) & (z < (n_fine - 2) * fine_mm)
        x, z, amplitude = x[keep], z[keep], amplitude[keep]
        sigma = self.sigma_mm(z)
        gain = self.amplitude(z)
        reach = math.ceil(3.0 * float(sigma.max()) / pitch) + 1
        nearest = np.rint((x - line_x[0]) / pitch).astype(np.int64)
        position = z / fine_mm
        sample = np.floor(position).astype(np.int64)
        frac = position - sample
        node_position = z / _NODE_SPACING_MM
        node = np.floor(node_position).astype(np.int64)
        node_frac = node_position - node
        rf = np.zeros((n_lines, n_samples))
        for k in range(int(node.max()) + 2):
            lower, upper = node == k, node == k - 1  # hat weight (1 - frac) from below, frac from above
            chosen = lower | upper
            if not chosen.any():
                continue
            hat = np.where(lower, 1.0 - node_frac, node_frac)[chosen]
            weight = (amplitude * gain)[chosen] * hat
            s, f, n, xs, sg = sample[chosen], frac[chosen], nearest[chosen], x[chosen], sigma[chosen]
            flats, weights = [], []
            for offset in range(-reach, reach + 1):
                line = n + offset
                inside = (line >= 0) & (line < n_lines)
                lateral = np.exp(-0.5 * ((xs[inside] - line_x[line[inside]]) / sg[inside]) ** 2)
                w = weight[inside] * lateral
                flat = line[inside] * n_fine + s[inside]
                flats += [flat, flat + 1]
                weights += [w * (1.0 - f[inside]), w * f[inside]]
            train = np.bincount(np.concatenate(flats), np.concatenate(weights), minlength=n_lines * n_fine)
            spectrum = np.fft.rfft(train.reshape(n_lines, n_fine), axis=1)[:, : n_fine // (2 * _FINE_FACTOR) + 1]
            filtered = spectrum * self.spectrum(n_fine, k * _NODE_SPACING_MM, attenuation_db_cm_mhz)
            rf += np.fft.irfft(filtered, n=n_samples, axis=1) * (n_samples / n_fine)
        return rf.T

    def speckle_rms(self, scatterers_per_mm2: float, rf_sample_mm: float) -> float:
        """Expected rms of the unattenuated RF speckle of unit-variance scatterers at the focus."""
        n_samples = 256
        n_fine = n_samples * _FINE_FACTOR
        impulse = np.zeros(n_fine)
        impulse[n_fine // 2] = 1.0
        spectrum = np.fft.rfft(impulse)[: n_fine // (2 * _FINE_FACTOR) + 1] * self.spectrum(n_fine, 0.0, 0.0)
        pulse = np.fft.irfft(spectrum, n=n_samples) * (n_samples / n_fine)
        lateral_integral = float(self.sigma_mm(self.focus)) * math.sqrt(math.pi)  # integral of exp(-x^2/sigma^2)
        return math.sqrt(scatterers_per_mm2 * lateral_integral * float(np.sum(pulse**2)) * rf_sample_mm)

    def band_limited_noise(self, rng: np.random.Generator, shape: tuple[int, ...]) -> np.ndarray:
        """Unit-rms Gaussian noise (samples, lines) in the transducer's band (the unattenuated pulse spectrum)."""
        n_samples = shape[0]
        white = np.fft.rfft(rng.standard_normal(shape), axis=0)
        f = np.arange(white.shape[0]) * (self.fs / n_samples)
        band = np.exp(-((f - self.f0) ** 2) / (2.0 * self.sigma_f**2))
        noise = np.fft.irfft(white * band[:, None], n=n_samples, axis=0)
        return noise / noise.std()


def b_mode_from_rf(
    rf: np.ndarray,
    rf_sample_mm: float,
    line_x_mm: np.ndarray,
    shape: tuple[int, int],
    pixel_mm: tuple[float, float],
    *,
    dynamic_range_db: float = 50.0,
    white_level_db: float = 0.0,
) -> np.ndarray:
    """uint8 (rows, cols) B-mode of RF A-lines (samples, lines): Hilbert envelope, log compression and
    resampling to a pixel grid.

    RF sample ``m`` lies at depth ``m * rf_sample_mm``; line ``l`` at ``line_x_mm[l]`` (mm, evenly spaced);
    pixel (r, c) at depth ``(r + 0.5) * pixel_mm[0]`` and lateral ``(c - (cols - 1) / 2) * pixel_mm[1]``.
    The log envelope (dB re an RF amplitude of 1) is averaged along depth over a pixel height, then
    interpolated linearly to the pixel centres (between lines laterally); ``white_level_db`` is shown as
    255 and ``white_level_db - dynamic_range_db`` as 0.
    """
    rows, cols = shape
    envelope = np.abs(hilbert(np.asarray(rf, dtype=np.float64), axis=0))
    level_db = 20.0 * np.log10(envelope + 1e-12)
    per_pixel = max(round(pixel_mm[0] / rf_sample_mm), 1)
    level_db = uniform_filter1d(level_db, per_pixel, axis=0, mode="nearest")
    row_sample = (np.arange(rows) + 0.5) * pixel_mm[0] / rf_sample_mm
    pitch = float(line_x_mm[1] - line_x_mm[0])
    col_line = ((np.arange(cols) - (cols - 1) / 2.0) * pixel_mm[1] - float(line_x_mm[0])) / pitch
    coords = np.meshgrid(row_sample, col_line, indexing="ij")
    resampled = map_coordinates(level_db, coords, order=1, mode="nearest")
    grey = 255.0 * (resampled - (white_level_db - dynamic_range_db)) / dynamic_range_db
    return np.clip(np.rint(grey), 0, 255).astype(np.uint8)
