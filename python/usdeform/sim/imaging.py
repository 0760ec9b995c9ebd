"""B-mode image formation for the simulator: tissue-attached speckle, vessel, attenuation, log compression.

Frames
------
The *surface frame* is the phantom's own frame: origin on the undeformed surface at sweep
coordinate s = 0, x lateral (the section's x), y along the sweep (s), z up out of the tissue. A
section point (x, depth z) at sweep coordinate s is the surface point (x, s, -z). The probe frame
follows the paper: origin at the centre of the probe face, x lateral, z along the probe axis into
the tissue, y = z cross x (the elevation axis). An untilted probe at sweep coordinate s pressed
lambda mm into the tissue has ``probe_to_surface`` = rotation diag(1, -1, -1), origin (0, s, -lambda).
Pixels map to the probe frame with the paper's eq. 2 (:func:`usdeform.recording.image_to_probe_from_geometry`);
pixel (col, row) samples exactly the probe point ``image_to_probe @ [col, row, 0, 1]``.

Speckle model
-------------
Point scatterers with zero-mean Gaussian amplitudes are seeded uniformly in the *reference*
(undeformed) tissue, in 1 mm thick elevation slabs generated on demand from the seed (so a sweep
of any length needs no global scatterer list). For a frame, each scatterer is moved by the
finite-element displacement of its section and imaged with a separable Gaussian point-spread
function (two-way amplitude, FWHM = the axial / lateral / elevation resolution). The echo is formed
as the complex (IQ-demodulated) sum ``sum_k a_k g(r - r_k) exp(-2 i k0 d_k)``, ``d_k`` the scatterer's
depth below the probe face and ``k0`` the wavenumber at the centre frequency, whose magnitude is
the envelope. Interference therefore depends on the scatterers' sub-wavelength positions exactly
as for an RF pulse followed by envelope detection, so the speckle moves with the tissue (and
decorrelates under strain and out-of-plane motion as real speckle does). For speed the complex
weights are splatted bilinearly onto a grid ``oversampling`` times finer than the pixels,
blurred with the separable Gaussian PSF (OpenCV) and sampled at the pixel positions; 3x
oversampling matches the exact per-scatterer sum to a correlation of 0.999.

Decorrelation: on top of what the deformation itself does to the interference, each scatterer can
move at random by ``scatterer_jitter_mm`` (rms per axis, lateral / axial / elevation; see
:class:`TissueAcoustics`). The jitter is a smooth random function of the scatterer's displacement
relative to the tissue surface above it (the compression between the surface and the scatterer;
a rigid motion does not change it), with correlation length ``jitter_correlation_mm``: frames of
the same tissue state see the same jitter, frames between which the tissue was compressed much
(a large step, a skipped frame) see independent jitter, deep tissue sooner than shallow tissue.
It stands for the sub-resolution motion the continuum field does not describe (non-affine
deformation of the scatterers, micro-motion) and lowers the correlation of speckle between frames
to the level of real data. The electronic noise is drawn anew for every frame.

Echogenicity: blood in the lumen is anechoic (no scatterers), the vessel wall (a ring of
``wall_thickness_mm`` outside the lumen in the reference section) echoes ``wall_echo_db`` brighter.
Round-trip attenuation ``2 * alpha * f * depth`` (alpha in dB/cm/MHz) is partly undone by a linear
time-gain compensation; complex Gaussian electronic noise sets the floor; the envelope is
log-compressed over ``dynamic_range_db`` to uint8.
"""

from __future__ import annotations

from collections import OrderedDict
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, Protocol

import cv2
import numpy as np

from ..errors import InputError
from ..recording import image_to_probe_from_geometry

__all__ = [
    "GriddedDisplacement",
    "GriddedSolution",
    "ImagingSettings",
    "ProbeState",
    "ScattererField",
    "TissueAcoustics",
    "b_mode",
    "echo_signal",
    "interpolation_bracket",
    "probe_to_surface",
    "render_frame",
    "scatterer_jitter_mm",
    "section_to_surface",
    "surface_to_image",
    "true_displacement_px",
    "unit_complex_noise",
    "vessel_mask",
]

