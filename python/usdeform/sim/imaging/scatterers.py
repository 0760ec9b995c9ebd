"""The point scatterers of the simulated tissue and their random jitter.

Point scatterers with zero-mean Gaussian amplitudes are seeded uniformly in the *reference*
(undeformed) tissue, in 1 mm thick elevation slabs generated on demand from the seed (so a sweep
of any length needs no global scatterer list).

Decorrelation: on top of what the deformation itself does to the interference, each scatterer can
move at random by ``scatterer_jitter_mm`` (rms per axis, lateral / axial / elevation; see
:class:`~usdeform.sim.imaging.TissueAcoustics`). The jitter is a smooth random function of the
scatterer's displacement relative to the tissue surface above it (the compression between the
surface and the scatterer; a rigid motion does not change it), with correlation length
``jitter_correlation_mm``: frames of the same tissue state see the same jitter, frames between which
the tissue was compressed much (a large step, a skipped frame) see independent jitter, deep tissue
sooner than shallow tissue. It stands for the sub-resolution motion the continuum field does not
describe (non-affine deformation of the scatterers, micro-motion) and lowers the correlation of
speckle between frames to the level of real data.
"""

from __future__ import annotations

import threading
from collections import OrderedDict

import numpy as np

from ...errors import InputError
from .settings import ImagingSettings, TissueAcoustics

__all__ = ["ScattererField", "scatterer_jitter_mm"]

_SLAB_MM = 1.0  # elevation thickness of one lazily generated scatterer slab
_SEED_LATERAL_MARGIN_MM = 15.0  # scatterers are seeded this far beyond the image sides ...
_SEED_DEPTH_MARGIN_MM = 30.0  # ... and below the image bottom, to cover compression and tilt
_JITTER_TERMS = 3  # random cosines in each scatterer's jitter function


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
        self._lock = threading.Lock()  # frames rendered in threads share the field and its caches

    def _slab(self, index: int) -> tuple[np.ndarray, np.ndarray]:
        """Slab ``index``'s scatterers (the caller holds the lock)."""
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
        with self._lock:
            return self._between(elevation_min_mm, elevation_max_mm)

    def _between(self, elevation_min_mm: float, elevation_max_mm: float) -> tuple[np.ndarray, np.ndarray]:
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
        with self._lock:
            return self._jitter_parameters_between(elevation_min_mm, elevation_max_mm)

    def _jitter_parameters_between(self, elevation_min_mm: float, elevation_max_mm: float) -> np.ndarray:
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
