"""The tracking driver: :func:`track_palpation` (the method and its checks: :mod:`usdeform.optical_flow`)."""

from __future__ import annotations

import numpy as np

from ..errors import InputError
from ._block_matching import _coarse_flow, _nanmedian, _neighbourhoods, _normalised_median_test
from ._displacements import REJECTION_REASONS, TrackedDisplacements
from ._frames import as_uint8_frames, force_order
from ._lucas_kanade import _affine_lucas_kanade, _lucas_kanade, _patch_correlation, _pyramid_levels, _texture_map

_MIN_SEARCH_PX = 8.0  # smallest block-matching search range, full-resolution pixels
_ESCALATE_EDGE_FRACTION = 0.1  # search the whole range again when more peaks than this lie on the edge


def _grid_points(rows: int, cols: int, spacing_px: float, border_px: float) -> tuple[np.ndarray, tuple[int, int]]:
    """(N, 2) float64 (x, y) points of a regular grid, at least ``border_px`` from the frame's edges,
    row by row, and the grid's (rows, cols)."""
    xs = np.arange(border_px, cols - 1 - border_px + 1e-9, spacing_px)
    ys = np.arange(border_px, rows - 1 - border_px + 1e-9, spacing_px)
    if len(xs) == 0 or len(ys) == 0:
        raise InputError(
            f"grid_spacing_px={spacing_px}, border_px={border_px}: no grid point fits in a {rows} x {cols} frame"
        )
    grid_y, grid_x = np.meshgrid(ys, xs, indexing="ij")
    return np.column_stack([grid_x.ravel(), grid_y.ravel()]), (len(ys), len(xs))


def _window_sides(window_px: int | tuple[int, int], name: str) -> tuple[int, int]:
    """(width, height) of a window given as one odd side or an odd (width, height) pair; InputError otherwise."""
    sides = (window_px, window_px) if isinstance(window_px, int | np.integer) else tuple(window_px)
    if len(sides) != 2 or not all(isinstance(side, int | np.integer) and side >= 3 and side % 2 == 1 for side in sides):
        raise InputError(f"{name}: expected an odd integer >= 3 or a (width, height) pair of them, got {window_px!r}")
    return int(sides[0]), int(sides[1])