_FWHM_TO_SIGMA = 1.0 / (2.0 * np.sqrt(2.0 * np.log(2.0)))
_ELEVATION_WINDOW_FWHM = 1.0  # scatterers beyond one elevation FWHM echo < 6 % (amplitude) and are skipped
_SLAB_MM = 1.0  # elevation thickness of one lazily generated scatterer slab
_SEED_LATERAL_MARGIN_MM = 15.0  # scatterers are seeded this far beyond the image sides ...
_SEED_DEPTH_MARGIN_MM = 30.0  # ... and below the image bottom, to cover compression and tilt
_JITTER_TERMS = 3  # random cosines in each scatterer's jitter function


class SectionSolution(Protocol):
    """What the imaging needs from a :class:`usdeform.sim.mechanics.MechanicsSolution`."""

    probe_displacement_mm: np.ndarray

    def displacement(self, points_mm: np.ndarray, probe_displacement_mm: float) -> np.ndarray: ...

    def lumen_boundary(self, probe_displacement_mm: float, n_points: int) -> np.ndarray: ...


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
    ``jitter_correlation_mm`` of it (see the module docstring). Calibration: 0.02 mm with the
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
    """

    sound_speed_m_s: float = 1540.0
    attenuation_db_per_cm_mhz: float = 0.5
    scatterer_density_per_mm3: float = 20.0
    wall_thickness_mm: float = 0.8
    wall_echo_db: float = 10.0
    scatterer_jitter_mm: float = 0.0
    jitter_correlation_mm: float = 1.0

    def __post_init__(self) -> None:
        for name in ("sound_speed_m_s", "scatterer_density_per_mm3", "jitter_correlation_mm"):
            value = getattr(self, name)
            if not (np.isfinite(value) and value > 0):
                raise InputError(f"TissueAcoustics.{name}: expected a positive finite number, got {value!r}")
        for name in ("attenuation_db_per_cm_mhz", "wall_thickness_mm", "wall_echo_db", "scatterer_jitter_mm"):
            value = getattr(self, name)
            if not np.isfinite(value) or (name != "wall_echo_db" and value < 0):
                raise InputError(f"TissueAcoustics.{name}: expected a finite non-negative number, got {value!r}")


@dataclass(frozen=True)
class ProbeState:
    """Where the probe is: sweep coordinate s (mm), indentation lambda (mm, probe face at depth
    lambda), tilt about the elevation axis (degrees, in the image plane) and the out-of-plane shift
    of the imaged tissue relative to the probe (mm, along the surface y axis)."""

    sweep_position_mm: float
    probe_displacement_mm: float
    tilt_deg: float = 0.0
    tissue_elevation_shift_mm: float = 0.0

    def at_zero_force(self) -> ProbeState:
        """The same probe position and tilt, touching the undeformed surface, no out-of-plane shift."""
        return ProbeState(self.sweep_position_mm, 0.0, self.tilt_deg)


def _transform(matrix: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Apply a (4, 4) transform to (m, 3) points (element-wise arithmetic: no BLAS threads to contend with OpenCV's)."""
    return (
        points[:, 0:1] * matrix[:3, 0] + points[:, 1:2] * matrix[:3, 1] + points[:, 2:3] * matrix[:3, 2] + matrix[:3, 3]
    )


def probe_to_surface(probe: ProbeState) -> np.ndarray:
    """(4, 4) pose of the probe in the surface frame (see the module docstring)."""
    tilt = np.radians(probe.tilt_deg)
    about_elevation = np.array([[np.cos(tilt), 0.0, np.sin(tilt)], [0.0, 1.0, 0.0], [-np.sin(tilt), 0.0, np.cos(tilt)]])
    pose = np.eye(4)
    pose[:3, :3] = np.diag([1.0, -1.0, -1.0]) @ about_elevation
    pose[:3, 3] = [0.0, probe.sweep_position_mm, -probe.probe_displacement_mm]
    return pose


