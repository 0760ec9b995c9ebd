"""NumPy and OpenCV twins of the tracker's patch kernels: the patch correlation (``cv2.remap``) and the
block matching (``cv2.matchTemplate``)."""

from __future__ import annotations

import cv2
import numpy as np

from ..optical_flow import window_offsets


def _sample_patches(image: np.ndarray, map_x: np.ndarray, map_y: np.ndarray) -> np.ndarray:
    """(N, M) float32 bilinear samples of ``image`` at the (N, M) subpixel points (``map_x``, ``map_y``),
    the edge replicated beyond the frame. One patch per map row, in chunks: OpenCV maps have fewer
    than 32767 rows and columns."""
    chunk = 16384
    parts = [
        cv2.remap(
            image,
            np.ascontiguousarray(map_x[first : first + chunk], dtype=np.float32),
            np.ascontiguousarray(map_y[first : first + chunk], dtype=np.float32),
            cv2.INTER_LINEAR,
            borderMode=cv2.BORDER_REPLICATE,
        ).reshape(-1, map_x.shape[1])
        for first in range(0, len(map_x), chunk)
    ]
    return np.concatenate(parts).astype(np.float32, copy=False) if parts else np.zeros(map_x.shape, np.float32)


def patch_correlation(
    before: np.ndarray, after: np.ndarray, start: np.ndarray, end: np.ndarray, window_px: tuple[int, int]
) -> np.ndarray:
    """Twin of ``_core.patch_correlation``: (N,) normalised correlation of the (width, height) ``window_px``
    patches of the uint8 frame ``before`` centred on the (N, 2) float32 points ``start`` and of ``after``
    centred on ``end`` (``cv2.remap``'s bilinear samples, 8 bits, edge replicated), 0 where one is flat."""
    x_offsets, y_offsets = window_offsets(window_px)

    def patches(image: np.ndarray, centres: np.ndarray) -> np.ndarray:
        values = _sample_patches(image, centres[:, 0, None] + x_offsets, centres[:, 1, None] + y_offsets)
        return values.astype(np.float64) - values.mean(axis=1, keepdims=True, dtype=np.float64)

    first, second = patches(before, start), patches(after, end)
    products = np.einsum("ij,ij->i", first, second)
    norms = np.sqrt(np.einsum("ij,ij->i", first, first) * np.einsum("ij,ij->i", second, second))
    return np.where(norms > 0, products / np.maximum(norms, 1e-12), 0.0)


def _parabola_peak(below: float, peak: float, above: float) -> float:
    """Subpixel offset (in (-0.5, 0.5)) of the maximum of a parabola through three equally spaced samples."""
    curvature = below - 2.0 * peak + above
    return 0.0 if curvature >= 0 else min(max(0.5 * float(below - above) / float(curvature), -0.5), 0.5)


def block_match(
    before: np.ndarray, after: np.ndarray, patch: int, spacing: int, search: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Twin of ``_core.block_match``: the ``patch`` x ``patch`` blocks of the float32 frame ``before`` on
    nodes ``spacing`` apart (from ``patch // 2``, blocks inside the frame) searched over +-``search``
    pixels of ``after`` (edge replicated) with ``cv2.matchTemplate``'s ``TM_CCOEFF_NORMED``, the peak
    refined by a parabola along each axis. Returns the flow (node rows, node cols, 2) float32 (dx, dy),
    the peak (node rows, node cols) float32 and whether it lies on the search range's edge."""
    rows, cols = before.shape
    half = patch // 2
    ys, xs = np.arange(half, rows - half, spacing), np.arange(half, cols - half, spacing)
    padded = cv2.copyMakeBorder(after, search, search, search, search, cv2.BORDER_REPLICATE)
    flow = np.zeros((len(ys), len(xs), 2), dtype=np.float32)
    peak = np.zeros((len(ys), len(xs)), dtype=np.float32)
    on_edge = np.zeros((len(ys), len(xs)), dtype=bool)
    for i, y in enumerate(ys):
        for j, x in enumerate(xs):
            block = before[y - half : y + half + 1, x - half : x + half + 1]
            region = padded[y - half : y + half + 1 + 2 * search, x - half : x + half + 1 + 2 * search]
            score = cv2.matchTemplate(region, block, cv2.TM_CCOEFF_NORMED)
            _, best, _, (col, row) = cv2.minMaxLoc(score)
            dx = col + (_parabola_peak(score[row, col - 1], best, score[row, col + 1]) if 0 < col < 2 * search else 0.0)
            dy = row + (_parabola_peak(score[row - 1, col], best, score[row + 1, col]) if 0 < row < 2 * search else 0.0)
            flow[i, j] = (dx - search, dy - search)
            peak[i, j] = best
            on_edge[i, j] = min(col, row) == 0 or max(col, row) == 2 * search
    return flow, peak, on_edge
