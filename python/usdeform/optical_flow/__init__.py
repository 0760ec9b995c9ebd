"""Pixel displacement during a palpation: Lucas-Kanade tracking on a grid that is right or rejects (paper Sec. III-A).

:func:`track_palpation` measures where the tissue at each point of a regular grid in the lowest-force
(reference) frame has moved in every other frame. The points are tracked between consecutive frames in
increasing force and the motion is chained. Each step starts from an estimate that survives large motion
and decorrelated speckle: normalised-correlation block matching of ~50-pixel patches at half resolution
on a coarse grid, outliers replaced by their neighbours' median (a single step of 40 px, a dropped frame
or a fast press; pyramidal Lucas-Kanade alone locks onto a wrong speckle there and, on real data, kept
tracks of the wrong sign). Lucas-Kanade refines it from the previous frame, then from the latest key
frame, which keeps Lucas-Kanade's small per-step bias from adding up (on simulated palpations it halves
the error at the highest force). Every new key frame passes on the error of the track in its own frame,
so a new one is taken only once the speckle no longer correlates with the key frame's (the median
correlation of the surviving tracks' patches with their key-frame patches falls below
``key_frame_correlation``), or after ``key_frame_interval`` frames (a fixed short interval lets the
error grow with the frame rate). Where the speckle decorrelated during the step (the patches around
the track correlate less than ``decorrelated_below``),
the random error of a 21-pixel window is large (at the real data's decorrelation, 0.4 px median even for
Lucas-Kanade started at the true position: the second frame's speckle is partly new), and it falls with
the area the estimate draws on. There a wide window refines the track from the key frame, and after the
checks the track's step is replaced by the median step of its 3 x 3 grid neighbourhood. A wide window
spans a strained motion (under 5 % axial strain, 2.5 px across 51 px), which a translation-only window
turns into a random error of its own: the wide window's last refinement therefore lets it stretch and
shear with the tissue (Lucas-Kanade with an affine warp, its correlation that of the warped window), and
so does the small window's wherever the motion since the key frame varies across it by more than
``max_translation_spread_px`` (estimated from the block matching). A track is dropped, for this and all
later frames, when any of these checks fails on a step (:data:`REJECTION_REASONS`, in this order; the
first that fails is counted in ``TrackedDisplacements.rejected``):

* ``left_frame``: the point has left the frame;
* ``texture``: the point has too little texture to track at the start of the step: the square
  root of the smaller eigenvalue of the structure tensor averaged over ``texture_window_px`` (an
  RMS intensity gradient, gray levels per pixel) is below ``min_texture_ratio`` times its median
  over the frame. The anechoic lumen of a vessel has no speckle and fails this;
* ``lucas_kanade_status``: OpenCV's status flag (of any of the step's calls) is 0;
* ``block_matching``: the refined step departs from the block-matching estimate it started from by
  more than that estimate's uncertainty (2 px plus how much the block-matching flow varies across
  one of its patches) and ``block_matching_margin_px``, where refining it again from the estimate
  does not confirm it (Lucas-Kanade left its own evidence for another speckle: on a real compression
  pair of 5 % strain, pyramid levels above the remaining motion moved deep tracks about 20 px away,
  to the wrong sign); or the estimate is itself less certain than ``max_block_matching_uncertainty_px``
  (the blocks there matched noise, and tracks started from them followed it, coherently);
* ``forward_backward``: tracking the new position back to the earlier frame misses the start by
  more than ``max_forward_backward_px``;
* ``lucas_kanade_error``: the Lucas-Kanade error of that backward call (mean absolute
  difference of the two windows, gray levels) exceeds ``max_lk_error``;
* ``correlation``: the normalised correlation of the ``window_px`` patches around the point
  before and after the step (where an affine warp refined the track: of the key frame's window,
  ``wide_window_px`` for decorrelated tracks, and its warped match) is below ``min_correlation``;
* ``neighbours``: the step disagrees with the steps of the surviving tracks within two grid
  spacings: its distance from their median exceeds ``max_neighbour_deviation_px``, or
  ``max_neighbour_residual`` times their own scatter about it (the normalised median test of
  particle image velocimetry, Westerweel & Scarano 2005, with a 0.1 px noise level).

:func:`boundary_constraints` gives the paper's eq. 10 displacements of the top and bottom image rows
in the same :class:`TrackedDisplacements` structure, so that the two can be joined
(:meth:`TrackedDisplacements.with_boundary`, :func:`concatenate`) into the measured displacements
D^m of the regression (paper eq. 11).

The parts: :mod:`._displacements` (:class:`TrackedDisplacements`, the boundary rows),
:mod:`._frames` (the frames as the trackers take them, shared with :mod:`usdeform.fitting`),
:mod:`._block_matching` (the coarse motion and the normalised median test), :mod:`._lucas_kanade`
(the refinements, the patch correlation and the texture), :mod:`._settings` (:class:`TrackingSettings`, whose
fields are the knobs named here) and :mod:`._tracking` (:func:`track_palpation`).

Coordinates: points are (x, y) = (column, row) in pixels, origin at the top-left pixel's centre, y
pointing down into the tissue; displacements are (lateral, axial) = (dx, dy) in pixels.
"""

from __future__ import annotations

from ._displacements import REJECTION_REASONS, TrackedDisplacements, boundary_constraints, concatenate
from ._frames import as_uint8_frames, force_order
from ._lucas_kanade import window_offsets
from ._settings import TrackingSettings
from ._tracking import track_palpation

__all__ = [
    "REJECTION_REASONS",
    "TrackedDisplacements",
    "TrackingSettings",
    "as_uint8_frames",
    "boundary_constraints",
    "concatenate",
    "force_order",
    "track_palpation",
    "window_offsets",
]
