"""The tracker's tuning knobs: :class:`TrackingSettings` (what each check does: :mod:`usdeform.optical_flow`)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..errors import InputError


def _window_sides(window_px: int | tuple[int, int], name: str) -> tuple[int, int]:
    """(width, height) of a window given as one odd side or an odd (width, height) pair; InputError otherwise."""
    sides = (window_px, window_px) if isinstance(window_px, int | np.integer) else tuple(window_px)
    if len(sides) != 2 or not all(isinstance(side, int | np.integer) and side >= 3 and side % 2 == 1 for side in sides):
        raise InputError(f"{name}: expected an odd integer >= 3 or a (width, height) pair of them, got {window_px!r}")
    return int(sides[0]), int(sides[1])


@dataclass(frozen=True)
class TrackingSettings:
    """How :func:`~usdeform.optical_flow.track_palpation` tracks and which tracks it drops; the defaults are
    the recommended settings. Lengths in pixels. InputError naming the field for a value out of range."""

    #: Spacing of the grid of tracked points, pixels.
    grid_spacing_px: float = 8.0
    #: Distance of the grid from the frame's edges, pixels; None: half the smaller side of ``window_px``.
    border_px: float | None = None
    #: Side (odd) of the Lucas-Kanade window and of the correlation check's patches, pixels, or their
    #: (width, height).
    window_px: int | tuple[int, int] = 21
    #: (width, height) (odd) of the window that refines the decorrelated tracks, pixels (one side for a
    #: square). On decorrelated speckle the random error falls with the window's area (benches/bench_tracking.py,
    #: at the real data's decorrelation: affine Lucas-Kanade started at the true position stops 0.45-0.59 px
    #: from it with a 21 x 21 window, 0.16-0.20 px with 51 x 51, 0.14-0.16 px with 61 x 61); a window much
    #: larger than the structures in view (a vessel of 3 mm radius, 39 px at 0.077 mm) averages over motions
    #: no affine warp describes (there 61 x 61 kept 86 % of the tracks, 51 x 51 91 %).
    wide_window_px: int | tuple[int, int] = 51
    #: A track whose ``window_px`` patches correlate less than this after a step is decorrelated: the wide
    #: window refines it and its step becomes its neighbourhood's median (-1 turns both off). 0.7 (about
    #: 1 / sqrt(2)) is where the factor sqrt(1 / rho^2 - 1) by which decorrelation scales the smallest
    #: possible speckle-tracking error (the Cramer-Rao bound of Walker & Trahey 1995, IEEE Trans. UFFC
    #: 42:301) reaches 1.
    decorrelated_below: float = 0.7
    #: Where the motion since the key frame varies across the small window by more than this, pixels (the
    #: block matching's displacement gradient times the window's sides), the small window's Lucas-Kanade is
    #: refined with an affine warp. At 0.5 px the translation-only window misfits its own edges by a quarter
    #: pixel, the order of the error aimed at; ``inf`` turns it off.
    max_translation_spread_px: float = 0.5
    #: Number of pyramid levels above the full-resolution image; None chooses, for each window and step,
    #: the fewest that reach the motion left after block matching (its uncertainty, or the whole search
    #: range where no block matched): 0 where block matching worked.
    pyramid_levels: int | None = None
    #: Most frames between two key frames (>= 1; 1 is plain frame-to-frame chaining).
    key_frame_interval: int = 25
    #: A new key frame is taken as soon as the median correlation of the surviving tracks' ``window_px``
    #: patches with their key-frame patches falls below this; the default is ``decorrelated_below``'s, where
    #: the Cramer-Rao factor reaches 1.
    key_frame_correlation: float = 0.7
    #: Largest motion between two consecutive frames (in force) that is searched, pixels (finite).
    max_step_px: float = 48.0
    #: How far a refined step may depart from the block-matching estimate it started from beyond that
    #: estimate's uncertainty (2 px plus the flow's variation across a block-matching patch), pixels
    #: (``inf`` turns the check off).
    block_matching_margin_px: float = 1.0
    #: A track whose block-matching estimate is less certain than this, pixels, is dropped: a flow that
    #: varies by 14 px across one 50-pixel patch (28 % strain in one step) is not a tissue's, the blocks
    #: there matched noise (``inf`` turns the check off).
    max_block_matching_uncertainty_px: float = 16.0
    #: Largest forward-backward error of a step, pixels.
    max_forward_backward_px: float = 1.0
    #: Largest Lucas-Kanade error of a step (mean absolute window difference), gray levels.
    max_lk_error: float = 30.0
    #: Side (odd) of the square over which the texture of a point is measured, pixels.
    texture_window_px: int = 9
    #: A point is trackable where its texture is at least this fraction of the median texture of the frame.
    min_texture_ratio: float = 0.5
    #: Smallest normalised correlation of a track's patches before and after a step.
    min_correlation: float = 0.2
    #: Largest normalised median residual of a track's step against the steps of its neighbours on the
    #: grid (see :mod:`usdeform.optical_flow`); ``inf`` turns the check off.
    max_neighbour_residual: float = 3.0
    #: Largest distance of a track's step from the median step of its neighbours on the grid, pixels;
    #: ``inf`` turns the check off.
    max_neighbour_deviation_px: float = 2.0

    def __post_init__(self) -> None:
        _window_sides(self.window_px, "window_px")
        _window_sides(self.wide_window_px, "wide_window_px")
        texture_window_px = self.texture_window_px
        if int(texture_window_px) != texture_window_px or texture_window_px < 3 or texture_window_px % 2 == 0:
            raise InputError(f"texture_window_px: expected an odd integer >= 3, got {texture_window_px!r}")
        pyramid_levels = self.pyramid_levels
        if pyramid_levels is not None and (int(pyramid_levels) != pyramid_levels or pyramid_levels < 0):
            raise InputError(f"pyramid_levels: expected None or an integer >= 0, got {pyramid_levels!r}")
        key_frame_interval = self.key_frame_interval
        if int(key_frame_interval) != key_frame_interval or key_frame_interval < 1:
            raise InputError(f"key_frame_interval: expected an integer >= 1, got {key_frame_interval!r}")
        for name in (
            "grid_spacing_px",
            "max_step_px",
            "block_matching_margin_px",
            "max_block_matching_uncertainty_px",
            "max_forward_backward_px",
            "max_lk_error",
            "max_neighbour_residual",
            "max_neighbour_deviation_px",
            "max_translation_spread_px",
        ):
            threshold = getattr(self, name)
            if not (threshold > 0) or np.isnan(threshold) or (name == "max_step_px" and not np.isfinite(threshold)):
                raise InputError(f"{name}: expected a positive number, got {threshold!r}")
        if not (np.isfinite(self.min_texture_ratio) and self.min_texture_ratio >= 0):
            raise InputError(f"min_texture_ratio: expected a non-negative number, got {self.min_texture_ratio!r}")
        for name in ("min_correlation", "decorrelated_below", "key_frame_correlation"):
            bound = getattr(self, name)
            if not (np.isfinite(bound) and -1.0 <= bound <= 1.0):
                raise InputError(f"{name}: expected a number in [-1, 1], got {bound!r}")
        border = self.grid_border_px
        if not (np.isfinite(border) and border >= 0):
            raise InputError(f"border_px: expected a non-negative number of pixels, got {self.border_px!r}")

    @property
    def window_sides_px(self) -> tuple[int, int]:
        """(width, height) of the Lucas-Kanade window, pixels."""
        return _window_sides(self.window_px, "window_px")

    @property
    def wide_window_sides_px(self) -> tuple[int, int]:
        """(width, height) of the wide window, pixels."""
        return _window_sides(self.wide_window_px, "wide_window_px")

    @property
    def grid_border_px(self) -> float:
        """Distance of the grid from the frame's edges, pixels (``border_px``, or half the window's smaller side)."""
        return float(min(self.window_sides_px) // 2 if self.border_px is None else self.border_px)
