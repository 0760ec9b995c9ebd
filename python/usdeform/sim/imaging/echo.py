"""B-mode image formation: the complex echo of the deformed tissue's scatterers, attenuation,
time-gain compensation, electronic noise and log compression.

For a frame, each scatterer (:class:`~usdeform.sim.imaging.ScattererField`) is moved by the
finite-element displacement of its section and imaged with a separable Gaussian point-spread
function (two-way amplitude, FWHM = the axial / lateral / elevation resolution). The echo is formed
as the complex (IQ-demodulated) sum ``sum_k a_k g(r - r_k) exp(-2 i k0 d_k)``, ``d_k`` the scatterer's
depth below the probe face and ``k0`` the wavenumber at the centre frequency, whose magnitude is
the envelope. Interference therefore depends on the scatterers' sub-wavelength positions exactly
as for an RF pulse followed by envelope detection, so the speckle moves with the tissue (and
decorrelates under strain and out-of-plane motion as real speckle does). For speed the complex
weights are splatted bilinearly onto a grid ``oversampling`` times finer than the pixels,
blurred with the separable Gaussian PSF (OpenCV) and sampled at the pixel positions; 3x
oversampling matches the exact per-scatterer sum to a correlation of 0.999. The electronic noise is
drawn anew for every frame.

Echogenicity: blood in the lumen is anechoic (no scatterers), the vessel wall (a ring of
``wall_thickness_mm`` outside the lumen in the reference section) echoes ``wall_echo_db`` brighter.
Round-trip attenuation ``2 * alpha * f * depth`` (alpha in dB/cm/MHz) is partly undone by a linear
time-gain compensation; complex Gaussian electronic noise sets the floor; the envelope is
log-compressed over ``dynamic_range_db`` to uint8.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import cv2
import numpy as np

from ... import _core
from ...errors import InputError
from .geometry import ProbeState, section_to_surface, surface_to_image, tissue_reach
from .scatterers import ScattererField, scatterer_jitter_mm
from .settings import ImagingSettings, TissueAcoustics

__all__ = ["b_mode", "echo_signal", "render_frame", "unit_complex_noise"]

_FWHM_TO_SIGMA = 1.0 / (2.0 * np.sqrt(2.0 * np.log(2.0)))
_ELEVATION_WINDOW_FWHM = 1.0  # scatterers beyond one elevation FWHM echo < 6 % (amplitude) and are skipped
_REFLECTOR_SPACING_MM = 0.05  # points of the reference reflector's line


def _echo_level(section: Any, points_xz_mm: np.ndarray, acoustics: TissueAcoustics) -> np.ndarray:
    """Echo amplitude factor (m,) of reference points: 0 outside the tissue and in the lumen, the wall
    level on the wall ring, 1 elsewhere."""
    x, z = points_xz_mm[:, 0], points_xz_mm[:, 1]
    lumens = section.lumens  # (n_vessels, 4): centre x, centre depth, radius, ratio
    beyond_wall = np.min(np.hypot(x[:, None] - lumens[:, 0], z[:, None] - lumens[:, 1]) - lumens[:, 2], axis=1)
    level = np.where(beyond_wall < acoustics.wall_thickness_mm, 10 ** (acoustics.wall_echo_db / 20), 1.0)
    tissue = (beyond_wall >= 0) & (z <= section.depth_mm) & (np.abs(x) <= section.width_mm / 2)
    return np.where(tissue, level, 0.0)


def _reference_reflector(
    probe: ProbeState, settings: ImagingSettings, acoustics: TissueAcoustics
) -> tuple[np.ndarray, np.ndarray]:
    """Surface points (m, 3) and echo amplitudes (m,) of the flat reflector fixed in the world at
    ``acoustics.reference_depth_mm`` below the unloaded surface, in the imaged plane: a row of points
    ``_REFLECTOR_SPACING_MM`` apart (far below the lateral resolution: a continuous specular line) whose echo is
    ``reference_echo_db`` above the tissue's rms speckle."""
    assert acoustics.reference_depth_mm is not None
    half_width, _ = tissue_reach(probe, settings)
    x = np.arange(-half_width, half_width + 1e-9, _REFLECTOR_SPACING_MM) + probe.lateral_mm
    points = np.column_stack(
        [x, np.full(len(x), probe.sweep_position_mm), np.full(len(x), -acoustics.reference_depth_mm)]
    )
    lateral_sigma = settings.lateral_resolution_mm * _FWHM_TO_SIGMA
    # a line of amplitude A per mm echoes A sqrt(2 pi) sigma at its peak; the tissue's rms is _speckle_rms
    per_point = (
        10 ** (acoustics.reference_echo_db / 20)
        * _speckle_rms(settings, acoustics)
        * _REFLECTOR_SPACING_MM
        / (np.sqrt(2 * np.pi) * lateral_sigma)
    )
    return points, np.full(len(x), per_point)


