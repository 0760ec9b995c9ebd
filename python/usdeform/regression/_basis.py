"""The spatial functions of the displacement models, and where a vessel's lumen lies.

The paper's quadratic terms (:func:`regression_vector`, eq. 7), tensor-product cubic B-splines on
uniform clamped knots over the normalised [0, 1] (:func:`bspline_basis`, :func:`bspline_vector`),
and the vessel-anchored window's functions (:func:`vessel_basis`), placed on a
:class:`VesselAnchor` (a lumen's centre and equivalent radius, pixels). The smoothness penalty of a
coefficient grid is its summed squared second differences (:func:`_second_differences`).
"""

from __future__ import annotations

import functools
from dataclasses import dataclass

import numpy as np
from scipy.interpolate import BSpline

from ..errors import InputError

#: Names of the regression terms, in the order of the columns of K.
M_TERMS = ("x^2", "y^2", "h^2", "xy", "xh", "yh", "x", "y", "h", "1")
#: Fewest cubic B-splines per axis of :class:`BSplineDisplacementModel` (one knot span).
BSPLINE_MIN_FUNCTIONS = 4


def regression_vector(x_n: np.ndarray, y_n: np.ndarray, h_terms: tuple[float, float, float]) -> np.ndarray:
    """``M`` of paper eq. 7 with its ``(1, h, h^2)`` factors replaced by ``h_terms``: shape (10, *x_n.shape).

    ``h_terms = (1, h, h^2)`` gives ``M(x, y, h)``; the force integrals of ``1, h, h^2`` give the
    integral of ``M`` over force (eq. 8), which is how the displacement is linear in ``K``.
    """
    one, h, h2 = h_terms
    return np.stack(
        [
            x_n**2 * one,
            y_n**2 * one,
            np.full_like(x_n, h2),
            x_n * y_n * one,
            x_n * h,
            y_n * h,
            x_n * one,
            y_n * one,
            np.full_like(x_n, h),
            np.full_like(x_n, one),
        ]
    )


def bspline_basis(u: np.ndarray, n_functions: int) -> np.ndarray:
    """The ``n_functions`` cubic B-splines on uniform clamped knots over [0, 1] at normalised ``u``
    (end pieces extended outside): shape (n_functions, *u.shape)."""
    u = np.asarray(u, dtype=np.float64)
    return _bspline_basis_at(u.tobytes(), u.shape, n_functions).copy(order="K")


@functools.lru_cache(maxsize=32)
def _bspline_basis_at(u_bytes: bytes, shape: tuple[int, ...], n_functions: int) -> np.ndarray:
    """:func:`bspline_basis` at the float64 values ``u_bytes`` of an array of ``shape`` (read-only).

    Remembered for the last few arrays of points: a fit evaluates the basis at the same points many
    times (once per force term, again in each held-out refit of its report, at every frame of a
    prediction), and each evaluation builds a sparse matrix."""
    u = np.frombuffer(u_bytes, dtype=np.float64).reshape(shape)
    knots = np.concatenate([np.zeros(3), np.linspace(0.0, 1.0, n_functions - 2), np.ones(3)])
    matrix = BSpline.design_matrix(u.ravel(), knots, 3, extrapolate=True).toarray()
    basis = matrix.T.reshape(n_functions, *shape)
    basis.setflags(write=False)
    return basis


def bspline_vector(
    x_n: np.ndarray, y_n: np.ndarray, h_terms: tuple[float, float, float], n_functions: tuple[int, int]
) -> np.ndarray:
    """The B-spline model's terms ``h_term * B_i(y_n) B_j(x_n)`` in the order (term, i, j) of its
    coefficients: shape (3 * n_y * n_x, *x_n.shape)."""
    n_y, n_x = n_functions
    spatial = bspline_basis(y_n, n_y)[:, np.newaxis] * bspline_basis(x_n, n_x)[np.newaxis]
    return np.concatenate([term * spatial.reshape(n_y * n_x, *np.shape(x_n)) for term in h_terms])


#: Half-width of the vessel-anchored basis's square window around the lumen centre, in lumen radii.
#: A lumen perturbs the strain of the tissue around it by about ``(radius / distance)^2`` (Kirsch's
#: solution for a hole in a strained plate): a quarter at two radii, where the smooth field of the
#: probe contact (the image-anchored part) takes over.
VESSEL_WINDOW_RADII = 2.0
#: Knot spacing of the vessel-anchored basis, in lumen radii: the collapse of a round lumen is
#: mostly its oval mode (``cos 2 theta`` around the wall), which half-radius knots resolve.
VESSEL_KNOT_SPACING_RADII = 0.5


