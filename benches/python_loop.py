"""Plain Python (no NumPy in the inner loops) correction + nearest/mean compounding, per pixel.

Only the benchmarks use it: it measures what the kernels would cost written as straightforward
Python loops. Same conventions as ``usdeform.reference``.
"""

from __future__ import annotations

import math

import numpy as np

from usdeform import reference
from usdeform.regression import QuadraticDisplacementModel, StiffnessProfile
from usdeform.volume import VoxelGrid


def correct_and_compound(
    frames: np.ndarray,
    image_to_world: np.ndarray,
    forces: np.ndarray,
    profile: StiffnessProfile,
    model: QuadraticDisplacementModel,
    grid: VoxelGrid,
) -> tuple[list[float], list[float]]:
    """Warp each frame to zero force and splat it (nearest voxel, mean) into flat sum/weight lists."""
    nz, ny, nx = grid.shape
    sums, weights = [0.0] * (nz * ny * nx), [0.0] * (nz * ny * nx)
    world_to_index = np.linalg.inv(grid.index_to_world)
    n = model.normalization
    for frame, pose, force in zip(frames, image_to_world, forces, strict=False):
        rows, cols = frame.shape
        pixels = frame.tolist()
        affine = (world_to_index @ pose).tolist()
        one, h, h2 = reference.force_integrals(float(force), profile, n, model.n_intervals)
        k = model.coefficients.tolist()
        for row in range(rows):
            y = row / n.y_scale
            for col in range(cols):
                x = col / n.x_scale
                m = [x * x * one, y * y * one, h2, x * y * one, x * h, y * h, x * one, y * one, h, one]
                dx = sum(a * b for a, b in zip(k[0], m, strict=False)) * n.lateral_scale
                dy = sum(a * b for a, b in zip(k[1], m, strict=False)) * n.axial_scale
                sx, sy = col + dx, row + dy
                if not (0 <= sx <= cols - 1 and 0 <= sy <= rows - 1):
                    value = 0.0
                else:
                    x0, y0 = min(int(sx), cols - 2), min(int(sy), rows - 2)
                    fx, fy = sx - x0, sy - y0
                    value = (pixels[y0][x0] * (1 - fx) + pixels[y0][x0 + 1] * fx) * (1 - fy) + (
                        pixels[y0 + 1][x0] * (1 - fx) + pixels[y0 + 1][x0 + 1] * fx
                    ) * fy
                    value = float(math.floor(value + 0.5))
                i = math.floor(affine[0][0] * col + affine[0][1] * row + affine[0][3] + 0.5)
                j = math.floor(affine[1][0] * col + affine[1][1] * row + affine[1][3] + 0.5)
                kk = math.floor(affine[2][0] * col + affine[2][1] * row + affine[2][3] + 0.5)
                if 0 <= i < nx and 0 <= j < ny and 0 <= kk < nz:
                    voxel = (kk * ny + j) * nx + i
                    sums[voxel] += value
                    weights[voxel] += 1.0
    return sums, weights
