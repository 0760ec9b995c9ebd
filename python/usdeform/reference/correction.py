"""NumPy twins of the correction kernels: the model's field, the force integrals and the warps."""

from __future__ import annotations

import numpy as np

from ..errors import InputError
from ..options import Integration
from ..regression import DisplacementModel, Normalization, StiffnessProfile, VesselAnchor, VesselAnchoredModel


def _pixel_grid(shape: tuple[int, int], normalization: Normalization) -> tuple[np.ndarray, np.ndarray]:
    rows, cols = shape
    y, x = np.mgrid[0:rows, 0:cols].astype(np.float64)
    return x / normalization.x_scale, y / normalization.y_scale


def field_for_terms(
    model: DisplacementModel, shape: tuple[int, int], h_terms: tuple[float, float, float]
) -> np.ndarray:
    """The model's field on a ``(rows, cols)`` pixel grid for the force terms ``h_terms`` (the
    normalised integrals of ``1``, ``h``, ``h^2``, or ``(1, h_n, h_n^2)`` for the rate), (2, rows, cols)
    pixels. The field is linear in the terms."""
    normalization = model.normalization
    x_n, y_n = _pixel_grid(shape, normalization)
    field = np.einsum("ct,t...->c...", model.coefficients.reshape(2, -1), model.spatial_vector(x_n, y_n, h_terms))
    field[0] *= normalization.lateral_scale
    field[1] *= normalization.axial_scale
    return field


def regression_rate(model: DisplacementModel, h_mm: float, shape: tuple[int, int]) -> np.ndarray:
    """``d(x, y, h) = K M(x, y, h)`` on a pixel grid, (2, rows, cols), either basis."""
    h_n = h_mm / model.normalization.h_scale
    return field_for_terms(model, shape, (1.0, h_n, h_n**2))


#: Gauss-Legendre nodes and weights on [-1, 1] of the force-integral twin.
_NODES, _WEIGHTS = np.polynomial.legendre.leggauss(64)


def _gauss(integrand, lower: float, upper: float) -> float:
    """``int_lower^upper integrand`` by 64-point Gauss-Legendre quadrature."""
    half = 0.5 * (upper - lower)
    return float(half * np.sum(_WEIGHTS * integrand(lower + half * (_NODES + 1.0))))


def stiffness_integral(profile: StiffnessProfile, force_n: float, p: int, q: int) -> float:
    """``int_0^F f^p / k(f)^q df`` by quadrature, ``k = sqrt(c2^2 + 4 c1 (f - c3))`` from the
    palpation start ``c3`` on and ``c2`` below it. Below the start the integrand is a polynomial
    (integrated exactly); above it the integral is taken over ``s = ln(k / c2)``, where it is smooth
    (``f = c3 + c2 lambda + c1 lambda^2``, ``lambda = c2 expm1(s) / (2 c1)``, ``df = k dlambda``,
    ``dlambda = k ds / (2 c1)``)."""
    c1, c2, c3 = profile.as_tuple()
    lower, upper, sign = (0.0, force_n, 1.0) if force_n >= 0 else (force_n, 0.0, -1.0)
    total = 0.0
    if lower < c3 or upper > c3:
        if c2 <= 0 or (upper > c3 and c2**2 + 4 * c1 * (upper - c3) <= 0):
            raise InputError(f"profiles: the stiffness of {profile.as_tuple()} is not positive on [{lower}, {upper}] N")
    if lower < c3:
        total += _gauss(lambda f: f**p / c2**q, lower, min(upper, c3))
    if upper > c3:
        start = max(lower, c3)
        if abs(4 * c1 * (upper - c3)) <= 1e-3 * c2**2:
            # Nearly linear (k changes by under 0.05 %): smooth in f itself, and 1 / c1 in the
            # substitution below would overflow for a subnormal c1.
            total += _gauss(lambda f: f**p / np.sqrt(c2**2 + 4 * c1 * (f - c3)) ** q, start, upper)
        else:

            def integrand(s: np.ndarray) -> np.ndarray:
                stiffness = c2 * np.exp(s)
                displacement = c2 * np.expm1(s) / (2 * c1)
                force = c3 + c2 * displacement + c1 * displacement**2
                return force**p * stiffness ** (2 - q) / (2 * c1)

            log_stiffness = [0.5 * np.log1p(4 * c1 * (f - c3) / c2**2) for f in (start, upper)]
            total += _gauss(integrand, *log_stiffness)
    return sign * total


def force_integrals(
    force_n: float,
    profile: StiffnessProfile,
    normalization: Normalization,
    integration: Integration = "force",
) -> tuple[float, float, float]:
    """Normalised integrals of ``1``, ``h`` and ``h^2`` (``h = f / k(f)``) from 0 to ``force_n``
    (paper eq. 8): over force, or over probe displacement (``dlambda = df / k``, normalised by
    ``h_scale``); by quadrature (:func:`stiffness_integral`), where the kernel has a closed form."""
    extra = 1 if integration == "displacement" else 0
    integral_1, integral_h, integral_h2 = (stiffness_integral(profile, force_n, p, p + extra) for p in range(3))
    n = normalization
    scale = n.h_scale if integration == "displacement" else n.force_scale
    return (integral_1 / scale, integral_h / (n.h_scale * scale), integral_h2 / (n.h_scale**2 * scale))


