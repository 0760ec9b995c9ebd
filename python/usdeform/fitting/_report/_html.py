"""Writing a fit report: ``report.html`` (self-contained) and ``report.json`` (:func:`write_fit_report`)."""

from __future__ import annotations

import html
import json
from pathlib import Path

import numpy as np

from ..._files import atomic_output, outputs_together
from ._report import _REASON_TEXT, FitReport


def _band_rows(report: FitReport) -> list[tuple[str, ...]]:
    return [
        (
            f"{band.depth_mm[0]:g}-{band.depth_mm[1]:g}",
            str(band.tracks),
            str(band.kept),
            f"{band.dropped_fraction:.0%}" if band.tracks else "",
            ", ".join(f"{_REASON_TEXT.get(name, name)} {count}" for name, count in band.dropped.items() if count),
        )
        for band in report.bands
    ]


def _summary(report: FitReport) -> str:
    n_tracks = sum(band.tracks for band in report.bands)
    kept = sum(band.kept for band in report.bands)
    document = report.to_json()["cross_validation"]
    held = document["held_out_rms_px"]
    overall = (
        f"; predicted from the other regions, the tracks are off by {held:.2f} px RMS "
        f"({document['held_out_rms_mm']:.3f} mm)"
        if held is not None
        else ""
    )
    head = (
        f"{len(report.palpations)} palpation{'s' if len(report.palpations) > 1 else ''}: {kept} of {n_tracks} tracks "
        f"kept to the highest force{overall}. "
    )
    if not report.warnings:
        return html.escape(head + "No warnings: every depth band kept most of its tracks, the stiffness fits hold "
                           "and the cross-validated residual is small everywhere.")  # fmt: skip
    items = "".join(f"<li>{html.escape(warning)}</li>" for warning in report.warnings)
    return f"{html.escape(head)}Warnings:<ul>{items}</ul>"


def _lumens_section(report: FitReport) -> list[str]:
    """The palpated lumens' table (none without lumens)."""
    from ..._html_report import table
    from ...correction import DEPTH_MARGIN_RADII, RADIUS_MARGIN_FRACTION

    lumens = report.palpated_lumens()
    if not lumens:
        return []
    rows = [
        (
            row["palpation"],
            "main" if row["vessel"] == 0 else f"further {row['vessel']}",
            f"{row['depth_mm']:.1f}",
            f"{row['radius_mm']:.2f}",
        )
        for row in lumens
    ]
    return [
        "<h2>Palpated lumens</h2><p>The lumens each palpation showed at contact: the model learnt each vessel's "
        "collapse at these depths and radii. <code>usdeform correct</code> warns for sweep frames whose lumen lies "
        f"beyond them (by more than {DEPTH_MARGIN_RADII:g} of their radius in depth, or {RADIUS_MARGIN_FRACTION:.0%} "
        "in radius): palpate where the vessel is deepest, shallowest, widest and narrowest.</p>",
        table(("palpation", "vessel", "depth (mm)", "radius (mm)"), rows),
    ]


def write_fit_report(report: FitReport, out_dir: str | Path) -> tuple[Path, Path]:
    """Write ``report`` as ``out_dir/report.html`` (self-contained) and ``out_dir/report.json``; the
    folder is created if missing; both files replace the old ones together, or neither does (they
    join an enclosing :func:`~usdeform._files.outputs_together` block). Returns the two paths."""
    # Matplotlib (0.5 s to import) is loaded only when a report is written, not on every fit.
    from ..._html_report import page, section, stiffness_figure, table
    from ._figures import _bands_figure, _field_figure, _regions_figure

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    fit = report.fitted.fit
    stiffness_rows = [
        (
            palpation.name,
            *(f"{palpation.r_squared[order]:.4f}" for order in sorted(palpation.r_squared)),
            "{:.0f} ± {:.0f}".format(*palpation.stiffness_n_per_m),
        )
        for palpation in report.palpations
    ]
    orders = sorted(report.palpations[0].r_squared)
    region_rows = [
        (
            f"{region.depth_mm[0]:g}-{region.depth_mm[1]:g}",
            region.lateral,
            str(region.points),
            str(region.samples),
            *(f"{value:.2f}" if np.isfinite(value) else "" for value in (region.held_out_px, region.fitted_px)),
            *(f"{value:.3f}" if np.isfinite(value) else "" for value in (region.held_out_mm, region.fitted_mm)),
        )
        for region in report.regions
    ]
    body = "".join(
        [
            "<h1>usdeform fit: can this model be trusted?</h1>",
            f'<div id="summary">{_summary(report)}</div>',
            f"<p>Fitted: {html.escape(report.fitted.method.description)}; the model is tied to the "
            f"{html.escape(str(report.fitted.provenance.get('anchor')))}; {fit.n_samples} samples, loss "
            f"{fit.loss:.4g}{f', smoothness {fit.smoothness:.3g}' if fit.smoothness else ''}. The numbers are also in "
            "<code>report.json</code> beside this page.</p>",
            section(
                "Tracks per depth band",
                "Optical-flow tracks by their depth below the probe face in the lowest-force frame "
                f"({report.band_mm:g} mm bands): kept to the highest force, or dropped by the first check they "
                "failed. Where most tracks were dropped the model has no data and extrapolates (or bridges the gap).",
                _bands_figure(report),
                "tracks per depth band",
            ),
            table(("depth (mm)", "tracks", "kept", "dropped", "dropped by"), _band_rows(report)),
            section(
                "Tracked and fitted field at the highest force",
                "Left: the tracked displacements (yellow) and the fitted model's at the same points (cyan) on the "
                "highest-force frame (lengthened where the title says so). Right: the length of their difference "
                "at each kept track; red crosses mark tracks that were dropped.",
                _field_figure(report),
                "tracked against fitted field",
            ),
            section(
                "Stiffness fits",
                "Force against probe displacement with polynomial fits and their R²; the quadratic is the stiffness "
                "profile the model uses.",
                stiffness_figure(
                    [m.stiffness for m in report.fitted.measured], [Path(p.name).name for p in report.palpations]
                ),
                "stiffness fits",
            ),
            table(("palpation", *(f"R² order {order}" for order in orders), "k (N/m)"), stiffness_rows),
            "<h2>Palpation phases</h2><p>Each palpation's frames by phase; the method is fitted on the loading "
            "ramp from contact, with the probe displacement counted from contact.</p>",
            table(("palpation", "phases"), [(p.name, p.summary()) for p in report.fitted.phases]),
            *_lumens_section(report),
            section(
                "Cross-validated residual by region",
                f"The frame cut into depth bands and lateral thirds; the regions dealt into {report.n_folds} folds, "
                "and each fold's tracks predicted by the model refitted without them (same settings and smoothness). "
                "Held out: how far the model is from tissue it was not fitted to there; fitted: from the tracks it "
                "was fitted to. RMS over the region's tracks and frames.",
                _regions_figure(report),
                "cross-validated residual by region",
            ),
            table(
                (
                    "depth (mm)",
                    "lateral",
                    "tracks",
                    "samples",
                    "held out (px)",
                    "fitted (px)",
                    "held out (mm)",
                    "fitted (mm)",
                ),
                region_rows,
            ),
        ]
    )
    html_path, json_path = out / "report.html", out / "report.json"
    with outputs_together():
        with atomic_output(html_path) as handle:
            handle.write(page("usdeform fit report", body).encode("utf-8"))
        with atomic_output(json_path) as handle:
            handle.write((json.dumps(report.to_json(), indent=1, allow_nan=False) + "\n").encode("utf-8"))
    return html_path, json_path
