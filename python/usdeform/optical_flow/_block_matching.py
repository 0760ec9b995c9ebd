"""Block matching: the motion of ~50-pixel patches at half resolution, robust to large steps and decorrelated
speckle, and the normalised median test that replaces its outliers (and checks the tracks' steps)."""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from .. import _core

_COARSE_PATCH = 25  # side of the block-matching patches at half resolution, pixels
_COARSE_SPACING = 12  # spacing of the block-matching grid at half resolution, pixels
_COARSE_MIN_PEAK = 0.2  # weaker correlation peaks are no match (unrelated 25 x 25 patches reach about 0.2)
_COARSE_UNCERTAINTY_PX = 2.0  # error bound of a matched block's motion: one half-resolution pixel either way


def _half_resolution(frame: np.ndarray) -> np.ndarray:
    """The frame at half resolution (2 x 2 pixel means), float32: half-resolution pixel (u, v) covers
    full-resolution pixels 2u..2u+1, so its centre is at (2u + 0.5, 2v + 0.5)."""
    return np.asarray(
        cv2.resize(frame, (frame.shape[1] // 2, frame.shape[0] // 2), interpolation=cv2.INTER_AREA), dtype=np.float32
    )


@dataclass(frozen=True)
class _CoarseFlow:
    """Block-matching displacement on a regular grid of the half-resolution frame.

    ``origin`` and ``spacing``: full-resolution (x, y) of grid node (0, 0) and the node spacing,
    pixels; ``flow``: (grid rows, grid cols, 2) float32 (dx, dy) at the nodes, full-resolution pixels.
    """

    origin: tuple[float, float]
    spacing: float
    flow: np.ndarray
    at_search_edge: float = 0.0  # fraction of the matched nodes whose peak lies on the edge of the search range
    matched: bool = True  # False where no block matched (a frame smaller than a patch, or no texture)

    def _sample(self, values: np.ndarray, points: np.ndarray) -> np.ndarray:
        """(N, C) bilinear samples of the (grid rows, grid cols, C) node ``values`` at (N, 2)
        full-resolution (x, y) points, edge values beyond the grid."""
        # OpenCV maps have fewer than 32767 rows and columns: lay the points out in rows of 1024.
        padded = np.zeros((-(-len(points) // 1024) * 1024, 2), dtype=np.float32)
        padded[: len(points)] = (points - np.asarray(self.origin)) / self.spacing
        map_x, map_y = (padded[:, i].reshape(-1, 1024) for i in (0, 1))
        sampled = cv2.remap(values, map_x, map_y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
        return np.asarray(sampled, dtype=np.float32).reshape(len(padded), -1)[: len(points)]

    def at(self, points: np.ndarray) -> np.ndarray:
        """(N, 2) bilinearly interpolated flow at (N, 2) full-resolution (x, y) points; beyond the grid
        (the frame's margins, which no patch centre reaches) continued linearly with the edge's gradient,
        as a compression's displacement grows with depth."""
        flow = self._sample(self.flow, points)
        grid = (np.asarray(points, dtype=np.float64) - np.asarray(self.origin)) / self.spacing
        for axis, column in ((1, 0), (0, 1)):  # the node axis and the (x, y) column it runs along
            nodes = self.flow.shape[axis]
            beyond = grid[:, column] - np.clip(grid[:, column], 0.0, nodes - 1.0)
            if nodes > 1 and np.any(beyond):
                gradient = np.gradient(self.flow, axis=axis)  # per node spacing
                flow += (self._sample(gradient, points) * beyond[:, None]).astype(np.float32)
        return flow

    def spread_at(self, points: np.ndarray, window_px: tuple[int, int]) -> np.ndarray:
        """(N,) how much the flow varies across a (width, height) window at (N, 2) (x, y) points, pixels:
        the larger over (dx, dy) of |d/dx| (width - 1) + |d/dy| (height - 1), the derivatives by
        differences between grid nodes (the scale of the block-matching patches, so a structure much
        smaller than them does not count)."""
        spread = np.zeros(self.flow.shape, dtype=np.float32)
        for axis, side in ((1, window_px[0]), (0, window_px[1])):
            if self.flow.shape[axis] > 1:
                spread += np.abs(np.gradient(self.flow, self.spacing, axis=axis)) * np.float32(side - 1)
        return self._sample(spread, points).max(axis=1)

    def uncertainty_at(self, points: np.ndarray) -> np.ndarray:
        """(N,) error bound of the flow at (N, 2) (x, y) points, pixels: ``_COARSE_UNCERTAINTY_PX`` plus
        how much the flow varies across a block-matching patch there (a strained patch's peak lies
        anywhere within that differential motion); infinite where no block matched."""
        if not self.matched:
            return np.full(len(points), np.inf)
        patch = 2 * _COARSE_PATCH
        return _COARSE_UNCERTAINTY_PX + self.spread_at(points, (patch, patch)).astype(np.float64)


def _coarse_flow(before: np.ndarray, after: np.ndarray, search_px: float) -> _CoarseFlow:
    """Motion from ``before`` to ``after`` by normalised-correlation block matching at half resolution.

    Patches of ``_COARSE_PATCH`` half-resolution pixels (about 50 full-resolution pixels: large
    enough that decorrelated speckle still has one clear correlation peak) on a grid
    ``_COARSE_SPACING`` apart are searched over +-``search_px`` full-resolution pixels; the peak is
    refined to subpixel by a parabola. Nodes whose peak is weak (below ``_COARSE_MIN_PEAK``: no
    texture, such as a lumen) or that fail the normalised median test against their 3 x 3
    neighbours (Westerweel & Scarano 2005, Exp. Fluids 39:1096, threshold 2, noise level 0.1 px)
    take their neighbours' median. The matching is ``_core.block_match`` (blocks in parallel; its twin,
    ``usdeform.reference.block_match``, is OpenCV's ``matchTemplate``). We write this ourselves rather than
    use OpenCV's dense flows:
    on simulated pairs with 40-pixel steps, DIS (medium preset) and Farneback (31 px, 5 levels)
    left 19-33 % and 27-36 % of the points more than 3 px wrong, this 0-0.9 %
    (benches/bench_tracking.py).
    """
    small_before, small_after = _half_resolution(before), _half_resolution(after)
    rows, cols = small_before.shape
    half = _COARSE_PATCH // 2
    search = int(np.ceil(search_px / 2.0))
    ys = np.arange(half, rows - half, _COARSE_SPACING)
    xs = np.arange(half, cols - half, _COARSE_SPACING)
    if len(ys) == 0 or len(xs) == 0:  # a frame smaller than one patch: no coarse motion, LK alone
        return _CoarseFlow((0.0, 0.0), 1.0, np.zeros((1, 1, 2), dtype=np.float32), matched=False)
    flow, peak, on_edge = _core.block_match(small_before, small_after, _COARSE_PATCH, _COARSE_SPACING, search)
    flow *= np.float32(2.0)  # half-resolution pixels to full-resolution ones
    matched = peak >= _COARSE_MIN_PEAK
    flow[~matched] = np.nan
    for _ in range(2):
        median, residual = _normalised_median_test(flow, 1, 0.1)
        replace = ~(residual <= 2.0) & np.isfinite(median).all(axis=2)  # outliers and missing nodes
        flow[replace] = median[replace]
    flow[np.isnan(flow)] = 0.0
    edge_fraction = float(on_edge[matched].mean()) if matched.any() else 0.0
    origin = (2.0 * xs[0] + 0.5, 2.0 * ys[0] + 0.5)
    return _CoarseFlow(origin, 2.0 * _COARSE_SPACING, flow, edge_fraction, bool(matched.any()))


def _neighbourhoods(values: np.ndarray, radius: int) -> np.ndarray:
    """(rows, cols, 2, (2 radius + 1)^2) view of the vectors of a (rows, cols, 2) grid in each node's
    (2 radius + 1)^2 neighbourhood (the node itself in the middle), NaN beyond the grid."""
    size = 2 * radius + 1
    padded = np.pad(values, ((radius, radius), (radius, radius), (0, 0)), constant_values=np.nan)
    return np.lib.stride_tricks.sliding_window_view(padded, (size, size), axis=(0, 1)).reshape(
        (*values.shape, size * size)
    )


def _nanmedian(values: np.ndarray) -> np.ndarray:
    """Median over the last axis ignoring NaN (NaN where all are NaN): ``np.nanmedian`` without its
    masked-array path, which costs milliseconds per call on the short axes of a neighbourhood."""
    ordered = np.sort(values, axis=-1)  # NaN sorts last
    count = np.count_nonzero(~np.isnan(values), axis=-1)
    lower = np.take_along_axis(ordered, np.maximum((count - 1) // 2, 0)[..., None], axis=-1)[..., 0]
    upper = np.take_along_axis(ordered, (count // 2)[..., None], axis=-1)[..., 0]
    return np.where(count > 0, 0.5 * (lower + upper), np.nan)


def _normalised_median_test(values: np.ndarray, radius: int, noise_px: float) -> tuple[np.ndarray, np.ndarray]:
    """The normalised median test of particle image velocimetry (Westerweel & Scarano 2005, Exp. Fluids 39:1096).

    For a (rows, cols, 2) grid of vectors (NaN: missing), the median u_m over each node's
    (2 radius + 1)^2 neighbourhood without the node itself and the residual
    |u - u_m| / (median_i |u_i - u_m| + noise_px) of the node's vector u against its neighbours u_i:
    the distance from the neighbours' median in units of their own scatter. Returns the medians
    (rows, cols, 2) and residuals (rows, cols), NaN where the node or all its neighbours are missing.
    """
    size = 2 * radius + 1
    neighbours = np.delete(_neighbourhoods(values, radius), size * size // 2, axis=-1)
    median = _nanmedian(neighbours)
    scatter = _nanmedian(np.linalg.norm(neighbours - median[..., None], axis=2))
    return median, np.linalg.norm(values - median, axis=-1) / (scatter + noise_px)