def integrated_displacement(
    model: DisplacementModel, force_n: float, profile: StiffnessProfile, shape: tuple[int, int]
) -> np.ndarray:
    """``D(x, y, F) = int_0^F K M(x, y, F'/k) dF'`` on a pixel grid, (2, rows, cols) pixels (either
    basis); force coupling replaces ``profile`` by 1 N/mm."""
    coupled = profile if model.coupling == "stiffness" else StiffnessProfile.UNIT
    terms = force_integrals(force_n, coupled, model.normalization, model.integration)
    return field_for_terms(model, shape, terms)


def inside_frame(x: np.ndarray, y: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    """Whether ``(x, y)`` lies in ``[0, cols-1] x [0, rows-1]``."""
    rows, cols = shape
    return (x >= 0) & (y >= 0) & (x <= cols - 1) & (y <= rows - 1)


def bilinear_samples(frame: np.ndarray, x: np.ndarray, y: np.ndarray, fill: float) -> np.ndarray:
    """Sample ``frame`` at ``(x, y)``; ``fill`` outside ``[0, cols-1] x [0, rows-1]``."""
    rows, cols = frame.shape
    inside = inside_frame(x, y, frame.shape)
    xs, ys = np.where(inside, x, 0.0), np.where(inside, y, 0.0)
    x0 = np.minimum(np.floor(xs).astype(np.int64), max(cols - 2, 0))
    y0 = np.minimum(np.floor(ys).astype(np.int64), max(rows - 2, 0))
    x1, y1 = np.minimum(x0 + 1, cols - 1), np.minimum(y0 + 1, rows - 1)
    fx, fy = xs - x0, ys - y0
    source = frame.astype(np.float64)
    top = source[y0, x0] * (1 - fx) + source[y0, x1] * fx
    bottom = source[y1, x0] * (1 - fx) + source[y1, x1] * fx
    return np.where(inside, top * (1 - fy) + bottom * fy, fill)


def warp_frames(
    frames: np.ndarray,
    forces: np.ndarray,
    profiles: np.ndarray,
    model: DisplacementModel,
    *,
    fill: float = 0.0,
    return_mask: bool = False,
) -> np.ndarray | tuple[np.ndarray, np.ndarray]:
    """Backward-map each frame to zero force: output (x, y) = frame at (x, y) + D(x, y, F_frame);
    with ``return_mask`` also the validity mask (True where the source lies inside the frame)."""
    out = np.empty_like(frames)
    valid = np.empty(frames.shape, dtype=bool)
    for index, frame in enumerate(frames):
        profile = StiffnessProfile(*profiles[index])
        field = integrated_displacement(model, float(forces[index]), profile, frame.shape)
        out[index], valid[index] = warp_frame(frame, field, fill)
    return (out, valid) if return_mask else out


def warp_frame(frame: np.ndarray, displacement: np.ndarray, fill: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """One ``frame`` backward-mapped by ``displacement`` (2, rows, cols; lateral, axial; pixels):
    bilinear, ``fill`` outside, uint8 rounded half up; and the validity mask (source inside the frame)."""
    rows, cols = frame.shape
    y, x = np.mgrid[0:rows, 0:cols].astype(np.float64)
    source_x, source_y = x + displacement[0], y + displacement[1]
    values = bilinear_samples(frame, source_x, source_y, fill)
    if frame.dtype == np.uint8:
        values = np.clip(np.floor(values + 0.5), 0, 255)
    return values.astype(frame.dtype), inside_frame(source_x, source_y, (rows, cols))


def anchored_displacement(
    model: VesselAnchoredModel,
    force_n: float,
    profile: StiffnessProfile,
    lumen: VesselAnchor | None,
    window: tuple[slice, slice] | None = None,
) -> np.ndarray:
    """``D(x, y, F)`` of a vessel-anchored model on ``window`` (a row and a column slice; None: the
    frame), its vessel part on ``lumen`` (None: the image part alone): (2, window rows, window
    columns), pixels. The image part by :func:`integrated_displacement`, the vessel part by the
    model's own NumPy :meth:`~usdeform.regression.VesselAnchoredModel.vessel_displacement`."""
    shape = model.frame_shape
    rows, cols = window or (slice(0, shape[0]), slice(0, shape[1]))
    field = integrated_displacement(model.image_model, force_n, profile, shape)[:, rows, cols]
    if lumen is None:
        return field
    return field + model.vessel_displacement(force_n, profile, shape, lumen, window=(rows, cols))


def warp_anchored_frames(
    frames: np.ndarray,
    forces: np.ndarray,
    profiles: np.ndarray,
    model: VesselAnchoredModel,
    anchors: np.ndarray,
    *,
    fill: float = 0.0,
    scales: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Each frame backward-mapped by :func:`anchored_displacement` with the vessel part on its row of
    ``anchors`` ((n_frames, 3) of (x, y, radius), pixels), that part scaled by its frame's entry of
    ``scales`` ((n_frames,); None: all 1): the frames and the validity mask."""
    out, valid = np.empty_like(frames), np.empty(frames.shape, dtype=bool)
    for index, frame in enumerate(frames):
        lumen = VesselAnchor(tuple(anchors[index, :2]), anchors[index, 2])
        profile = StiffnessProfile(*profiles[index])
        field = anchored_displacement(model, float(forces[index]), profile, lumen)
        if scales is not None and scales[index] != 1.0:
            image = anchored_displacement(model, float(forces[index]), profile, None)
            field = image + scales[index] * (field - image)
        out[index], valid[index] = warp_frame(frame, field, fill)
    return out, valid


#: Smallest trilinear weight with which a pixel updates a voxel under linear maximum compounding, as
#: PLUS's trilinear maximum (core ``compound::MAXIMUM_MIN_WEIGHT``).