def unit_complex_noise(rng: np.random.Generator, settings: ImagingSettings) -> np.ndarray:
    """(rows, cols) complex Gaussian noise of unit rms, to pass to :func:`render_frame`."""
    shape = (settings.rows, settings.cols)
    return (rng.standard_normal(shape) + 1j * rng.standard_normal(shape)) / np.sqrt(2.0)


def _speckle_rms(settings: ImagingSettings, acoustics: TissueAcoustics) -> float:
    """Expected rms echo amplitude of uniform tissue at zero depth (peak-1 Gaussian PSF)."""
    sigmas = (
        np.array([settings.lateral_resolution_mm, settings.axial_resolution_mm, settings.elevation_resolution_mm])
        * _FWHM_TO_SIGMA
    )
    return float(np.sqrt(acoustics.scatterer_density_per_mm3 * np.pi**1.5 * np.prod(sigmas)))


def _envelope(col_row: np.ndarray, weights: np.ndarray, settings: ImagingSettings) -> np.ndarray:
    """Complex echo (rows, cols) of point scatterers at pixel coordinates ``col_row`` (m, 2) with complex ``weights``.

    Bilinear splat onto the oversampled grid (``_core.splat_bilinear``), separable Gaussian blur, sampling at the
    pixels.
    """
    factor = settings.oversampling
    lateral_px, axial_px = settings.pixel_size_mm
    sigma_cols = settings.lateral_resolution_mm * _FWHM_TO_SIGMA / lateral_px * factor
    sigma_rows = settings.axial_resolution_mm * _FWHM_TO_SIGMA / axial_px * factor
    pad_cols, pad_rows = int(np.ceil(4 * sigma_cols)) + 1, int(np.ceil(4 * sigma_rows)) + 1
    grid_rows, grid_cols = settings.rows * factor + 2 * pad_rows, settings.cols * factor + 2 * pad_cols
    fine_col = col_row[:, 0] * factor + pad_cols
    fine_row = col_row[:, 1] * factor + pad_rows
    weight_real, weight_imag = np.ascontiguousarray(weights.real), np.ascontiguousarray(weights.imag)
    grids = _core.splat_bilinear(fine_col, fine_row, weight_real, weight_imag, (grid_rows, grid_cols))
    peak_normalisation = 2 * np.pi * sigma_cols * sigma_rows  # OpenCV's kernel sums to 1; the PSF peaks at 1
    parts = []
    for grid in grids:
        blurred = cv2.GaussianBlur(grid, (0, 0), sigmaX=sigma_cols, sigmaY=sigma_rows, borderType=cv2.BORDER_CONSTANT)
        parts.append(
            blurred[
                pad_rows : pad_rows + settings.rows * factor : factor,
                pad_cols : pad_cols + settings.cols * factor : factor,
            ]
        )
    return (parts[0].astype(np.float64) + 1j * parts[1].astype(np.float64)) * peak_normalisation


