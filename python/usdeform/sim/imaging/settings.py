"""The scanner's and the tissue's settings of the simulated imaging: image geometry, transducer
resolution and display chain (:class:`ImagingSettings`); sound speed, attenuation, scatterers and
their jitter (:class:`TissueAcoustics`)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ...errors import InputError
from ...recording import image_to_probe_from_geometry

__all__ = ["ImagingSettings", "TissueAcoustics"]


@dataclass(frozen=True)
class ImagingSettings:
    """The scanner: image geometry, transducer resolution and display chain.

    Defaults follow the paper's setup (40 mm depth, 37.5 mm array, 7.6 MHz, 50 fps handled by the
    recorder). Resolutions are full widths at half maximum of the two-way PSF amplitude, mm: at
    7.6 MHz the wavelength is 0.2 mm, a two-cycle pulse gives ~0.25 mm axially, an f-number ~2.5
    aperture ~0.5 mm laterally, and linear arrays have a 1-2 mm thick elevation slice (Szabo,
    *Diagnostic Ultrasound Imaging: Inside Out*, 2004, ch. 7). ``assumed_sound_speed_m_s`` is the
    speed the scanner uses to convert echo time to depth. ``tgc_db_per_cm`` is the time-gain
    compensation (per cm of displayed depth), ``gain_db`` the level of average tissue speckle at
    the top of the image relative to full white, ``noise_db`` the electronic noise relative to
    that speckle before gain, ``dynamic_range_db`` the log-compression window.
    """

    rows: int = 256
    cols: int = 256
    depth_mm: float = 40.0
    width_mm: float = 37.5
    image_offset_mm: float = 0.0
    center_frequency_mhz: float = 7.6
    assumed_sound_speed_m_s: float = 1540.0
    axial_resolution_mm: float = 0.25
    lateral_resolution_mm: float = 0.5
    elevation_resolution_mm: float = 1.5
    tgc_db_per_cm: float = 6.0
    gain_db: float = -20.0
    noise_db: float = -40.0
    dynamic_range_db: float = 60.0
    oversampling: int = 3

    def __post_init__(self) -> None:
        for name in ("rows", "cols", "oversampling"):
            value = getattr(self, name)
            if int(value) != value or value < 1:
                raise InputError(f"ImagingSettings.{name}: expected a positive integer, got {value!r}")
        for name in (
            "depth_mm",
            "width_mm",
            "center_frequency_mhz",
            "assumed_sound_speed_m_s",
            "axial_resolution_mm",
            "lateral_resolution_mm",
            "elevation_resolution_mm",
            "dynamic_range_db",
        ):
            value = getattr(self, name)
            if not (np.isfinite(value) and value > 0):
                raise InputError(f"ImagingSettings.{name}: expected a positive finite number, got {value!r}")

    @property
    def image_to_probe(self) -> np.ndarray:
        """(4, 4) pixel (col, row) -> probe mm (paper eq. 2)."""
        return image_to_probe_from_geometry(self.rows, self.cols, self.depth_mm, self.width_mm, self.image_offset_mm)

    @property
    def pixel_size_mm(self) -> tuple[float, float]:
        """(lateral, axial) pixel size, mm."""
        return self.width_mm / self.cols, self.depth_mm / self.rows


@dataclass(frozen=True)
class TissueAcoustics:
    """Acoustic properties of the phantom.

    ``sound_speed_m_s``: true speed of sound (soft tissue 1540 m/s on average; fat ~1450, muscle
    ~1580, gelatin phantoms 1500-1560: Duck, *Physical Properties of Tissue*, 1990).
    ``attenuation_db_per_cm_mhz``: one-way attenuation slope (soft tissue 0.5-1, fat ~0.6, gelatin
    phantoms 0.1-0.7 depending on additives: Duck 1990; Szabo 2004, ch. 4).
    ``scatterer_density_per_mm3``: seeded point scatterers per mm^3 of reference tissue (a low
    density gives sparse, low-texture speckle);
    ``wall_thickness_mm`` / ``wall_echo_db``: the bright vessel wall ring and its echo level over
    tissue.
    ``scatterer_jitter_mm``: rms random displacement of each scatterer per axis, mm (0: none), a
    smooth random function of the scatterer's displacement that decorrelates over
    ``jitter_correlation_mm`` of it (see :mod:`usdeform.sim.imaging.scatterers`). Calibration: 0.02 mm with the
    default 1 mm correlation length brings the median peak normalised correlation of 25 x 25 pixel
    patches between a pre- and a post-compression frame (5 % strain, 0.077 mm pixels, 23 px at
    the bottom) to 0.52-0.54, that of consecutive frames of the real PLUS SpinePhantom freehand
    sweep (PLUS test data, kept outside the repository in ../shared/data/plus: 0.53, frames 1.6 mm
    apart in elevation); without jitter the simulated pair correlates at 0.82
    (:func:`usdeform.sim.tracking_cases.peak_patch_correlation`). The peak correlation has a floor
    (unrelated frames score 0.33 on the sweep, 0.20 on simulated speckle), and the sweep
    decorrelates mostly through its out-of-plane steps, which a palpation lacks: the level bounds a
    palpation's decorrelation from above rather than measuring it
    (``python benches/bench_tracking.py`` prints the floors).
    ``reference_depth_mm``: a flat specular reflector fixed in the world (the phantom's base plate, the table under
    it, a wire plane held by the phantom's box) this deep below the unloaded surface, echoing
    ``reference_echo_db`` above tissue speckle; None: none. It does not move with the tissue, so its image moves by
    the probe's displacement times assumed / true sound speed.
    """

    sound_speed_m_s: float = 1540.0
    attenuation_db_per_cm_mhz: float = 0.5
    scatterer_density_per_mm3: float = 20.0
    wall_thickness_mm: float = 0.8
    wall_echo_db: float = 10.0
    scatterer_jitter_mm: float = 0.0
    jitter_correlation_mm: float = 1.0
    reference_depth_mm: float | None = None
    reference_echo_db: float = 20.0

    def __post_init__(self) -> None:
        if self.reference_depth_mm is not None and not (
            np.isfinite(self.reference_depth_mm) and self.reference_depth_mm > 0
        ):
            raise InputError(
                f"TissueAcoustics.reference_depth_mm: expected a positive depth in mm or None, "
                f"got {self.reference_depth_mm!r}"
            )
        for name in ("sound_speed_m_s", "scatterer_density_per_mm3", "jitter_correlation_mm"):
            value = getattr(self, name)
            if not (np.isfinite(value) and value > 0):
                raise InputError(f"TissueAcoustics.{name}: expected a positive finite number, got {value!r}")
        for name in (
            "attenuation_db_per_cm_mhz",
            "wall_thickness_mm",
            "wall_echo_db",
            "scatterer_jitter_mm",
            "reference_echo_db",
        ):
            value = getattr(self, name)
            if not np.isfinite(value) or (not name.endswith("_echo_db") and value < 0):
                raise InputError(f"TissueAcoustics.{name}: expected a finite non-negative number, got {value!r}")