def section_to_surface(points_xz_mm: np.ndarray, elevation_mm: np.ndarray | float) -> np.ndarray:
    """Section points (m, 2) (x, depth) at sweep coordinate(s) ``elevation_mm`` -> surface frame (m, 3)."""
    points_xz_mm = np.asarray(points_xz_mm, dtype=np.float64)
    elevation = np.broadcast_to(np.asarray(elevation_mm, dtype=np.float64), points_xz_mm.shape[:1])
    return np.column_stack([points_xz_mm[:, 0], elevation, -points_xz_mm[:, 1]])


def surface_to_image(
    points_mm: np.ndarray, probe: ProbeState, settings: ImagingSettings, acoustics: TissueAcoustics
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Surface points (m, 3) -> where the scanner displays them.

    Returns (col_row (m, 2) pixel coordinates, depth_mm (m,) true depth below the probe face along
    its axis, elevation_mm (m,) distance from the image plane). The displayed depth is the true
    depth times ``assumed / true`` sound speed (echo time converted with the assumed speed).
    """
    surface_to_probe = np.linalg.inv(probe_to_surface(probe))
    in_probe = _transform(surface_to_probe, points_mm)
    depth = in_probe[:, 2]
    displayed = in_probe.copy()
    displayed[:, 2] = depth * (settings.assumed_sound_speed_m_s / acoustics.sound_speed_m_s)
    probe_to_image = np.linalg.inv(settings.image_to_probe)
    in_image = _transform(probe_to_image, displayed)
    return in_image[:, :2], depth, in_probe[:, 1]


def _image_to_surface(
    col_row: np.ndarray, probe: ProbeState, settings: ImagingSettings, acoustics: TissueAcoustics
) -> np.ndarray:
    """Pixel coordinates (m, 2) -> surface points (m, 3): the inverse of :func:`surface_to_image` in the image plane."""
    in_probe = _transform(settings.image_to_probe, np.column_stack([col_row, np.zeros(len(col_row))]))
    in_probe[:, 2] *= acoustics.sound_speed_m_s / settings.assumed_sound_speed_m_s
    return _transform(probe_to_surface(probe), in_probe)


class ScattererField:
    """Point scatterers of a phantom in its reference (undeformed) configuration, deterministic per seed.

    Scatterers fill x in [-(width/2 + 15), width/2 + 15] mm and depth [0, image depth + 30] mm with
    ``density`` per mm^3, in 1 mm elevation slabs generated on demand (slab k from the seed and k).
    """

    def __init__(self, seed: int, settings: ImagingSettings, acoustics: TissueAcoustics, cached_slabs: int = 16):
        if int(seed) != seed or seed < 0:
            raise InputError(f"seed: expected a non-negative integer, got {seed!r}")
        self.seed = int(seed)
        self.half_width_mm = settings.width_mm / 2 + _SEED_LATERAL_MARGIN_MM
        self.max_depth_mm = settings.depth_mm + _SEED_DEPTH_MARGIN_MM
        self.density_per_mm3 = acoustics.scatterer_density_per_mm3
        self._cached_slabs = cached_slabs
        self._slabs: OrderedDict[int, tuple[np.ndarray, np.ndarray]] = OrderedDict()
        self._last_query: tuple[tuple[float, float], tuple[np.ndarray, np.ndarray]] | None = None
        self._last_jitter_query: tuple[tuple[float, float], np.ndarray] | None = None

    def _slab(self, index: int) -> tuple[np.ndarray, np.ndarray]:
        if index in self._slabs:
            self._slabs.move_to_end(index)
            return self._slabs[index]
        rng = np.random.default_rng([self.seed, index + 2**31])
        volume = 2 * self.half_width_mm * self.max_depth_mm * _SLAB_MM
        count = rng.poisson(self.density_per_mm3 * volume)
        positions = np.column_stack(
            [
                rng.uniform(-self.half_width_mm, self.half_width_mm, count),
                rng.uniform(0.0, self.max_depth_mm, count),
                rng.uniform(index * _SLAB_MM, (index + 1) * _SLAB_MM, count),
            ]
        )
        amplitudes = rng.standard_normal(count)
        self._slabs[index] = (positions, amplitudes)
        if len(self._slabs) > self._cached_slabs:
            self._slabs.popitem(last=False)
        return positions, amplitudes

    def between(self, elevation_min_mm: float, elevation_max_mm: float) -> tuple[np.ndarray, np.ndarray]:
        """Scatterers with elevation (sweep coordinate) in [min, max): positions (n, 3) as (x, depth,
        elevation) mm in the reference section, and amplitudes (n,)."""
        if self._last_query is not None and self._last_query[0] == (elevation_min_mm, elevation_max_mm):
            return self._last_query[1]  # a palpation asks for the same scatterers every frame
        first, last = int(np.floor(elevation_min_mm / _SLAB_MM)), int(np.floor(elevation_max_mm / _SLAB_MM))
        slabs = [self._slab(index) for index in range(first, last + 1)]
        positions = np.concatenate([slab[0] for slab in slabs])
        amplitudes = np.concatenate([slab[1] for slab in slabs])
        inside = (positions[:, 2] >= elevation_min_mm) & (positions[:, 2] < elevation_max_mm)
        self._last_query = ((elevation_min_mm, elevation_max_mm), (positions[inside], amplitudes[inside]))
        return self._last_query[1]

    def jitter_parameters_between(self, elevation_min_mm: float, elevation_max_mm: float) -> np.ndarray:
        """(n, terms, 6) float32 random parameters of the jitter functions of the scatterers that
        :meth:`between` returns for the same range (in the same order): per term a 3-vector
        amplitude, a 2-vector wave vector (both standard normal) and a phase in [0, 2 pi).

        Drawn from a stream of their own (slab k from the seed, k and 1), so that the scatterers
        themselves are the same with or without jitter.
        """
        query = (elevation_min_mm, elevation_max_mm)
        if self._last_jitter_query is not None and self._last_jitter_query[0] == query:
            return self._last_jitter_query[1]
        first, last = int(np.floor(elevation_min_mm / _SLAB_MM)), int(np.floor(elevation_max_mm / _SLAB_MM))
        parts = []
        for index in range(first, last + 1):
            positions, _ = self._slab(index)
            rng = np.random.default_rng([self.seed, index + 2**31, 1])
            parameters = np.empty((len(positions), _JITTER_TERMS, 6), dtype=np.float32)
            parameters[:, :, :5] = rng.standard_normal((len(positions), _JITTER_TERMS, 5))
            parameters[:, :, 5] = rng.uniform(0.0, 2 * np.pi, (len(positions), _JITTER_TERMS))
            inside = (positions[:, 2] >= elevation_min_mm) & (positions[:, 2] < elevation_max_mm)
            parts.append(parameters[inside])
        self._last_jitter_query = (query, np.concatenate(parts))
        return self._last_jitter_query[1]


def scatterer_jitter_mm(
    parameters: np.ndarray, displacement_mm: np.ndarray, rms_mm: float, correlation_mm: float
) -> np.ndarray:
    """(m, 3) random displacement (lateral, depth, elevation), mm, of scatterers displaced by
    ``displacement_mm`` (m, 2) (x, depth): a sum of random cosines of the displacement.

    Each component has rms ``rms_mm``; two displacements u1, u2 of the same scatterer give jitters
    correlated by exp(-|u1 - u2|^2 / (2 correlation_mm^2)) (the characteristic function of the
    standard normal wave vectors), so the jitter changes little between nearby tissue states and is
    independent between distant ones. ``parameters`` from :meth:`ScattererField.jitter_parameters_between`.
    """
    amplitudes, wave_vectors, phases = parameters[:, :, :3], parameters[:, :, 3:5], parameters[:, :, 5]
    scaled = (displacement_mm / correlation_mm).astype(np.float32)
    arguments = wave_vectors[:, :, 0] * scaled[:, None, 0] + wave_vectors[:, :, 1] * scaled[:, None, 1] + phases
    terms = parameters.shape[1]
    return np.einsum("mt,mtk->mk", np.cos(arguments), amplitudes).astype(np.float64) * (rms_mm * np.sqrt(2.0 / terms))


def _tissue_reach(probe: ProbeState, settings: ImagingSettings) -> tuple[float, float]:
    """(half width, depth), mm, of the reference tissue that can appear in the image of ``probe``
    (tilt and compression included, with 5 mm to spare for lateral and axial tissue motion)."""
    depth = settings.depth_mm + abs(probe.probe_displacement_mm) + 5.0
    tilt = np.radians(abs(probe.tilt_deg))
    return settings.width_mm / 2 * np.cos(tilt) + depth * np.sin(tilt) + 5.0, depth


def interpolation_bracket(knots: np.ndarray, value: float) -> tuple[int, int, float]:
    """(lower index, upper index, weight of upper) for linear interpolation of ``value`` between
    increasing ``knots`` (held at the ends; one knot gives (0, 0, 0))."""
    position = float(np.interp(value, knots, np.arange(len(knots))))
    lower = int(np.floor(position))
    return lower, min(lower + 1, len(knots) - 1), position - lower


class GriddedDisplacement:
    """A displacement field sampled at the nodes of a regular grid, interpolated bilinearly.

    ``origin`` (2,) and ``spacing`` (2,) in mm (x, depth), ``lateral`` / ``axial`` flat (n_x * n_z,)
    node values in mm, node (i, j) at index i * n_z + j.
    """

    def __init__(
        self, origin: np.ndarray, spacing: np.ndarray, shape: tuple[int, int], lateral: np.ndarray, axial: np.ndarray
    ):
        self._origin, self._spacing, self._shape = origin, spacing, shape
        self._lateral, self._axial = lateral, axial

    def __call__(self, points_mm: np.ndarray) -> np.ndarray:
        """Displacement (m, 2), mm, of reference points (m, 2) (x, depth); beyond the grid, its edge values."""
        index = (points_mm - self._origin) / self._spacing
        lower = np.clip(np.floor(index).astype(np.int64), 0, np.array(self._shape) - 2)
        fraction = np.clip(index - lower, 0.0, 1.0)
        fx, fz = fraction[:, 0], fraction[:, 1]
        corner = lower[:, 0] * self._shape[1] + lower[:, 1]
        corners_and_weights = (
            (corner, (1 - fx) * (1 - fz)),
            (corner + self._shape[1], fx * (1 - fz)),
            (corner + 1, (1 - fx) * fz),
            (corner + self._shape[1] + 1, fx * fz),
        )
        return np.column_stack(
            [
                sum(np.take(values, index) * weight for index, weight in corners_and_weights)
                for values in (self._lateral, self._axial)
            ]
        )

    def reference_position(
        self, points_mm: np.ndarray, tolerance_mm: float = 1e-6, max_iterations: int = 50
    ) -> np.ndarray:
        """Reference positions (m, 2) of material points found at ``points_mm`` (fixed point X = x - u(X))."""
        reference = points_mm - self(points_mm)
        for _ in range(max_iterations):
            updated = points_mm - self(reference)
            converged = np.abs(updated - reference).max(initial=0.0) < tolerance_mm
            reference = updated
            if converged:
                break
        return reference


class GriddedSolution:
    """A section's finite-element displacement, sampled on a regular grid at its solved lambda steps.

    Evaluating the finite-element field at every scatterer of every frame is slow. The grid
    covers the tissue the probe can image (up to the solution's largest lambda and ``tilt_deg``);
    a step is sampled when first needed; between steps the field is linear in lambda, as the
    solution's own. Bilinear interpolation on the ``spacing_mm`` grid errs by ~spacing^2 u''/8:
    below 0.01 mm except at the lumen wall, where the strain jumps (below 0.1 mm there).
    """

    def __init__(
        self,
        solution: SectionSolution,
        section: Any,
        settings: ImagingSettings,
        tilt_deg: float = 0.0,
        spacing_mm: float = 0.5,
    ):
        self._solution = solution
        self._steps = np.asarray(solution.probe_displacement_mm, dtype=float)
        half_width, depth = _tissue_reach(ProbeState(0.0, float(self._steps[-1]), tilt_deg), settings)
        half_width, depth = min(half_width, section.width_mm / 2), min(depth, section.depth_mm)
        self._origin = np.array([-half_width, 0.0])
        self._shape = (int(np.ceil(2 * half_width / spacing_mm)) + 1, int(np.ceil(depth / spacing_mm)) + 1)
        self._spacing = np.array([2 * half_width / (self._shape[0] - 1), depth / (self._shape[1] - 1)])
        x = self._origin[0] + self._spacing[0] * np.arange(self._shape[0])
        z = self._spacing[1] * np.arange(self._shape[1])
        self._nodes = np.stack(np.meshgrid(x, z, indexing="ij"), axis=-1).reshape(-1, 2)
        self._step_values: dict[int, np.ndarray] = {}

    def _values_at_step(self, step: int) -> np.ndarray:
        if step not in self._step_values:
            self._step_values[step] = self._solution.displacement(self._nodes, float(self._steps[step]))
        return self._step_values[step]

    def at(self, probe_displacement_mm: float) -> GriddedDisplacement:
        """The displacement field at lambda (mm), within the solved range."""
        if not (self._steps[0] <= probe_displacement_mm <= self._steps[-1]):
            raise InputError(
                f"probe displacement {probe_displacement_mm} mm is outside the solved range "
                f"[{self._steps[0]}, {self._steps[-1]}] mm"
            )
        lower, upper, weight = interpolation_bracket(self._steps, probe_displacement_mm)
        values = (1 - weight) * self._values_at_step(lower) + weight * self._values_at_step(upper)
        return GriddedDisplacement(self._origin, self._spacing, self._shape, values[:, 0].copy(), values[:, 1].copy())


def _echo_level(section: Any, points_xz_mm: np.ndarray, acoustics: TissueAcoustics) -> np.ndarray:
    """Echo amplitude factor (m,) of reference points: 0 outside the tissue and in the lumen, the wall
    level on the wall ring, 1 elsewhere."""
    x, z = points_xz_mm[:, 0], points_xz_mm[:, 1]
    distance = np.hypot(x - section.vessel_center_x_mm, z - section.vessel_depth_mm)
    level = np.where(
        distance < section.vessel_radius_mm + acoustics.wall_thickness_mm, 10 ** (acoustics.wall_echo_db / 20), 1.0
    )
    tissue = (distance >= section.vessel_radius_mm) & (z <= section.depth_mm) & (np.abs(x) <= section.width_mm / 2)
    return np.where(tissue, level, 0.0)


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

    Bilinear splat onto the oversampled grid, separable Gaussian blur, sampling at the pixels.
    """
    factor = settings.oversampling
    lateral_px, axial_px = settings.pixel_size_mm
    sigma_cols = settings.lateral_resolution_mm * _FWHM_TO_SIGMA / lateral_px * factor
    sigma_rows = settings.axial_resolution_mm * _FWHM_TO_SIGMA / axial_px * factor
    pad_cols, pad_rows = int(np.ceil(4 * sigma_cols)) + 1, int(np.ceil(4 * sigma_rows)) + 1
    grid_rows, grid_cols = settings.rows * factor + 2 * pad_rows, settings.cols * factor + 2 * pad_cols
    fine_col = col_row[:, 0] * factor + pad_cols
    fine_row = col_row[:, 1] * factor + pad_rows
    col0, row0 = np.floor(fine_col).astype(np.int64), np.floor(fine_row).astype(np.int64)
    inside = (col0 >= 0) & (col0 < grid_cols - 1) & (row0 >= 0) & (row0 < grid_rows - 1)
    col0, row0, weights = col0[inside], row0[inside], weights[inside]
    frac_col, frac_row = fine_col[inside] - col0, fine_row[inside] - row0
    index = row0 * grid_cols + col0
    corner_index = np.concatenate([index, index + 1, index + grid_cols, index + grid_cols + 1])
    corner_weight = np.concatenate(
        [
            weights * (1 - frac_row) * (1 - frac_col),
            weights * (1 - frac_row) * frac_col,
            weights * frac_row * (1 - frac_col),
            weights * frac_row * frac_col,
        ]
    )
    size = grid_rows * grid_cols
    peak_normalisation = 2 * np.pi * sigma_cols * sigma_rows  # OpenCV's kernel sums to 1; the PSF peaks at 1
    parts = []
    for component in (corner_weight.real, corner_weight.imag):
        grid = np.bincount(corner_index, component, size).reshape(grid_rows, grid_cols).astype(np.float32)
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
    half_width, reach = _tissue_reach(probe, settings)
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


def vessel_mask(
    solution: SectionSolution, probe: ProbeState, settings: ImagingSettings, acoustics: TissueAcoustics
) -> np.ndarray:
    """(rows, cols) bool: pixels whose sample point lies inside the deformed lumen, as rendered."""
    boundary = solution.lumen_boundary(probe.probe_displacement_mm, 360)
    polygon, _, _ = surface_to_image(section_to_surface(boundary, probe.sweep_position_mm), probe, settings, acoustics)
    mask = np.zeros((settings.rows, settings.cols), dtype=bool)
    col_min, row_min = np.maximum(np.floor(polygon.min(axis=0)).astype(int), 0)
    col_max, row_max = np.minimum(np.ceil(polygon.max(axis=0)).astype(int), [settings.cols - 1, settings.rows - 1])
    if col_min > col_max or row_min > row_max:
        return mask
    rows = np.arange(row_min, row_max + 1, dtype=float)[:, None]
    cols = np.arange(col_min, col_max + 1, dtype=float)[None, :, None]
    # Even-odd rule: count the edges crossed by a ray from each pixel centre towards +col.
    start, end = polygon, np.roll(polygon, -1, axis=0)
    edges = start[:, 1] != end[:, 1]
    start, end = start[edges], end[edges]
    straddles = (start[:, 1] > rows) != (end[:, 1] > rows)  # (rows, edges)
    crossing_col = start[:, 0] + (rows - start[:, 1]) * (end[:, 0] - start[:, 0]) / (end[:, 1] - start[:, 1])
    crossing_col = np.where(straddles, crossing_col, -np.inf)[:, None, :]  # (rows, 1, edges)
    inside = np.count_nonzero(cols < crossing_col, axis=2) % 2 == 1
    mask[row_min : row_max + 1, col_min : col_max + 1] = inside
    return mask


def true_displacement_px(
    section: Any,
    zero_force_displacement: GriddedDisplacement,
    displacement: Callable[[np.ndarray], np.ndarray],
    probe: ProbeState,
    settings: ImagingSettings,
    acoustics: TissueAcoustics,
) -> np.ndarray:
    """(rows, cols, 2) float32 true displacement (d_col, d_row) in pixels of every zero-force pixel.

    The zero-force pixel (col, row) shows the tissue point that the deformed frame shows at
    (col + d_col, row + d_row): backward mapping, ``zero_force[r, c] = deformed[r + d_row, c + d_col]``.
    ``zero_force_displacement`` is the section's field at lambda = 0 (non-zero with lumen pressure),
    ``displacement`` the field at ``probe.probe_displacement_mm``. NaN where the zero-force pixel
    shows no tissue (beyond the section, or above its surface when tilted).
    """
    rows, cols = np.mgrid[0 : settings.rows, 0 : settings.cols]
    col_row = np.column_stack([cols.ravel(), rows.ravel()]).astype(np.float64)
    at_zero_force = _image_to_surface(col_row, probe.at_zero_force(), settings, acoustics)
    section_points = np.column_stack([at_zero_force[:, 0], -at_zero_force[:, 2]])
    tissue = (
        (section_points[:, 1] >= 0)
        & (section_points[:, 1] <= section.depth_mm)
        & (np.abs(section_points[:, 0]) <= section.width_mm / 2)
    )
    reference = zero_force_displacement.reference_position(section_points[tissue])
    deformed = reference + displacement(reference)
    deformed_col_row, _, _ = surface_to_image(
        section_to_surface(deformed, probe.sweep_position_mm), probe, settings, acoustics
    )
    result = np.full(col_row.shape, np.nan, dtype=np.float32)
    result[tissue] = deformed_col_row - col_row[tissue]
    return result.reshape(settings.rows, settings.cols, 2)
