"""A section's finite-element displacement sampled on a regular grid, as the imaging evaluates it at
every scatterer of every frame."""

from __future__ import annotations

import threading
from typing import Any, Protocol

import numpy as np

from ...errors import InputError
from .geometry import ProbeState, tissue_reach
from .settings import ImagingSettings

__all__ = ["GriddedDisplacement", "GriddedSolution", "SectionSolution", "interpolation_bracket"]


class SectionSolution(Protocol):
    """What the imaging needs from a :class:`usdeform.sim.mechanics.MechanicsSolution`."""

    probe_displacement_mm: np.ndarray

    def displacement(self, points_mm: np.ndarray, probe_displacement_mm: float) -> np.ndarray: ...

    def lumen_boundary(self, probe_displacement_mm: float, n_points: int, vessel: int = 0) -> np.ndarray: ...


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
        half_width, depth = tissue_reach(ProbeState(0.0, float(self._steps[-1]), tilt_deg), settings)
        half_width, depth = min(half_width, section.width_mm / 2), min(depth, section.depth_mm)
        self._origin = np.array([-half_width, 0.0])
        self._shape = (int(np.ceil(2 * half_width / spacing_mm)) + 1, int(np.ceil(depth / spacing_mm)) + 1)
        self._spacing = np.array([2 * half_width / (self._shape[0] - 1), depth / (self._shape[1] - 1)])
        x = self._origin[0] + self._spacing[0] * np.arange(self._shape[0])
        z = self._spacing[1] * np.arange(self._shape[1])
        self._nodes = np.stack(np.meshgrid(x, z, indexing="ij"), axis=-1).reshape(-1, 2)
        self._step_values: dict[int, np.ndarray] = {}
        self._lock = threading.Lock()  # frames rendered in threads share a section's grid: a step is sampled once

    def _values_at_step(self, step: int) -> np.ndarray:
        with self._lock:
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
