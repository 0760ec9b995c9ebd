"""An axial-displacement reference computed from RF, independent of the package's B-mode tracker.

* :func:`load_deepuse_sequence` reads the DeepUSE in-vivo RF frames (layout in the data's README.md);
* :func:`deepuse_b_mode` makes the B-mode frames a tracker sees from them (envelope, 50 dB log
  compression, resampling to :data:`DEEPUSE_PIXEL_MM`);
* :func:`axial_displacement` estimates the axial displacement of RF A-line segments from one frame to
  another by normalised cross-correlation of the RF (time-delay estimation as in elastography), with the
  peak correlation of each window; :func:`compose` chains consecutive steps; :func:`band_summary`
  reduces an estimate to depth bands with the consistency measures the tests use.

Sign: a positive displacement moves the tissue deeper (away from the probe), as the tracker's dy.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy.ndimage import map_coordinates, median_filter
from scipy.signal import hilbert

from usdeform.sim.rf_compression import b_mode_from_rf

DEEPUSE_SEQUENCES = ("299", "300", "302", "304")
DEEPUSE_SAMPLE_MM = 0.02
"""Depth step of the DeepUSE RF samples, mm (the headers' ElementSpacing)."""
DEEPUSE_LINE_MM = 0.2
"""Spacing of the DeepUSE scan lines, mm (the headers' ElementSpacing; not confirmed independently)."""
DEEPUSE_SHAPE = (2000, 128)
DEEPUSE_PIXEL_MM = (0.08, 0.1)
"""(axial, lateral) pixel of the B-mode grid made from the DeepUSE RF: 4 RF samples deep (close to the real
phantom pair's 0.077 mm) and half a line wide (0.1 mm, near its 0.0745 mm), so 500 x 255 pixels."""
DEEPUSE_BMODE_SHAPE = (500, 255)


def load_deepuse_frame(folder: Path, sequence: str, k: int) -> np.ndarray:
    """(2000, 128) float32 RF of frame ``k`` (1..6) of a DeepUSE sequence, (depth sample, line)."""
    path = Path(folder) / sequence / f"frame{k}.raw"
    return np.fromfile(path, dtype="<f4").reshape(DEEPUSE_SHAPE)


def load_deepuse_sequence(folder: Path, sequence: str) -> np.ndarray:
    """(6, 2000, 128) float32 RF of frames 1..6 of a DeepUSE sequence."""
    return np.stack([load_deepuse_frame(folder, sequence, k) for k in range(1, 7)])


def deepuse_b_mode(rf_frames: np.ndarray, dynamic_range_db: float = 50.0) -> np.ndarray:
    """(n, 500, 255) uint8 B-mode frames of (n, 2000, 128) DeepUSE RF frames.

    One gain for the whole sequence (as a scanner): white is the 99.9th percentile of the first frame's
    envelope, so the frames differ only by the tissue's motion and the noise.
    """
    line_x = (np.arange(DEEPUSE_SHAPE[1]) - (DEEPUSE_SHAPE[1] - 1) / 2.0) * DEEPUSE_LINE_MM
    white = 20.0 * np.log10(np.percentile(np.abs(hilbert(rf_frames[0], axis=0)), 99.9))
    return np.stack(
        [
            b_mode_from_rf(
                rf,
                DEEPUSE_SAMPLE_MM,
                line_x,
                DEEPUSE_BMODE_SHAPE,
                DEEPUSE_PIXEL_MM,
                dynamic_range_db=dynamic_range_db,
                white_level_db=white,
            )
            for rf in rf_frames
        ]
    )


@dataclass(frozen=True)
class AxialReference:
    """Axial displacement of RF windows from frame A to frame B.

    Attributes:
        depth_mm: (windows,) depth of each window's centre in frame A, mm.
        displacement_mm: (windows, lines) axial displacement, mm (positive deeper).
        correlation: (windows, lines) normalised RF correlation at the peak (1 = identical echoes).
        sample_mm: depth step of the RF samples, mm.
    """

    depth_mm: np.ndarray
    displacement_mm: np.ndarray
    correlation: np.ndarray
    sample_mm: float

    def at(self, depth_mm: np.ndarray, line: np.ndarray) -> np.ndarray:
        """Displacement (mm) interpolated at depths (mm) and fractional line indices."""
        window = (np.asarray(depth_mm) - self.depth_mm[0]) / (self.depth_mm[1] - self.depth_mm[0])
        return map_coordinates(self.displacement_mm, [window, np.asarray(line)], order=1, mode="nearest")


def _ncc(windows: np.ndarray, segments: np.ndarray) -> np.ndarray:
    """Normalised cross-correlation of windows (K, n) with every position in segments (K, m >= n): (K, m - n + 1)."""
    n, m = windows.shape[1], segments.shape[1]
    a = windows - windows.mean(axis=1, keepdims=True)
    size = 1 << int(np.ceil(np.log2(n + m)))
    products = np.fft.irfft(np.conj(np.fft.rfft(a, size, axis=1)) * np.fft.rfft(segments, size, axis=1), size, axis=1)
    products = products[:, : m - n + 1]
    sums = np.concatenate([np.zeros((segments.shape[0], 1)), np.cumsum(segments, axis=1)], axis=1)
    squares = np.concatenate([np.zeros((segments.shape[0], 1)), np.cumsum(segments**2, axis=1)], axis=1)
    b_sum = sums[:, n:] - sums[:, :-n]
    b_var = np.maximum(squares[:, n:] - squares[:, :-n] - b_sum**2 / n, 0.0)
    a_var = np.sum(a**2, axis=1, keepdims=True)
    return products / np.sqrt(a_var * b_var + 1e-30)


def _peak(ncc: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Sub-sample position (parabola through the peak and its neighbours) and height of each row's maximum."""
    best = np.argmax(ncc, axis=1)
    rows = np.arange(ncc.shape[0])
    height = ncc[rows, best]
    left = ncc[rows, np.maximum(best - 1, 0)]
    right = ncc[rows, np.minimum(best + 1, ncc.shape[1] - 1)]
    curvature = left - 2.0 * height + right
    inner = (best > 0) & (best < ncc.shape[1] - 1) & (curvature < 0)
    offset = np.where(inner, 0.5 * (left - right) / np.where(inner, curvature, -1.0), 0.0)
    return best + offset, height


def _match(a: np.ndarray, b: np.ndarray, starts: np.ndarray, n: int, guess: np.ndarray, search: int):
    """Match windows a[start:start+n, line] in b within +-search samples of guess (windows, lines) samples."""
    lines = a.shape[1]
    line_index = np.arange(lines)[None, :, None]
    centre = np.rint(guess).astype(np.int64)
    windows = np.transpose(a[starts[:, None] + np.arange(n)[None, :]], (0, 2, 1))  # (W, lines, n)
    seg_index = (starts[:, None] + centre - search)[:, :, None] + np.arange(n + 2 * search)[None, None, :]
    valid_segment = (seg_index[:, :, 0] >= 0) & (seg_index[:, :, -1] < b.shape[0])
    segments = b[np.clip(seg_index, 0, b.shape[0] - 1), line_index]  # (W, lines, n + 2 search)
    ncc = _ncc(windows.reshape(-1, n), segments.reshape(-1, n + 2 * search))
    position, height = _peak(ncc)
    shift = centre + position.reshape(len(starts), lines) - search
    height = np.where(valid_segment, height.reshape(len(starts), lines), np.nan)
    return shift, height


def axial_displacement(
    rf_a: np.ndarray,
    rf_b: np.ndarray,
    sample_mm: float,
    *,
    window_mm: float = 1.5,
    step_mm: float = 0.5,
    max_shift_mm: float = 2.5,
    coarse_window_mm: float = 4.0,
) -> AxialReference:
    """Axial displacement (mm) of RF windows of ``rf_a`` (samples, lines) found in ``rf_b``.

    Two stages: (1) the envelopes of ``coarse_window_mm`` windows are matched over +-``max_shift_mm``
    (no carrier ambiguity) and smoothed across neighbouring windows and lines (median), giving a guess
    within a fraction of a wavelength; (2) twice, ``rf_b`` is warped by the current smooth estimate (which
    undoes most of the strain inside a window) and ``window_mm`` RF windows are matched within +-0.3 mm
    of it, the peak refined by a parabola. Windows are centred every ``step_mm`` from one window below
    the top to one above the bottom.
    """
    rf_a = np.asarray(rf_a, dtype=np.float64)
    rf_b = np.asarray(rf_b, dtype=np.float64)
    n_samples, lines = rf_a.shape
    n = round(window_mm / sample_mm)
    n_coarse = round(coarse_window_mm / sample_mm)
    step = round(step_mm / sample_mm)
    search = round(max_shift_mm / sample_mm)
    centres = np.arange(n_coarse // 2 + search // 4, n_samples - n_coarse // 2 - search // 4, step)
    depth_samples = np.arange(n_samples, dtype=np.float64)

    # The envelope is smooth: match it at every other sample.
    env_a, env_b = (np.abs(hilbert(rf, axis=0))[::2] for rf in (rf_a, rf_b))
    half = n_coarse // 4
    guess = np.zeros((centres.size, lines))
    shift, _ = _match(env_a, env_b, centres // 2 - half, 2 * half, guess, search // 2)
    shift = median_filter(np.nan_to_num(2.0 * shift), size=(5, 5), mode="nearest")
    fine_search = round(0.3 / sample_mm)
    for _ in range(2):
        smooth = median_filter(shift, size=(3, 5), mode="nearest")
        dense = np.stack([np.interp(depth_samples, centres, smooth[:, line]) for line in range(lines)], axis=1)
        warped = map_coordinates(
            rf_b, [depth_samples[:, None] + dense, np.broadcast_to(np.arange(lines), (n_samples, lines))], order=3
        )
        residual, height = _match(rf_a, warped, centres - n // 2, n, np.zeros((centres.size, lines)), fine_search)
        shift = smooth + residual
    return AxialReference(
        depth_mm=centres * sample_mm,
        displacement_mm=shift * sample_mm,
        correlation=height,
        sample_mm=sample_mm,
    )


def compose(steps: list[AxialReference]) -> AxialReference:
    """The displacement from the first frame to the last of a chain of consecutive steps (Lagrangian sum:
    each step is read where the tissue has moved by the steps before it); correlation: the lowest."""
    first = steps[0]
    total = first.displacement_mm.copy()
    correlation = first.correlation.copy()
    lines = np.broadcast_to(np.arange(total.shape[1]), total.shape)
    for step in steps[1:]:
        moved = first.depth_mm[:, None] + total
        total = total + step.at(moved, lines)
        window = (moved - step.depth_mm[0]) / (step.depth_mm[1] - step.depth_mm[0])
        correlation = np.fmin(correlation, map_coordinates(step.correlation, [window, lines], order=0, mode="nearest"))
    return AxialReference(first.depth_mm, total, correlation, first.sample_mm)


@dataclass(frozen=True)
class Band:
    """One depth band of a reference: where the reference agrees with itself."""

    top_mm: float
    bottom_mm: float
    median_mm: float  # median displacement over the band's windows and lines
    correlation: float  # median peak correlation
    neighbour_agreement: float  # fraction of estimates within tolerance of their 3 x 5 neighbourhood median
    chain_difference_mm: float  # |median(direct) - median(chain of consecutive steps)|, NaN without a chain


def band_summary(
    reference: AxialReference,
    band_mm: float = 5.0,
    *,
    lines: slice = slice(None),
    chain: AxialReference | None = None,
    tolerance_mm: float = 0.02,
) -> list[Band]:
    """Per ``band_mm`` depth band: the reference's median displacement and its consistency measures."""
    local = median_filter(reference.displacement_mm, size=(3, 5), mode="nearest")
    agree = np.abs(reference.displacement_mm - local) <= tolerance_mm
    bands = []
    for top in np.arange(0.0, reference.depth_mm[-1], band_mm):
        rows = (reference.depth_mm >= top) & (reference.depth_mm < top + band_mm)
        if rows.sum() < 2:
            continue
        values = reference.displacement_mm[rows][:, lines]
        median = float(np.median(values))
        chain_difference = float("nan")
        if chain is not None:
            chain_difference = abs(median - float(np.median(chain.displacement_mm[rows][:, lines])))
        bands.append(
            Band(
                top_mm=float(top),
                bottom_mm=float(top + band_mm),
                median_mm=median,
                correlation=float(np.nanmedian(reference.correlation[rows][:, lines])),
                neighbour_agreement=float(np.mean(agree[rows][:, lines])),
                chain_difference_mm=chain_difference,
            )
        )
    return bands
