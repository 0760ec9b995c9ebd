"""NumPy twin of the tracker's affine Lucas-Kanade refinement."""

from __future__ import annotations

import numpy as np

from ..optical_flow import window_offsets
from .correction import bilinear_samples, inside_frame


def _replicated_bilinear(image: np.ndarray, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Bilinear samples of ``image`` at ``(x, y)``, the edge replicated beyond the frame (OpenCV's
    ``BORDER_REPLICATE``: the position clamped into it); 0 at NaN."""
    rows, cols = image.shape
    return bilinear_samples(image, np.clip(x, 0, cols - 1), np.clip(y, 0, rows - 1), 0.0)


def affine_lucas_kanade(
    before: np.ndarray,
    gradient_x: np.ndarray,
    gradient_y: np.ndarray,
    after: np.ndarray,
    start: np.ndarray,
    initial: np.ndarray,
    window_px: tuple[int, int],
    max_iterations: int = 30,
    epsilon: float = 0.01,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Twin of ``_core.affine_lucas_kanade``: where the (width, height) ``window_px`` window of ``before``
    around each (N, 2) float32 point ``start`` lies in ``after``, from ``initial`` (N, 2), with an affine
    warp of the window (the step and the local displacement gradient).

    Inverse compositional Gauss-Newton (Baker & Matthews 2004, IJCV 56:221) on zero-mean windows, all
    windows at once. The template and the descent images are ``before``, ``gradient_x`` and
    ``gradient_y`` sampled at ``start`` plus the window's offsets, the match ``after`` sampled at the
    warped offsets, all by exact bilinear interpolation. A window is cut (weight 0) where it leaves
    ``before`` or, warped, ``after``, and its template and Hessian are prepared again after a cut. The
    iteration stops after ``max_iterations`` or once both components of the translation update are below
    ``epsilon``; an update that undoes the previous one (translation within ``epsilon``) is halved and
    ends it. Returns the tracked points (N, 2) float32 (``initial`` where not ok), ok (N,) (the Hessian's
    smallest eigenvalue above 1e-6 of its largest, a finite result moved less than half the window's
    smaller side from ``initial``) and the (N,) correlation of each template with its warped match (0
    where not ok).
    """
    x_offsets, y_offsets = (offsets.astype(np.float64) for offsets in window_offsets(window_px))
    rows, cols = before.shape
    initial = np.asarray(initial, dtype=np.float32)
    start_xy, initial_xy = np.asarray(start, dtype=np.float64), initial.astype(np.float64)
    n = len(start_xy)

    def in_frame(x: np.ndarray, y: np.ndarray) -> np.ndarray:
        return inside_frame(x, y, (rows, cols))

    map_x, map_y = start_xy[:, 0, None] + x_offsets, start_xy[:, 1, None] + y_offsets
    sampled, gx, gy = (_replicated_bilinear(image, map_x, map_y) for image in (before, gradient_x, gradient_y))
    # (N, M, 6) steepest-descent images: gx and gy times 1, x and y (parameters dx, d(dx)/dx, d(dx)/dy,
    # dy, d(dy)/dx, d(dy)/dy in this order).
    descent = np.stack([gx, gx * x_offsets, gx * y_offsets, gy, gy * x_offsets, gy * y_offsets], axis=-1)
    weight = (
        in_frame(map_x, map_y) & in_frame(initial_xy[:, 0, None] + x_offsets, initial_xy[:, 1, None] + y_offsets)
    ).astype(np.float64)
    count = np.ones(n)
    template = np.zeros_like(sampled)
    determined = np.zeros(n, dtype=bool)
    inverse_hessian = np.tile(np.eye(6), (n, 1, 1))

    def zero_mean(values: np.ndarray, points: np.ndarray) -> np.ndarray:
        """(n, M) window values minus their mean over the window, 0 where the window is cut."""
        values = values * weight[points]
        return (values - values.sum(axis=1, keepdims=True) / count[points, None]) * weight[points]

    def prepare(points: np.ndarray) -> None:
        """The template and the inverse Gauss-Newton Hessian of these windows (after a cut)."""
        count[points] = np.maximum(weight[points].sum(axis=1), 1.0)
        template[points] = zero_mean(sampled[points], points)
        weighted = descent[points] * weight[points, :, None]
        means = weighted.sum(axis=1)
        # Zero-mean windows: remove the part of the descent images a change of brightness explains.
        hessian = np.einsum("nmi,nmj->nij", weighted, descent[points])
        hessian -= means[:, :, None] * means[:, None, :] / count[points, None, None]
        eigenvalues = np.linalg.eigvalsh(hessian)
        determined[points] = eigenvalues[:, 0] > 1e-6 * np.maximum(eigenvalues[:, -1], 1e-12)
        hessian[~determined[points]] = np.eye(6)
        inverse_hessian[points] = np.linalg.inv(hessian)

    prepare(np.arange(n))
    warp = np.tile(np.eye(3), (n, 1, 1))  # (N, 3, 3): window offset (homogeneous) -> position in after
    warp[:, :2, 2] = initial_xy

    def warped_window(points: np.ndarray) -> np.ndarray:
        """The windows warped into ``after`` (zero mean), after cutting them where they left it."""
        (a, b, c), (d, e, f) = (warp[points, row, :, None].transpose(1, 0, 2) for row in (0, 1))
        moved_x, moved_y = a * x_offsets + b * y_offsets + c, d * x_offsets + e * y_offsets + f
        inside = in_frame(moved_x, moved_y)
        cut = (weight[points] > inside).any(axis=1)
        if cut.any():
            weight[points[cut]] *= inside[cut]
            prepare(points[cut])
        return zero_mean(_replicated_bilinear(after, moved_x, moved_y), points)

    active = np.flatnonzero(determined)
    previous = np.zeros((n, 6))
    for _ in range(int(max_iterations)):
        active = active[determined[active]]
        if len(active) == 0:
            break
        difference = warped_window(active) - template[active]
        gradient = np.einsum("nmi,nm->ni", descent[active], difference)
        update = np.einsum("nij,nj->ni", inverse_hessian[active], gradient)
        # A step that undoes the previous one oscillates about the optimum: take half of it and stop (as
        # OpenCV's Lucas-Kanade does).
        oscillates = (np.abs(update[:, [0, 3]] + previous[active][:, [0, 3]]) < epsilon).all(axis=1)
        update[oscillates] *= 0.5
        # Compose with the inverse of the increment [[1 + p1, p2, p0], [p4, 1 + p5, p3]].
        increment = np.tile(np.eye(3), (len(active), 1, 1))
        increment[:, :2, :2] += update[:, [[1, 2], [4, 5]]]
        increment[:, :2, 2] = update[:, [0, 3]]
        with np.errstate(divide="ignore", invalid="ignore"):
            warp[active] = warp[active] @ _affine_inverse(increment)
        previous[active] = update
        active = active[~oscillates & (np.abs(update[:, [0, 3]]).max(axis=1) >= epsilon)]
    tracked = warp[:, :2, 2].astype(np.float32)
    with np.errstate(invalid="ignore"):
        ok = (
            determined & np.isfinite(tracked).all(axis=1) & (np.abs(tracked - initial).max(axis=1) < min(window_px) / 2)
        )
    correlation = np.zeros(n)
    if ok.any():
        matched = warped_window(np.flatnonzero(ok))
        norms = np.sqrt((template[ok] ** 2).sum(axis=1) * (matched**2).sum(axis=1))
        correlation[ok] = (template[ok] * matched).sum(axis=1) / np.maximum(norms, 1e-12)
    return np.where(ok[:, None], tracked, initial).astype(np.float32), ok, correlation


def _affine_inverse(matrices: np.ndarray) -> np.ndarray:
    """The inverses of (n, 3, 3) affine matrices (last row 0, 0, 1) in closed form (inf or NaN where singular)."""
    linear = matrices[:, :2, :2]
    determinant = linear[:, 0, 0] * linear[:, 1, 1] - linear[:, 0, 1] * linear[:, 1, 0]
    inverse = np.zeros_like(matrices)
    inverse[:, 0, 0], inverse[:, 1, 1] = linear[:, 1, 1], linear[:, 0, 0]
    inverse[:, 0, 1], inverse[:, 1, 0] = -linear[:, 0, 1], -linear[:, 1, 0]
    inverse[:, :2, :2] /= determinant[:, None, None]
    inverse[:, :2, 2] = -np.einsum("nij,nj->ni", inverse[:, :2, :2], matrices[:, :2, 2])
    inverse[:, 2, 2] = 1.0
    return inverse
