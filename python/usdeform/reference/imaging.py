"""NumPy twin of the B-mode simulator's bilinear splat (``usdeform.sim.imaging.echo``)."""

from __future__ import annotations

import numpy as np


def splat_bilinear(
    fine_col: np.ndarray,
    fine_row: np.ndarray,
    weight_real: np.ndarray,
    weight_imag: np.ndarray,
    grid_shape: tuple[int, int],
) -> tuple[np.ndarray, np.ndarray]:
    """The real and imaginary (rows, cols) float32 grids of the points (``fine_col``, ``fine_row``) (n,)
    (positions in grid cells, fractional) with complex weights ``weight_real + 1j * weight_imag`` (n,)
    (echo amplitude, any unit) splatted bilinearly onto a grid of ``grid_shape`` (rows, cols) cells.

    Each point adds its weight times the bilinear coefficients to the four cells around it; points whose
    four cells are not all on the grid are left out. Summed in float64 with ``np.bincount`` over the four
    corners of all points, then cast to float32.
    """
    grid_rows, grid_cols = grid_shape
    weights = np.empty(len(weight_real), np.complex128)
    weights.real, weights.imag = weight_real, weight_imag
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
    real, imag = (
        np.bincount(corner_index, component, size).reshape(grid_rows, grid_cols).astype(np.float32)
        for component in (corner_weight.real, corner_weight.imag)
    )
    return real, imag