def echo_signal(
    field: ScattererField,
    section: Any,
    displacement: Callable[[np.ndarray], np.ndarray],
    probe: ProbeState,
    settings: ImagingSettings,
    acoustics: TissueAcoustics,
) -> np.ndarray:
    """The noiseless complex (IQ) echo (rows, cols) of ``section`` deformed by ``displacement``, seen by ``probe``.

    ``section`` is the :class:`~usdeform.sim.mechanics.SectionSpec` at ``probe.sweep_position_mm``
    (vessel and tissue extent), ``displacement`` maps reference points (m, 2) to their displacement
    (m, 2) at ``probe.probe_displacement_mm`` (e.g. from :meth:`GriddedSolution.at`). Amplitude 1
    is the rms echo of uniform tissue at zero depth.
    """
    imaged_reference_plane = probe.sweep_position_mm - probe.tissue_elevation_shift_mm
    window = _ELEVATION_WINDOW_FWHM * settings.elevation_resolution_mm
    elevation_range = (imaged_reference_plane - window, imaged_reference_plane + window)
    positions, amplitudes = field.between(*elevation_range)
    half_width, reach = tissue_reach(probe, settings)
    near = (np.abs(positions[:, 0]) <= half_width) & (positions[:, 1] <= reach)
    echo = amplitudes[near] * _echo_level(section, positions[near, :2], acoustics)
    tissue = echo != 0
    positions, echo = positions[near][tissue], echo[tissue]

    moved = displacement(positions[:, :2])
    deformed, elevation_mm = positions[:, :2] + moved, positions[:, 2] + probe.tissue_elevation_shift_mm
    if acoustics.scatterer_jitter_mm > 0:
        parameters = field.jitter_parameters_between(*elevation_range)[near][tissue]
        at_surface = displacement(np.column_stack([positions[:, 0], np.zeros(len(positions))]))
        jitter = scatterer_jitter_mm(
            parameters, moved - at_surface, acoustics.scatterer_jitter_mm, acoustics.jitter_correlation_mm
        )
        deformed, elevation_mm = deformed + jitter[:, :2], elevation_mm + jitter[:, 2]
    in_surface = section_to_surface(deformed, elevation_mm)
    if acoustics.reference_depth_mm is not None:
        reflector, reflector_echo = _reference_reflector(probe, settings, acoustics)
        in_surface, echo = np.concatenate([in_surface, reflector]), np.concatenate([echo, reflector_echo])
    col_row, depth, elevation = surface_to_image(in_surface, probe, settings, acoustics)

    depth_cm = depth / 10.0
    displayed_depth_cm = depth_cm * settings.assumed_sound_speed_m_s / acoustics.sound_speed_m_s
    gain_db = (
        -2 * acoustics.attenuation_db_per_cm_mhz * settings.center_frequency_mhz * depth_cm
        + settings.tgc_db_per_cm * displayed_depth_cm
    )
    elevation_sigma = settings.elevation_resolution_mm * _FWHM_TO_SIGMA
    wavenumber_per_mm = 2 * np.pi * settings.center_frequency_mhz * 1e3 / acoustics.sound_speed_m_s
    weights = (
        echo
        * np.exp(-0.5 * (elevation / elevation_sigma) ** 2)
        * 10 ** (gain_db / 20)
        * np.exp(-2j * wavenumber_per_mm * depth)
    )
    weights[depth < 0] = 0.0  # above the probe face: not imaged
    return _envelope(col_row, weights, settings) / _speckle_rms(settings, acoustics)


def b_mode(echo: np.ndarray, noise: np.ndarray, settings: ImagingSettings) -> np.ndarray:
    """Log-compressed uint8 frame (rows, cols) of an :func:`echo_signal` plus electronic noise.

    ``noise`` is a unit-rms complex (rows, cols) array from :func:`unit_complex_noise` (pass the
    same one to get the same noise).
    """
    if noise.shape != echo.shape:
        raise InputError(f"noise: expected shape {echo.shape}, got {noise.shape}")
    received = echo + noise * 10 ** (settings.noise_db / 20)
    level_db = 20 * np.log10(np.abs(received) + 1e-12) + settings.gain_db
    grey = np.clip((level_db + settings.dynamic_range_db) / settings.dynamic_range_db, 0.0, 1.0) * 255.0
    return np.rint(grey).astype(np.uint8)


def render_frame(
    field: ScattererField,
    section: Any,
    displacement: Callable[[np.ndarray], np.ndarray],
    probe: ProbeState,
    settings: ImagingSettings,
    acoustics: TissueAcoustics,
    noise: np.ndarray,
) -> np.ndarray:
    """The B-mode frame (rows, cols) uint8: :func:`b_mode` of :func:`echo_signal` (see both)."""
    return b_mode(echo_signal(field, section, displacement, probe, settings, acoustics), noise, settings)
