"""The fit report's figures: tracks per depth band, the field at the highest force, the held-out
residual by region."""

from __future__ import annotations

from pathlib import Path

import numpy as np
from matplotlib.figure import Figure

from ...optical_flow import REJECTION_REASONS
from ._assess import _predicted
from ._report import _REASON_TEXT, HELD_OUT_WARNING_PX, LATERAL_REGIONS, UNRECORDED, FitReport

_KEPT_COLOUR = "tab:green"


def _bands_figure(report: FitReport) -> Figure:
    """Per palpation, kept and dropped tracks per depth band, stacked by reason."""
    figure = Figure(figsize=(4.6 * len(report.palpations), 0.28 * len(report.bands) + 2.2))
    axes = np.atleast_1d(figure.subplots(1, len(report.palpations), sharey=True))
    names = [name for name in (*REJECTION_REASONS, UNRECORDED) if any(b.dropped.get(name) for b in report.bands)]
    colours = {name: f"C{index % 10}" for index, name in enumerate(n for n in (*REJECTION_REASONS, UNRECORDED))}
    colours = {name: ("tab:gray" if c == "C2" else c) for name, c in colours.items()}  # C2 is the kept green
    for axis, palpation in zip(axes, report.palpations, strict=True):
        centres = [np.mean(band.depth_mm) for band in palpation.bands]
        heights = [0.9 * (band.depth_mm[1] - band.depth_mm[0]) for band in palpation.bands]
        left = np.array([band.kept for band in palpation.bands], dtype=float)
        axis.barh(centres, left, height=heights, color=_KEPT_COLOUR, label="kept")
        for name in names:
            counts = np.array([band.dropped.get(name, 0) for band in palpation.bands], dtype=float)
            axis.barh(
                centres, counts, height=heights, left=left, color=colours[name], label=_REASON_TEXT.get(name, name)
            )
            left += counts
        axis.set(title=Path(palpation.name).name, xlabel="tracks", ylabel="depth below the probe (mm)")
        axis.title.set_fontsize(9)
        axis.grid(axis="x", alpha=0.3)
    axes[0].invert_yaxis()
    axes[-1].legend(fontsize=7, loc="lower right")
    figure.tight_layout()
    return figure


def _arrow_gain(moves_mm: np.ndarray, width_mm: float) -> float:
    """How many times longer than true to draw displacement arrows so that the longest (95th
    percentile) spans at most 8 % of the frame's width: 1, 2, 5, 10, 20 or 50."""
    length = float(np.percentile(np.linalg.norm(moves_mm, axis=-1), 95)) if len(moves_mm) else 0.0
    fitting = [gain for gain in (1.0, 2.0, 5.0, 10.0, 20.0, 50.0) if gain * length <= 0.08 * width_mm]
    return fitting[-1] if fitting else 1.0


