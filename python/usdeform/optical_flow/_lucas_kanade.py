"""Lucas-Kanade refinement: OpenCV's pyramidal (translation-only) and the compiled affine one, the patch
correlation that checks a step, and the texture that makes a point trackable."""

from __future__ import annotations

import cv2
import numpy as np

from .. import _core

_LK_CRITERIA = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 30, 0.01)


def _texture_map(frame: np.ndarray, window_px: int) -> np.ndarray:
    """(rows, cols) float32 sqrt of the smaller eigenvalue of the structure tensor averaged over a
    ``window_px`` square: the RMS intensity gradient along the least-textured direction, gray levels / px."""
    image = frame.astype(np.float32)
    gx = np.asarray(cv2.Sobel(image, cv2.CV_32F, 1, 0, ksize=3), dtype=np.float32) / np.float32(8.0)
    gy = np.asarray(cv2.Sobel(image, cv2.CV_32F, 0, 1, ksize=3), dtype=np.float32) / np.float32(8.0)
    size = (window_px, window_px)
    jxx = cv2.boxFilter(np.multiply(gx, gx), -1, size)
    jyy = cv2.boxFilter(np.multiply(gy, gy), -1, size)
    jxy = cv2.boxFilter(np.multiply(gx, gy), -1, size)
    smaller = 0.5 * (jxx + jyy) - np.sqrt(0.25 * (jxx - jyy) ** 2 + jxy**2)
    return np.sqrt(np.maximum(smaller, 0.0))


def _lucas_kanade(
    before: np.ndarray,
    after: np.ndarray,
    points: np.ndarray,
    initial: np.ndarray | None,
    window_px: tuple[int, int],
    pyramid_levels: int,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Pyramidal Lucas-Kanade from ``before`` to ``after`` of (N, 1, 2) float32 (x, y) points, starting
    at ``initial`` (N, 1, 2) if given, with a (width, height) window. Returns the tracked points
    (N, 1, 2), status (N,) and error (N,; infinite where a point was lost)."""
    tracked, status, error = cv2.calcOpticalFlowPyrLK(
        before,
        after,
        points,
        (points if initial is None else initial).copy(),
        winSize=window_px,
        maxLevel=pyramid_levels,
        criteria=_LK_CRITERIA,
        flags=0 if initial is None else cv2.OPTFLOW_USE_INITIAL_FLOW,
    )
    found = np.asarray(status).ravel() == 1
    # OpenCV leaves the error of a lost point uninitialised (at times a NaN, which numpy warns about when the
    # array is copied): infinite instead
    return np.asarray(tracked), found, np.where(found, np.asarray(error).ravel(), np.inf)


def window_offsets(window_px: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
    """(M,) float32 x and y offsets of the pixels of a (width, height) window from its centre, row by row."""
    width, height = window_px
    y_offsets, x_offsets = np.mgrid[-(height // 2) : height // 2 + 1, -(width // 2) : width // 2 + 1]
    return x_offsets.ravel().astype(np.float32), y_offsets.ravel().astype(np.float32)


def _patch_correlation(
    before: np.ndarray, after: np.ndarray, start: np.ndarray, end: np.ndarray, window_px: tuple[int, int]
) -> np.ndarray:
    """(N,) normalised correlation of the (width, height) ``window_px`` patches of the uint8 frame ``before``
    centred on the (N, 2) subpixel points ``start`` and of ``after`` centred on ``end`` (bilinear samples
    rounded to 8 bits, as ``cv2.remap`` gives them; 0 where a point is not finite or a patch is flat). The
    kernel is ``_core.patch_correlation`` (points in parallel; its twin is ``usdeform.reference.patch_correlation``)."""
    start, end = (np.ascontiguousarray(points, dtype=np.float32).reshape(-1, 2) for points in (start, end))
    correlation = np.zeros(len(start))
    finite = np.isfinite(start).all(axis=1) & np.isfinite(end).all(axis=1)
    correlation[finite] = _core.patch_correlation(
        before, after, start[finite], end[finite], (int(window_px[0]), int(window_px[1]))
    )
    return correlation


def _affine_lucas_kanade(
    before: np.ndarray,
    after: np.ndarray,
    start: np.ndarray,
    initial: np.ndarray,
    window_px: tuple[int, int],
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Lucas-Kanade with an affine warp of the window: where ``before``'s (width, height) window around
    each of the (N, 2) float32 points ``start`` lies in ``after``, starting at ``initial`` (N, 2).

    The window may stretch and shear (six parameters: the step and the local displacement gradient),
    as the tissue under it does: under 5-9 % axial strain a 51-pixel window spans 2.5-4.5 px of
    differential motion, which OpenCV's translation-only Lucas-Kanade turns into a random error
    (benches/bench_tracking.py). Inverse compositional Gauss-Newton (Baker & Matthews 2004, IJCV
    56:221) on zero-mean windows (blind to a change of brightness), until the step changes by less
    than ``_LK_CRITERIA``'s epsilon or after its iteration count. The window is cut where it leaves
    ``before`` or, warped, ``after`` (no replicated edge). We write it ourselves: OpenCV's
    Lucas-Kanade is translation-only and its ECC alignment (``cv2.findTransformECC``) aligns one
    window per call, too slow for a thousand windows per frame. The kernel is
    ``_core.affine_lucas_kanade`` (exact bilinear samples, windows in parallel; its NumPy twin is
    ``usdeform.reference.affine_lucas_kanade``); the gradients of ``before`` are OpenCV's Scharr.

    Returns the tracked points (N, 2) float32 (``initial`` where not ok), (N,) True where the
    window's texture determines all six parameters, the result is finite and moved less than half
    the window's smaller side from ``initial``, and the (N,) normalised correlation of the window
    and its warped match (0 where not ok).
    """
    image = before.astype(np.float32)
    gradient_x, gradient_y = (
        np.asarray(cv2.Scharr(image, cv2.CV_32F, dx, 1 - dx, scale=1.0 / 32.0), dtype=np.float32) for dx in (1, 0)
    )
    start, initial = (np.ascontiguousarray(points, dtype=np.float32) for points in (start, initial))
    tracked, ok, correlation = initial.copy(), np.zeros(len(initial), dtype=bool), np.zeros(len(initial))
    # The kernel refuses points that are not finite: their windows are not ok and stay where they are.
    finite = np.isfinite(start).all(axis=1) & np.isfinite(initial).all(axis=1)
    _, max_iterations, epsilon = _LK_CRITERIA
    tracked[finite], ok[finite], correlation[finite] = _core.affine_lucas_kanade(
        image,
        gradient_x,
        gradient_y,
        np.ascontiguousarray(after, dtype=np.float32),
        start[finite],
        initial[finite],
        (int(window_px[0]), int(window_px[1])),
        max_iterations=int(max_iterations),
        epsilon=float(epsilon),
    )
    return tracked, ok, correlation


def _pyramid_levels(remaining_px: float, window_px: tuple[int, int]) -> int:
    """Fewest pyramid levels for Lucas-Kanade to reach a motion of ``remaining_px`` pixels from its start:
    a window converges over about a quarter of its smaller side, and each level doubles that. A level
    more than the motion needs lets the coarse, smoothed image pull the track onto another speckle."""
    reach_px = min(window_px) / 4.0
    return max(0, int(np.ceil(np.log2(remaining_px / reach_px)))) if remaining_px > reach_px else 0
