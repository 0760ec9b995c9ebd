"""Image pairs that break trackers: one large step of known motion, speckle decorrelation, low texture.

A palpation recorded at a low frame rate, a fast press or a dropped frame gives the tracker one
large step instead of many small ones, and real speckle decorrelates more between such frames than
the simulator's default speckle does. :func:`compression_pair` renders a pre- and post-compression
pair through the simulator's image formation (:mod:`usdeform.sim.imaging`: tissue-attached
speckle, attenuation, noise drawn anew for each frame) under a known analytic motion, so the true
displacement of every pixel follows from a formula:

* axial: the tissue at depth z moves towards the probe by ``offset + strain * z`` (the step at the
  image bottom is ``offset_px + strain * (rows - 1)`` pixels);
* lateral: it spreads sideways by ``lateral_ratio * strain`` times its distance from the centre.

Decorrelation comes from the deformation itself, the per-frame noise, the scatterer jitter
(``TissueAcoustics.scatterer_jitter_mm``) and an out-of-plane shift of the second frame; low
texture from a vessel lumen in view (no scatterers), a low scatterer density, or attenuation that
leaves the deep image to the noise. Frames skipped in a simulated palpation are
``recording.select(slice(None, None, k))``.

:func:`peak_patch_correlation` measures how decorrelated two frames are: the median, over textured
25 x 25 pixel patches of the first frame, of the best normalised correlation with the second frame
near the true (or zero) motion. The real PLUS SpinePhantom freehand sweep (PLUS test data, kept
outside the repository in ../shared/data/plus) gives 0.53 between consecutive frames; it is the
reference level for the decorrelation of the tests (``TissueAcoustics(scatterer_jitter_mm=0.02)``
reaches it on the default pair). Unrelated frames do not give 0 but the measure's floor (0.33 on
the sweep, 0.20 on simulated speckle), so the same number leaves the simulated pair more of its
correlation above the floor than the sweep; and the sweep's speckle decorrelates mostly by its
0.6-2.7 mm of out-of-plane motion between frames, which a palpation does not have. The level
bounds a palpation's decorrelation from above; the repository holds no real palpation to measure it
on.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from ..errors import InputError
from .imaging import (
    ImagingSettings,
    ProbeState,
    ScattererField,
    TissueAcoustics,
    b_mode,
    echo_signal,
    section_to_surface,
    surface_to_image,
    unit_complex_noise,
)
from .mechanics import SectionSpec

__all__ = ["CompressionPair", "compression_pair", "peak_patch_correlation"]


@dataclass(frozen=True, eq=False)
class CompressionPair:
    """Two frames and the true motion between them.

    Attributes:
        frames: (2, rows, cols) uint8, before and after the step.
        displacement_px: (rows, cols, 2) float64 true displacement (dx, dy), pixels, of the tissue
            shown at each pixel of the first frame into the second (forward mapping).
        lumen: (rows, cols) bool, pixels of the first frame inside the anechoic vessel lumen.
    """

    frames: np.ndarray
    displacement_px: np.ndarray
    lumen: np.ndarray


class _AnalyticStep:
    """The motion of :func:`compression_pair` in section coordinates (x lateral, z depth), mm."""

    def __init__(self, strain: float, offset_mm: float, lateral_ratio: float):
        self.strain, self.offset_mm, self.lateral_ratio = strain, offset_mm, lateral_ratio

    def __call__(self, points_mm: np.ndarray) -> np.ndarray:
        x, z = points_mm[:, 0], points_mm[:, 1]
        return np.column_stack([self.lateral_ratio * self.strain * x, -(self.offset_mm + self.strain * z)])


def compression_pair(
    strain: float = 0.05,
    *,
    offset_px: float = 0.0,
    lateral_ratio: float = 0.5,
    rows: int = 464,
    cols: int = 256,
    pixel_mm: float = 0.077,
    elevation_shift_mm: float = 0.0,
    lumen: bool = False,
    acoustics: TissueAcoustics | None = None,
    settings: ImagingSettings | None = None,
    seed: int = 0,
) -> CompressionPair:
    """A pre-/post-compression pair of simulated B-mode frames with a known large step.

    The defaults reproduce a real phantom pair: 5 % axial strain, 0.077 mm pixels, 464 rows
    (35.7 mm), so the tissue at the bottom moves 23 pixels.

    Parameters
    ----------
    strain : float
        Axial strain of the step (dimensionless, positive = compression), in [0, 0.5).
    offset_px : float
        Extra axial motion of the whole tissue towards the probe, pixels (>= 0).
    lateral_ratio : float
        Lateral spread per unit axial strain (about the Poisson ratio).
    rows, cols : int
        Frame size, pixels (used when ``settings`` is None).
    pixel_mm : float
        Pixel size, mm (square pixels; used when ``settings`` is None).
    elevation_shift_mm : float
        Out-of-plane shift of the tissue in the second frame, mm.
    lumen : bool
        Put an anechoic vessel lumen (radius 3 mm) in the middle of the image.
    acoustics : TissueAcoustics or None
        Scatterer density, attenuation and the scatterer jitter between the frames; default
        :class:`TissueAcoustics` () (no jitter).
    settings : ImagingSettings or None
        The scanner; default 7.6 MHz with the given frame and pixel size.
    seed : int
        Seed of the scatterers and the noise.

    Returns
    -------
    CompressionPair
    """
    if not (np.isfinite(strain) and 0 <= strain < 0.5):
        raise InputError(f"strain: expected a number in [0, 0.5), got {strain!r}")
    if not (np.isfinite(offset_px) and offset_px >= 0):
        raise InputError(f"offset_px: expected a non-negative number of pixels, got {offset_px!r}")
    if not (np.isfinite(pixel_mm) and pixel_mm > 0):
        raise InputError(f"pixel_mm: expected a positive size in mm, got {pixel_mm!r}")
    if not np.isfinite(elevation_shift_mm) or not np.isfinite(lateral_ratio):
        raise InputError("elevation_shift_mm and lateral_ratio: expected finite numbers")
    if int(seed) != seed or seed < 0:
        raise InputError(f"seed: expected a non-negative integer, got {seed!r}")
    acoustics = TissueAcoustics() if acoustics is None else acoustics
    if settings is None:
        settings = ImagingSettings(rows=rows, cols=cols, depth_mm=rows * pixel_mm, width_mm=cols * pixel_mm)
    depth_mm = settings.depth_mm
    if lumen:
        section = SectionSpec(vessel_center_x_mm=0.0, vessel_depth_mm=0.55 * depth_mm, vessel_radius_mm=3.0)
    else:  # the section needs a vessel: put it beside the image
        section = SectionSpec(vessel_center_x_mm=settings.width_mm / 2 + 20.0, vessel_depth_mm=20.0)
    axial_mm = settings.pixel_size_mm[1]
    motion = _AnalyticStep(float(strain), float(offset_px) * axial_mm, float(lateral_ratio))
    scatterer_seed, noise_seed = np.random.SeedSequence(int(seed)).spawn(2)
    field = ScattererField(int(scatterer_seed.generate_state(1)[0]), settings, acoustics)
    noise_rng = np.random.default_rng(noise_seed)
    frames = np.empty((2, settings.rows, settings.cols), np.uint8)
    for index, (displacement, shift) in enumerate(
        ((_AnalyticStep(0.0, 0.0, 0.0), 0.0), (motion, float(elevation_shift_mm)))
    ):
        probe = ProbeState(0.0, 0.0, 0.0, shift)
        echo = echo_signal(field, section, displacement, probe, settings, acoustics)
        frames[index] = b_mode(echo, unit_complex_noise(noise_rng, settings), settings)

    # Truth: the section point each pixel shows, moved, and imaged again.
    grid_rows, grid_cols = np.mgrid[0 : settings.rows, 0 : settings.cols]
    col_row = np.column_stack([grid_cols.ravel(), grid_rows.ravel(), np.zeros(grid_rows.size), np.ones(grid_rows.size)])
    in_probe = col_row @ settings.image_to_probe.T
    in_probe[:, 2] *= acoustics.sound_speed_m_s / settings.assumed_sound_speed_m_s
    section_points = np.column_stack([in_probe[:, 0], in_probe[:, 2]])  # untilted probe at s = 0, lambda = 0
    moved, _, _ = surface_to_image(
        section_to_surface(section_points + motion(section_points), 0.0), ProbeState(0.0, 0.0), settings, acoustics
    )
    displacement_px = (moved - col_row[:, :2]).reshape(settings.rows, settings.cols, 2)
    distance = np.hypot(
        section_points[:, 0] - section.vessel_center_x_mm, section_points[:, 1] - section.vessel_depth_mm
    )
    return CompressionPair(
        frames=frames,
        displacement_px=displacement_px,
        lumen=(distance < section.vessel_radius_mm).reshape(settings.rows, settings.cols),
    )


def peak_patch_correlation(
    before: np.ndarray,
    after: np.ndarray,
    displacement_px: np.ndarray | None = None,
    *,
    patch_px: int = 25,
    search_px: int = 4,
    spacing_px: int = 24,
    min_mean: float = 30.0,
    min_std: float = 10.0,
) -> float:
    """Median peak normalised correlation of ``patch_px`` square patches of ``before`` with ``after``.

    Patches on a grid ``spacing_px`` apart, with mean grey level >= ``min_mean`` and standard
    deviation >= ``min_std`` (speckle, not background), are correlated (OpenCV's TM_CCOEFF_NORMED)
    with ``after`` within ``search_px`` pixels of their true position (``displacement_px``
    (rows, cols, 2) (dx, dy) at the patch centre, or no motion); the best value of each counts.

    Parameters
    ----------
    before, after : (rows, cols) uint8 or float arrays.
    displacement_px : (rows, cols, 2) array or None
        Known motion from ``before`` to ``after``, pixels.

    Returns
    -------
    float
        The median over the patches (1: identical speckle, about 0: unrelated); NaN without any
        textured patch.
    """
    before = np.asarray(before, dtype=np.float32)
    after = np.asarray(after, dtype=np.float32)
    if before.ndim != 2 or before.shape != after.shape:
        raise InputError(f"before, after: expected two frames of the same shape, got {before.shape} and {after.shape}")
    if displacement_px is not None and np.shape(displacement_px) != (*before.shape, 2):
        raise InputError(f"displacement_px: expected shape {(*before.shape, 2)}, got {np.shape(displacement_px)}")
    half, rows, cols = patch_px // 2, before.shape[0], before.shape[1]
    reach = half + search_px
    peaks = []
    for y in range(reach, rows - reach, spacing_px):
        for x in range(reach, cols - reach, spacing_px):
            patch = before[y - half : y + half + 1, x - half : x + half + 1]
            if patch.mean() < min_mean or patch.std() < min_std:
                continue
            dx, dy = (0, 0) if displacement_px is None else np.rint(displacement_px[y, x]).astype(int)
            top, left = y + dy - reach, x + dx - reach
            if top < 0 or left < 0 or top + 2 * reach + 1 > rows or left + 2 * reach + 1 > cols:
                continue
            search = after[top : top + 2 * reach + 1, left : left + 2 * reach + 1]
            peaks.append(float(cv2.matchTemplate(search, patch, cv2.TM_CCOEFF_NORMED).max()))
    return float(np.median(peaks)) if peaks else float("nan")
