"""The ground truth of a simulated frame, as the scanner would show it: the deformed lumen's pixels
and the true displacement of every pixel from zero force."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np

from .fields import GriddedDisplacement, SectionSolution
from .geometry import ProbeState, image_to_surface, section_to_surface, surface_to_image
from .settings import ImagingSettings, TissueAcoustics

__all__ = ["true_displacement_px", "vessel_mask"]


def vessel_mask(
    solution: SectionSolution, probe: ProbeState, settings: ImagingSettings, acoustics: TissueAcoustics
) -> np.ndarray:
    """(rows, cols) bool: pixels whose sample point lies inside a deformed lumen (any vessel), as rendered."""
    mask = np.zeros((settings.rows, settings.cols), dtype=bool)
    spec = getattr(solution, "spec", None)  # a section's solution; a stand-in without one has one lumen
    lumens = 1 if spec is None else len(spec.lumens)
    lam = probe.probe_displacement_mm
    boundaries = [solution.lumen_boundary(lam, 360)] + [solution.lumen_boundary(lam, 360, v) for v in range(1, lumens)]
    for boundary in boundaries:
        polygon, _, _ = surface_to_image(
            section_to_surface(boundary, probe.sweep_position_mm), probe, settings, acoustics
        )
        _fill_polygon(mask, polygon)
    return mask


def _fill_polygon(mask: np.ndarray, polygon: np.ndarray) -> None:
    """Set the pixels of ``mask`` (rows, cols) whose centre lies inside ``polygon`` (n, 2) (col, row)."""
    settings_rows, settings_cols = mask.shape
    col_min, row_min = np.maximum(np.floor(polygon.min(axis=0)).astype(int), 0)
    col_max, row_max = np.minimum(np.ceil(polygon.max(axis=0)).astype(int), [settings_cols - 1, settings_rows - 1])
    if col_min > col_max or row_min > row_max:
        return
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
    mask[row_min : row_max + 1, col_min : col_max + 1] |= inside


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
    at_zero_force = image_to_surface(col_row, probe.at_zero_force(), settings, acoustics)
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