def track_palpation(
    frames: np.ndarray,
    force: np.ndarray | None = None,
    *,
    grid_spacing_px: float = 8.0,
    border_px: float | None = None,
    window_px: int | tuple[int, int] = 21,
    wide_window_px: int | tuple[int, int] = 51,
    decorrelated_below: float = 0.7,
    max_translation_spread_px: float = 0.5,
    pyramid_levels: int | None = None,
    key_frame_interval: int = 25,
    key_frame_correlation: float = 0.7,
    max_step_px: float = 48.0,
    block_matching_margin_px: float = 1.0,
    max_block_matching_uncertainty_px: float = 16.0,
    max_forward_backward_px: float = 1.0,
    max_lk_error: float = 30.0,
    texture_window_px: int = 9,
    min_texture_ratio: float = 0.5,
    min_correlation: float = 0.2,
    max_neighbour_residual: float = 3.0,
    max_neighbour_deviation_px: float = 2.0,
) -> TrackedDisplacements:
    """Track a grid of points from the lowest-force frame through a palpation; drop what cannot be trusted.

    Each step from one frame to the next (in increasing force) starts from a block-matching
    estimate of the motion that survives large steps and decorrelated speckle (normalised
    correlation of ~50-pixel patches at half resolution over +-``max_step_px``, outliers replaced by
    their neighbours' median), refines it with Lucas-Kanade from the current frame, then refines
    that by tracking directly from the latest key frame with it as the initial flow. A new key
    frame is taken once the median correlation of the surviving tracks' patches with the key frame's
    falls below ``key_frame_correlation``, or after ``key_frame_interval`` frames. Refining against a key
    frame keeps the small per-step bias of Lucas-Kanade (it underestimates subpixel motion) from adding
    up over many steps, while the key frame stays close enough for the speckle to correlate;
    ``key_frame_interval=1`` is plain frame-to-frame chaining. Tracks whose patches correlate less
    than ``decorrelated_below`` after the step are refined with the wider ``wide_window_px`` (its
    last refinement with an affine warp) and take the median step of their neighbourhood; where the
    motion varies across the small window by more than ``max_translation_spread_px`` it is refined
    with an affine warp too (see :mod:`usdeform.optical_flow`). The checks listed there then drop the
    tracks that are not trustworthy (``TrackedDisplacements.rejected`` counts them).

    Args:
        frames: (n, rows, cols) uint8 or float32 B-mode frames, n >= 2 (float32 is scaled linearly
            from the stack's [min, max] to 8 bits, since OpenCV's Lucas-Kanade works on 8-bit images).
        force: (n,) contact force per frame, N (any quantity increasing with compression, such as
            lambda_z, will do). Frames are tracked in increasing (stable-sorted) force from the
            lowest-force frame. None: the frames are taken to be in increasing force already.
        grid_spacing_px: spacing of the grid of tracked points, pixels.
        border_px: distance of the grid from the frame's edges, pixels; default half the window's
            smaller side.
        window_px: side (odd) of the Lucas-Kanade window and of the correlation check's patches, pixels,
            or their (width, height).
        wide_window_px: (width, height) (odd) of the window that refines the decorrelated tracks,
            pixels (one side for a square). On decorrelated speckle the random error falls with the
            window's area (benches/bench_tracking.py, at the real data's decorrelation: affine
            Lucas-Kanade started at the true position stops 0.45-0.59 px from it with a 21 x 21 window,
            0.16-0.20 px with 51 x 51, 0.14-0.16 px with 61 x 61); a window much larger than the
            structures in view (a vessel of 3 mm radius, 39 px at 0.077 mm) averages over motions
            no affine warp describes (there 61 x 61 kept 86 % of the tracks, 51 x 51 91 %).
        decorrelated_below: a track whose ``window_px`` patches correlate less than this after a
            step is decorrelated: the wide window refines it and its step becomes its
            neighbourhood's median (-1 turns both off). The default, 0.7 (about 1 / sqrt(2)), is
            where the factor sqrt(1 / rho^2 - 1) by which decorrelation scales the smallest
            possible speckle-tracking error (the Cramer-Rao bound of Walker & Trahey 1995, IEEE
            Trans. UFFC 42:301) reaches 1.
        max_translation_spread_px: where the motion since the key frame varies across the small window
            by more than this, pixels (the block matching's displacement gradient times the window's
            sides), the small window's Lucas-Kanade is refined with an affine warp. At 0.5 px the
            translation-only window misfits its own edges by a quarter pixel, the order of the error
            aimed at; ``inf`` turns it off.
        pyramid_levels: number of pyramid levels above the full-resolution image; None (the default)
            chooses, for each window and step, the fewest that reach the motion left after block
            matching (its uncertainty, or the whole search range where no block matched): 0 where
            block matching worked.
        key_frame_interval: most frames between two key frames (>= 1).
        key_frame_correlation: a new key frame is taken as soon as the median correlation of the surviving
            tracks' ``window_px`` patches with their key-frame patches falls below this; the default is
            ``decorrelated_below``'s, where the Cramer-Rao factor reaches 1.
        max_step_px: largest motion between two consecutive frames (in force) that is searched, pixels.
        block_matching_margin_px: how far a refined step may depart from the block-matching estimate
            it started from beyond that estimate's uncertainty (2 px plus the flow's variation across
            a block-matching patch), pixels (``inf`` turns the check off).
        max_block_matching_uncertainty_px: a track whose block-matching estimate is less certain than
            this, pixels, is dropped: a flow that varies by 14 px across one 50-pixel patch (28 % strain in
            one step) is not a tissue's, the blocks there matched noise (``inf`` turns the check off).
        max_forward_backward_px: largest forward-backward error of a step, pixels.
        max_lk_error: largest Lucas-Kanade error of a step (mean absolute window difference, gray levels).
        texture_window_px: side of the (odd) square over which the texture of a point is measured, pixels.
        min_texture_ratio: a point is trackable where its texture is at least this fraction of the
            median texture of the frame.
        min_correlation: smallest normalised correlation of a track's patches before and after a step.
        max_neighbour_residual: largest normalised median residual of a track's step against the
            steps of its neighbours on the grid (see :mod:`usdeform.optical_flow`); ``inf`` turns the check off.
        max_neighbour_deviation_px: largest distance of a track's step from the median step of its
            neighbours on the grid, pixels; ``inf`` turns the check off.

    Returns:
        :class:`TrackedDisplacements` with M = n - 1 frames in increasing force (``frame_indices``
        says which input frame each is) and ``reference_index`` the lowest-force frame.
    """
    images = as_uint8_frames(frames)
    n, rows, cols = images.shape
    order = force_order(force, n)
    window, wide_window = _window_sides(window_px, "window_px"), _window_sides(wide_window_px, "wide_window_px")
    if int(texture_window_px) != texture_window_px or texture_window_px < 3 or texture_window_px % 2 == 0:
        raise InputError(f"texture_window_px: expected an odd integer >= 3, got {texture_window_px!r}")
    if pyramid_levels is not None and (int(pyramid_levels) != pyramid_levels or pyramid_levels < 0):
        raise InputError(f"pyramid_levels: expected None or an integer >= 0, got {pyramid_levels!r}")
    if int(key_frame_interval) != key_frame_interval or key_frame_interval < 1:
        raise InputError(f"key_frame_interval: expected an integer >= 1, got {key_frame_interval!r}")
    for name, threshold in (
        ("grid_spacing_px", grid_spacing_px),
        ("max_step_px", max_step_px),
        ("block_matching_margin_px", block_matching_margin_px),
        ("max_block_matching_uncertainty_px", max_block_matching_uncertainty_px),
        ("max_forward_backward_px", max_forward_backward_px),
        ("max_lk_error", max_lk_error),
        ("max_neighbour_residual", max_neighbour_residual),
        ("max_neighbour_deviation_px", max_neighbour_deviation_px),
        ("max_translation_spread_px", max_translation_spread_px),
    ):
        if not (threshold > 0) or np.isnan(threshold) or (name == "max_step_px" and not np.isfinite(threshold)):
            raise InputError(f"{name}: expected a positive number, got {threshold!r}")
    if not (np.isfinite(min_texture_ratio) and min_texture_ratio >= 0):
        raise InputError(f"min_texture_ratio: expected a non-negative number, got {min_texture_ratio!r}")
    for name, bound in (
        ("min_correlation", min_correlation),
        ("decorrelated_below", decorrelated_below),
        ("key_frame_correlation", key_frame_correlation),
    ):
        if not (np.isfinite(bound) and -1.0 <= bound <= 1.0):
            raise InputError(f"{name}: expected a number in [-1, 1], got {bound!r}")
    border = float(min(window) // 2 if border_px is None else border_px)
    if not (np.isfinite(border) and border >= 0):
        raise InputError(f"border_px: expected a non-negative number of pixels, got {border_px!r}")

    points, grid_shape = _grid_points(rows, cols, float(grid_spacing_px), border)
    alive = np.ones(len(points), dtype=bool)
    current = points.astype(np.float32)[:, None, :]  # (N, 1, 2) subpixel positions in the latest frame
    key_step, key_positions = 0, current
    displacements = np.full((n - 1, len(points), 2), np.nan)
    valid = np.zeros((n - 1, len(points)), dtype=bool)
    rejected = {reason: np.zeros(n - 1, dtype=np.int64) for reason in REJECTION_REASONS}
    dropped_reason = np.full(len(points), -1, dtype=np.int64)
    dropped_at = np.full(len(points), -1, dtype=np.int64)
    search_px = float(max_step_px)
    for step in range(n - 1):
        before, after, key = images[order[step]], images[order[step + 1]], images[order[key_step]]
        texture = _texture_map(before, int(texture_window_px))
        start_cols = np.clip(np.rint(current[:, 0, 0]).astype(int), 0, cols - 1)
        start_rows = np.clip(np.rint(current[:, 0, 1]).astype(int), 0, rows - 1)
        textured = texture[start_rows, start_cols] >= min_texture_ratio * np.median(texture)

        coarse_flow = _coarse_flow(before, after, search_px)
        if search_px < max_step_px and coarse_flow.at_search_edge > _ESCALATE_EDGE_FRACTION:
            coarse_flow = _coarse_flow(before, after, float(max_step_px))
        # The next step is searched over twice this one's largest motion (a dropped frame doubles
        # it) plus a margin, and over the whole range when many peaks land on the edge of that.
        search_px = min(float(max_step_px), 2.0 * float(np.abs(coarse_flow.flow).max()) + _MIN_SEARCH_PX)
        coarse = coarse_flow.at(current[:, 0])
        initial = current + coarse[:, None, :]
        # Lucas-Kanade need only reach what block matching leaves uncertain (nearly all tracks' bound).
        uncertainty_px = coarse_flow.uncertainty_at(current[:, 0])
        # Where the blocks matched noise their flow varies wildly; no start there is evidence of anything.
        evidence = ~(uncertainty_px > max_block_matching_uncertainty_px) | (not coarse_flow.matched)
        starts = alive & evidence
        remaining_px = min(float(np.percentile(uncertainty_px[starts], 90)) if starts.any() else 0.0, search_px)
        levels, wide_levels = (
            (int(pyramid_levels),) * 2
            if pyramid_levels is not None
            else (_pyramid_levels(remaining_px, window), _pyramid_levels(remaining_px, wide_window))
        )
        predicted, predicted_ok, _ = _lucas_kanade(before, after, current, initial, window, levels)
        if key_step == step:
            tracked, tracked_ok = predicted.copy(), predicted_ok
        else:
            tracked, tracked_ok, _ = _lucas_kanade(key, after, key_positions, predicted, window, levels)
        correlation = _patch_correlation(before, after, current[:, 0], tracked[:, 0], window)
        # Where the speckle decorrelated, the small window's random error is large: refine those tracks with the
        # wide window (from the key frame, like the small one; OpenCV's translation-only window brings them within
        # reach of the affine one). Where the motion since the key frame varies by more than
        # ``max_translation_spread_px`` across the small window (estimated as this step's spread times the steps
        # since the key frame: a press goes one way), its translation-only model misfits: let it stretch.
        decorrelated = correlation < decorrelated_below
        strained = coarse_flow.spread_at(current[:, 0], window) * (step + 1 - key_step) > max_translation_spread_px
        wide, affine = np.flatnonzero(alive & decorrelated), np.flatnonzero(alive & strained & ~decorrelated)
        if len(wide):
            tracked[wide], wide_ok, _ = _lucas_kanade(
                key, after, key_positions[wide], tracked[wide], wide_window, wide_levels
            )
            tracked_ok[wide] &= wide_ok
        for group, group_window in ((wide, wide_window), (affine, window)):
            if len(group):
                tracked[group, 0], affine_ok, correlation[group] = _affine_lucas_kanade(
                    key, after, key_positions[group, 0], tracked[group, 0], group_window
                )
                tracked_ok[group] &= affine_ok
        # A step that left the block-matching estimate by more than the estimate's uncertainty is refined again
        # from the estimate, at full resolution with the wide window: kept where the two refinements agree (the
        # estimate was off), replaced where only the new one stays with the estimate (the first jumped to another
        # speckle), dropped where neither holds.
        tolerance_px = uncertainty_px + block_matching_margin_px
        departed = np.flatnonzero(alive & (np.linalg.norm(tracked - initial, axis=2).ravel() > tolerance_px))
        with_block_matching = np.ones(len(tracked), dtype=bool)
        if len(departed):
            again, again_ok, _ = _lucas_kanade(before, after, current[departed], initial[departed], wide_window, 0)
            stays = again_ok & (np.linalg.norm(again - initial[departed], axis=2).ravel() <= tolerance_px[departed])
            agrees = again_ok & (np.linalg.norm(again - tracked[departed], axis=2).ravel() <= max_forward_backward_px)
            replaced = departed[stays & ~agrees]
            tracked[replaced] = again[stays & ~agrees]
            correlation[replaced] = _patch_correlation(
                before, after, current[replaced, 0], tracked[replaced, 0], window
            )
            with_block_matching[departed[~stays & ~agrees]] = False
        uses_wide = np.zeros(len(tracked), dtype=bool)
        uses_wide[wide] = True
        back, back_ok, back_error = np.empty_like(tracked), np.empty(len(tracked), bool), np.empty(len(tracked))
        for group, group_window, group_levels in ((~uses_wide, window, levels), (uses_wide, wide_window, wide_levels)):
            if group.any():
                guess = tracked[group] - coarse[group, None, :]
                back[group], back_ok[group], back_error[group] = _lucas_kanade(
                    after, before, tracked[group], guess, group_window, group_levels
                )
        if len(wide):  # the way back like the way there (a small window's strain errs well within the check's 1 px)
            back[wide, 0], affine_ok, _ = _affine_lucas_kanade(
                after, before, tracked[wide, 0], back[wide, 0], wide_window
            )
            back_ok[wide] &= affine_ok
        x, y = tracked[:, 0, 0], tracked[:, 0, 1]
        inside = (x >= 0) & (x <= cols - 1) & (y >= 0) & (y <= rows - 1)
        forward_backward = np.linalg.norm(back - current, axis=2).ravel() <= max_forward_backward_px
        checks = {
            "left_frame": inside,
            "texture": textured,
            "lucas_kanade_status": predicted_ok & tracked_ok & back_ok,
            "block_matching": with_block_matching & evidence,
            "forward_backward": forward_backward,
            "lucas_kanade_error": back_error <= max_lk_error,
            "correlation": correlation >= min_correlation,
        }
        passed = alive.copy()
        for reason, ok in checks.items():
            failed = passed & ~ok
            rejected[reason][step] = np.count_nonzero(failed)
            dropped_reason[failed], dropped_at[failed] = REJECTION_REASONS.index(reason), step
            passed &= ok
        # Consistency: each surviving track's step against its surviving neighbours' steps.
        increments = np.where(passed[:, None], (tracked - current)[:, 0], np.nan).reshape((*grid_shape, 2))
        median, residual = _normalised_median_test(increments, 2, 0.1)
        deviation = np.linalg.norm(increments - median, axis=-1).ravel()
        # NaN (no neighbour at all: nothing to disagree with) passes.
        consistent = ~(residual.ravel() > max_neighbour_residual) & ~(deviation > max_neighbour_deviation_px)
        failed = passed & ~consistent
        rejected["neighbours"][step] = np.count_nonzero(failed)
        dropped_reason[failed], dropped_at[failed] = REJECTION_REASONS.index("neighbours"), step
        alive = passed & consistent
        # A decorrelated track's own step is noisy: take the median of the steps in its 3 x 3 neighbourhood
        # (itself included; per component: it keeps a linear motion and ignores a minority that moves
        # otherwise, such as tracks across a vessel wall).
        steps = np.where(alive[:, None], (tracked - current)[:, 0], np.nan).reshape((*grid_shape, 2))
        smoothed = alive & decorrelated
        if smoothed.any():
            neighbourhood_median = _nanmedian(_neighbourhoods(steps, 1)).reshape(-1, 2)  # NaN where none is alive
            tracked[smoothed, 0] = current[smoothed, 0] + neighbourhood_median[smoothed]
        current = np.where(alive[:, None, None], tracked, current)
        valid[step] = alive
        displacements[step, alive] = current[alive, 0].astype(np.float64) - points[alive]
        new_key = step + 1 - key_step >= key_frame_interval or not alive.any()
        if not new_key:  # the key frame's patches are compared only where the interval has not ended it already
            key_patches = _patch_correlation(key, after, key_positions[alive, 0], current[alive, 0], window)
            new_key = bool(np.median(key_patches) < key_frame_correlation)
        if new_key:
            key_step, key_positions = step + 1, current
    return TrackedDisplacements(
        points_px=points,
        displacements_px=displacements,
        valid=valid,
        frame_indices=order[1:],
        reference_index=int(order[0]),
        frame_shape=(rows, cols),
        rejected=rejected,
        dropped_reason=dropped_reason,
        dropped_at=dropped_at,
    )
