"""The tracking driver: :func:`track_palpation` (the method and its checks: :mod:`usdeform.optical_flow`)."""

from __future__ import annotations

import numpy as np

from ..errors import InputError
from ._block_matching import _coarse_flow, _nanmedian, _neighbourhoods, _normalised_median_test
from ._displacements import REJECTION_REASONS, TrackedDisplacements
from ._frames import as_uint8_frames, force_order
from ._lucas_kanade import _affine_lucas_kanade, _lucas_kanade, _patch_correlation, _pyramid_levels, _texture_map
from ._settings import TrackingSettings

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


def track_palpation(
    frames: np.ndarray,
    force: np.ndarray | None = None,
    settings: TrackingSettings = TrackingSettings(),
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
        settings: the grid, the windows, the key frames and the checks' thresholds (the names above are
            its fields).

    Returns:
        :class:`TrackedDisplacements` with M = n - 1 frames in increasing force (``frame_indices``
        says which input frame each is) and ``reference_index`` the lowest-force frame.
    """
    images = as_uint8_frames(frames)
    n, rows, cols = images.shape
    order = force_order(force, n)
    window, wide_window = settings.window_sides_px, settings.wide_window_sides_px
    border = settings.grid_border_px

    points, grid_shape = _grid_points(rows, cols, float(settings.grid_spacing_px), border)
    alive = np.ones(len(points), dtype=bool)
    current = points.astype(np.float32)[:, None, :]  # (N, 1, 2) subpixel positions in the latest frame
    key_step, key_positions = 0, current
    displacements = np.full((n - 1, len(points), 2), np.nan)
    valid = np.zeros((n - 1, len(points)), dtype=bool)
    rejected = {reason: np.zeros(n - 1, dtype=np.int64) for reason in REJECTION_REASONS}
    dropped_reason = np.full(len(points), -1, dtype=np.int64)
    dropped_at = np.full(len(points), -1, dtype=np.int64)
    search_px = float(settings.max_step_px)
    for step in range(n - 1):
        before, after, key = images[order[step]], images[order[step + 1]], images[order[key_step]]
        texture = _texture_map(before, int(settings.texture_window_px))
        start_cols = np.clip(np.rint(current[:, 0, 0]).astype(int), 0, cols - 1)
        start_rows = np.clip(np.rint(current[:, 0, 1]).astype(int), 0, rows - 1)
        textured = texture[start_rows, start_cols] >= settings.min_texture_ratio * np.median(texture)

        coarse_flow = _coarse_flow(before, after, search_px)
        if search_px < settings.max_step_px and coarse_flow.at_search_edge > _ESCALATE_EDGE_FRACTION:
            coarse_flow = _coarse_flow(before, after, float(settings.max_step_px))
        # The next step is searched over twice this one's largest motion (a dropped frame doubles
        # it) plus a margin, and over the whole range when many peaks land on the edge of that.
        search_px = min(float(settings.max_step_px), 2.0 * float(np.abs(coarse_flow.flow).max()) + _MIN_SEARCH_PX)
        coarse = coarse_flow.at(current[:, 0])
        initial = current + coarse[:, None, :]
        # Lucas-Kanade need only reach what block matching leaves uncertain (nearly all tracks' bound).
        uncertainty_px = coarse_flow.uncertainty_at(current[:, 0])
        # Where the blocks matched noise their flow varies wildly; no start there is evidence of anything.
        evidence = ~(uncertainty_px > settings.max_block_matching_uncertainty_px) | (not coarse_flow.matched)
        starts = alive & evidence
        remaining_px = min(float(np.percentile(uncertainty_px[starts], 90)) if starts.any() else 0.0, search_px)
        levels, wide_levels = (
            (int(settings.pyramid_levels),) * 2
            if settings.pyramid_levels is not None
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
        decorrelated = correlation < settings.decorrelated_below
        strained = (
            coarse_flow.spread_at(current[:, 0], window) * (step + 1 - key_step) > settings.max_translation_spread_px
        )
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
        tolerance_px = uncertainty_px + settings.block_matching_margin_px
        departed = np.flatnonzero(alive & (np.linalg.norm(tracked - initial, axis=2).ravel() > tolerance_px))
        with_block_matching = np.ones(len(tracked), dtype=bool)
        if len(departed):
            again, again_ok, _ = _lucas_kanade(before, after, current[departed], initial[departed], wide_window, 0)
            stays = again_ok & (np.linalg.norm(again - initial[departed], axis=2).ravel() <= tolerance_px[departed])
            agrees = again_ok & (
                np.linalg.norm(again - tracked[departed], axis=2).ravel() <= settings.max_forward_backward_px
            )
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
        forward_backward = np.linalg.norm(back - current, axis=2).ravel() <= settings.max_forward_backward_px
        checks = {
            "left_frame": inside,
            "texture": textured,
            "lucas_kanade_status": predicted_ok & tracked_ok & back_ok,
            "block_matching": with_block_matching & evidence,
            "forward_backward": forward_backward,
            "lucas_kanade_error": back_error <= settings.max_lk_error,
            "correlation": correlation >= settings.min_correlation,
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
        consistent = ~(residual.ravel() > settings.max_neighbour_residual) & ~(
            deviation > settings.max_neighbour_deviation_px
        )
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
        new_key = step + 1 - key_step >= settings.key_frame_interval or not alive.any()
        if not new_key:  # the key frame's patches are compared only where the interval has not ended it already
            key_patches = _patch_correlation(key, after, key_positions[alive, 0], current[alive, 0], window)
            new_key = bool(np.median(key_patches) < settings.key_frame_correlation)
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