@dataclass(frozen=True)
class VesselAnchor:
    """Where a vessel's lumen lies in a frame: its centre ``centre_px`` (x, y) and equivalent radius
    ``radius_px`` (``sqrt(area / pi)``), pixels.

    Examples
    --------
    >>> mask = np.zeros((32, 32), dtype=bool)
    >>> mask[10:20, 4:14] = True
    >>> VesselAnchor.of_mask(mask).centre_px
    (8.5, 14.5)
    """

    centre_px: tuple[float, float]
    radius_px: float

    def __post_init__(self) -> None:
        centre = tuple(float(c) for c in self.centre_px)
        if len(centre) != 2 or not np.all(np.isfinite(centre)):
            raise InputError(f"centre_px: expected a finite (x, y), got {self.centre_px!r}")
        if not (np.isfinite(self.radius_px) and self.radius_px > 0):
            raise InputError(f"radius_px: expected a positive radius in pixels, got {self.radius_px!r}")
        object.__setattr__(self, "centre_px", centre)
        object.__setattr__(self, "radius_px", float(self.radius_px))

    @classmethod
    def of_mask(cls, mask: np.ndarray) -> VesselAnchor:
        """The centroid and equivalent radius of a lumen ``mask`` (rows, cols) of at least one pixel."""
        pixels = np.argwhere(np.asarray(mask, dtype=bool))
        if len(pixels) == 0:
            raise InputError("mask: the lumen mask is empty")
        row, col = pixels.mean(axis=0)
        return cls((float(col), float(row)), float(np.sqrt(len(pixels) / np.pi)))


@dataclass
class LumenTrack:
    """Where a sweep's lumen search stands, to go on with the next frames of the same sweep (the live
    service corrects a scan a batch at a time): the last lumen found (None: none yet) and the frames
    searched since without one. Updated in place by :func:`usdeform.correction.sweep_lumens`."""

    last_found: VesselAnchor | None = None
    frames_missed: int = 0


def _window_coordinates(
    x_px: np.ndarray, y_px: np.ndarray, anchor: VesselAnchor, window_radii: float
) -> tuple[np.ndarray, np.ndarray]:
    """Pixel coordinates as the vessel window's normalised [0, 1] coordinates (lumen centre at 0.5)."""
    width = 2.0 * window_radii * anchor.radius_px
    return (x_px - anchor.centre_px[0]) / width + 0.5, (y_px - anchor.centre_px[1]) / width + 0.5


def _window_functions(u: np.ndarray, n_functions: int) -> np.ndarray:
    """The inner ``n_functions - 4`` cubic B-splines of a clamped basis of ``n_functions`` over the
    window [0, 1], zero outside it: (n_functions - 4, *u.shape). Leaving out the two outer functions
    at each end makes the vessel part vanish with its slope at the window's edge (C1)."""
    inside = (u >= 0.0) & (u <= 1.0)
    functions: np.ndarray = bspline_basis(np.clip(u, 0.0, 1.0), n_functions)[2:-2] * inside
    return functions


def vessel_basis(
    x_px: np.ndarray,
    y_px: np.ndarray,
    anchor: VesselAnchor,
    reference_radius_px: float,
    n_functions: int,
    window_radii: float = VESSEL_WINDOW_RADII,
) -> np.ndarray:
    """The vessel-anchored spatial functions at pixel points: (n_inner^2, *x_px.shape), in the (y, x)
    order of the coefficient grid, with ``n_inner = n_functions - 4``.

    The window follows the lumen: coordinates are measured from ``anchor``'s centre in units of its
    radius, and the functions are scaled by ``radius / reference_radius_px``, so that a lumen twice
    as large gets the same collapse twice as large (the displacement around a hole in a strained
    elastic medium scales with the hole).
    """
    u, v = _window_coordinates(np.asarray(x_px, float), np.asarray(y_px, float), anchor, window_radii)
    along_y, along_x = _window_functions(v, n_functions), _window_functions(u, n_functions)
    spatial = along_y[:, np.newaxis] * along_x[np.newaxis] * (anchor.radius_px / reference_radius_px)
    return spatial.reshape(-1, *np.shape(x_px))


def _second_differences(n_functions: tuple[int, int]) -> np.ndarray:
    """``R`` with ``|R c|^2`` the summed squared second differences along x and along y of each
    force term's coefficient grid, for ``c`` in the (term, y, x) order: (n_differences, 3 n_y n_x)."""
    n_y, n_x = n_functions
    along_x = np.kron(np.eye(n_y), np.diff(np.eye(n_x), 2, axis=0))
    along_y = np.kron(np.diff(np.eye(n_y), 2, axis=0), np.eye(n_x))
    return np.kron(np.eye(3), np.vstack([along_x, along_y]))


@functools.cache
def _roughness(n_functions: tuple[int, int]) -> np.ndarray:
    """``R^T R`` of :func:`_second_differences`: the smoothness penalty's quadratic form (read-only,
    computed once per grid; its entries are small integers, exact whatever the BLAS)."""
    penalty = _second_differences(n_functions)
    roughness = penalty.T @ penalty
    roughness.setflags(write=False)
    return roughness