def _field_figure(report: FitReport) -> Figure:
    """Per palpation at its highest force: tracked and fitted arrows on the frame, and the residual map."""
    fitted = report.fitted
    figure = Figure(figsize=(11, 4.6 * len(report.palpations)))
    axes = np.atleast_2d(figure.subplots(len(report.palpations), 2))
    for (arrows, residuals), palpation, measured, recording in zip(
        axes, report.palpations, fitted.measured, fitted.loading_recordings, strict=True
    ):
        tracked, row = measured.tracked, palpation.highest_force_row
        lateral, axial = palpation.pixel_size_mm
        rows, cols = recording.shape
        extent = (0.0, cols * lateral, rows * axial, 0.0)
        kept = tracked.valid[row] if len(tracked.frame_indices) else np.zeros(len(tracked.points_px), bool)
        points = np.flatnonzero(kept)
        model = _predicted(fitted.fit.fitted, measured.observations, points)[row]
        measured_px = tracked.displacements_px[row, points]
        x_mm, y_mm = tracked.points_px[points, 0] * lateral, tracked.points_px[points, 1] * axial
        frame = recording.frames[int(tracked.frame_indices[row])] if len(tracked.frame_indices) else recording.frames[0]
        arrows.imshow(frame, cmap="gray", extent=extent)
        gain = _arrow_gain(measured_px * [lateral, axial], extent[1])
        # The fitted arrows thinner, on top of the tracked ones: both show where they agree.
        for values, colour, width, label in (
            (measured_px, "yellow", 0.007, "tracked"),
            (model, "cyan", 0.003, "fitted"),
        ):
            arrows.quiver(
                x_mm, y_mm, values[:, 0] * lateral, values[:, 1] * axial, color=colour, angles="xy",
                scale_units="xy", scale=1 / gain, width=width, label=label,
            )  # fmt: skip
        arrows.legend(fontsize=7, loc="lower right")
        arrows.set(
            title=f"{Path(palpation.name).name}: {palpation.highest_force_n:.1f} N, {len(points)} of {len(kept)} "
            "tracks kept" + (f" (arrows x{gain:g})" if gain > 1 else ""),
            xlabel="lateral (mm)",
            ylabel="depth (mm)",
        )
        residuals.imshow(frame, cmap="gray", extent=extent, alpha=0.35)
        error = np.linalg.norm(measured_px - model, axis=-1)
        limit = max(float(np.percentile(error, 98)) if error.size else 0.0, 0.5)
        dots = residuals.scatter(x_mm, y_mm, c=error, cmap="magma_r", vmin=0, vmax=limit, s=22, edgecolors="0.3")
        dropped = np.flatnonzero(~kept)
        residuals.scatter(
            tracked.points_px[dropped, 0] * lateral, tracked.points_px[dropped, 1] * axial, marker="x",
            color="red", s=14, linewidths=0.8, label="dropped",
        )  # fmt: skip
        if len(dropped):
            residuals.legend(fontsize=7, loc="lower right")
        residuals.set(
            title=f"|tracked - fitted|: RMS {palpation.highest_force_rms_px:.2f} px "
            f"({palpation.highest_force_rms_mm:.3f} mm)",
            xlabel="lateral (mm)",
            ylabel="depth (mm)",
            xlim=extent[:2],
            ylim=extent[2:],
        )
        figure.colorbar(dots, ax=residuals, fraction=0.046, label="px")
        for axis in (arrows, residuals):
            axis.title.set_fontsize(9)
    figure.tight_layout()
    return figure


def _regions_figure(report: FitReport) -> Figure:
    """The held-out residual per depth band x lateral third, px (and mm) written in each cell."""
    n_bands = len(report.bands)
    grid = np.full((n_bands, 3), np.nan)
    labels: dict[tuple[int, int], str] = {}
    for region in report.regions:
        band = next(i for i, b in enumerate(report.bands) if b.depth_mm == region.depth_mm)
        third = LATERAL_REGIONS.index(region.lateral)
        grid[band, third] = region.held_out_px
        if np.isfinite(region.held_out_px):
            labels[band, third] = f"{region.held_out_px:.2f} px\n{region.held_out_mm:.3f} mm"
    figure = Figure(figsize=(6.4, 0.42 * n_bands + 1.6))
    axis = figure.subplots()
    top = report.bands[-1].depth_mm[1]
    finite = grid[np.isfinite(grid)]
    image = axis.imshow(
        np.ma.masked_invalid(grid),
        cmap="Reds",
        vmin=0,
        vmax=max(float(finite.max()) if finite.size else 0.0, HELD_OUT_WARNING_PX),
        aspect="auto",
        extent=(0, 3, top, 0),
    )
    for (band, third), text in labels.items():
        centre = float(np.mean(report.bands[band].depth_mm))
        axis.text(third + 0.5, centre, text, ha="center", va="center", fontsize=7)
    axis.set_xticks([0.5, 1.5, 2.5], [f"{name} third" for name in LATERAL_REGIONS])
    axis.set(ylabel="depth below the probe (mm)", title="held-out residual (RMS of |tracked - predicted|)")
    axis.title.set_fontsize(9)
    figure.colorbar(image, ax=axis, fraction=0.05, label="px")
    figure.tight_layout()
    return figure
