"""The demo's report: one self-contained HTML page (figures embedded as base64 PNG) with the summary first."""

from __future__ import annotations

import html
from pathlib import Path

import numpy as np
from matplotlib.axes import Axes
from matplotlib.figure import Figure

from .._files import atomic_output
from .._html_report import page, stiffness_figure
from .._html_report import section as _section
from .._html_report import table as _table
from ..fitting import FIT_METHODS
from .config import DemoResult

__all__ = ["compensation_change", "effect_line", "summary_lines", "summary_text", "write_report"]

_COLOURS = {"deformed": "red", "recommended": "deepskyblue", "paper": "orange", "corrected": "deepskyblue"}
_TRUTH_COLOUR = "lime"


def summary_text(result: DemoResult) -> str:
    """One paragraph: what was simulated, what the correction achieved against the truth, how long it took."""
    config, frames, volumes = result.config, result.frame_metrics, result.volume_metrics
    method, other = config.method, next(name for name in FIT_METHODS if name != config.method)
    stiffness = [m.stiffness.stiffness_mean_sd_n_per_m[0] for m in result.measured]
    positions = ", ".join(f"{p:g}" for p in config.palpation_positions_mm)
    vessel = volumes.vessel_volume_mm3
    return (
        f"The robot palpated the simulated {config.preset} phantom at {positions} mm along its length up to "
        f"{result.phantom.max_force_n:g} N (fitted stiffness {min(stiffness):.0f}-{max(stiffness):.0f} N/m), a "
        f"displacement model ({method} settings: {FIT_METHODS[method].description}) was fitted to the tracked pixel "
        "motion, and a "
        f"{len(result.sweep)}-frame sweep at {result.sweep_force_n:g} N was corrected frame by frame to zero force. "
        "Against the simulator's zero-force truth the mean vessel Dice rose from "
        f"{frames.mean('dice', 'deformed'):.3f} "
        f"(deformed) to {frames.mean('dice', method):.3f} (corrected), the mean |area error| fell from "
        f"{frames.mean('area', 'deformed'):.1f} to {frames.mean('area', method):.1f} mm², and the centroid error from "
        f"{frames.mean('centroid', 'deformed'):.2f} to {frames.mean('centroid', method):.2f} mm "
        f"(the {other} settings: Dice {frames.mean('dice', other):.3f}, "
        f"|area error| {frames.mean('area', other):.1f} mm²). "
        f"Compounded, the vessel measures {vessel['deformed']:.0f} mm³ deformed, {vessel['corrected']:.0f} mm³ "
        f"corrected and {vessel['truth']:.0f} mm³ in truth; its centre line lies "
        f"{volumes.depth_error_mm['deformed']:.2f} mm (deformed) and {volumes.depth_error_mm['corrected']:.2f} mm "
        f"(corrected) from the truth's on average. The stages took {sum(result.timings_s.values()):.0f} s."
    )


def effect_line(result: DemoResult) -> str | None:
    """One line: the simulated effects, what the blind diagnosis found, the corrected vessel with the effects
    uncompensated and compensated with the diagnosis (mean Dice, mean |area error| mm², compounded vessel mm³,
    on the same frames and slices), what compensation gives back, or why it was refused. None without effects."""
    outcome = result.effect_outcome
    if outcome is None:
        return None
    effects = "; ".join(result.config.effects)
    diagnosis = outcome.diagnosis
    found = (
        "no diagnosis"
        if diagnosis is None
        else f"diagnosis: verdict {diagnosis['verdict']}, named {', '.join(diagnosis['named']) or 'none'}"
    )
    frames, volumes = outcome.frame_metrics, outcome.volume_metrics
    if outcome.record is None or frames is None or volumes is None:
        uncompensated, vessel = result.frame_metrics, result.volume_metrics.vessel_volume_mm3
        return (
            f"Effect {effects} ({found}): corrected with the effect uncompensated, Dice "
            f"{uncompensated.mean('dice', result.config.method):.3f} / |area error| "
            f"{uncompensated.mean('area', result.config.method):.1f} mm² / vessel {vessel['corrected']:.0f} mm³ "
            f"(truth {vessel['truth']:.0f} mm³); not compensated: {outcome.refusal}"
        )
    diagnosed = "; ".join(
        f"{effect} " + ", ".join(f"{name} {value:.3g}" for name, value in parameters.items())
        for effect, parameters in outcome.record["effects"].items()
    )
    vessel = volumes.vessel_volume_mm3
    scores = {
        name: f"Dice {frames.mean('dice', name):.3f} / |area error| {frames.mean('area', name):.1f} mm² / "
        f"vessel {vessel[name]:.0f} mm³"
        for name in ("corrected", "compensated")
    }
    kept = len(frames.sweep_position_mm)
    on = f" on the {kept} of {len(result.sweep)} frames the re-pairing kept" if kept < len(result.sweep) else ""
    return (
        f"Effect {effects} ({found}; {diagnosed}): corrected with the effect uncompensated, {scores['corrected']}; "
        f"compensated with the diagnosis, {scores['compensated']} (truth {vessel['truth']:.0f} mm³){on}: "
        + compensation_change(
            frames.mean("dice", "compensated") - frames.mean("dice", "corrected"),
            frames.mean("area", "compensated") - frames.mean("area", "corrected"),
        )
        + " (the cost against the effect-free run is not measured here: usdeform compensation-benchmark measures it)"
    )


def compensation_change(dice_change: float, area_error_change_mm2: float) -> str:
    """What compensating did to the mean Dice and |area error| (mm²): given back, or made worse."""
    change = f"{dice_change:+.3f} Dice, |area error| {area_error_change_mm2:+.1f} mm²"
    if dice_change >= 0:
        return f"compensation gives back {change}"
    return f"compensation made it worse, {change}: check the diagnosis's fitted size before compensating"


def summary_lines(result: DemoResult) -> list[str]:
    """The few lines the command prints: the scores against the truth, with effects :func:`effect_line`, and the
    time per stage."""
    config, frames, vessel = result.config, result.frame_metrics, result.volume_metrics.vessel_volume_mm3
    method, other = config.method, next(name for name in FIT_METHODS if name != config.method)
    depth = result.volume_metrics.depth_error_mm
    return [
        f"{config.preset} phantom, {len(result.sweep)}-frame sweep at {result.sweep_force_n:g} N, {method} settings "
        f"({FIT_METHODS[method].description})",
        f"vessel against the zero-force truth, deformed -> corrected: Dice {frames.mean('dice', 'deformed'):.3f} -> "
        f"{frames.mean('dice', method):.3f} ({other} settings {frames.mean('dice', other):.3f}), |area error| "
        f"{frames.mean('area', 'deformed'):.1f} -> {frames.mean('area', method):.1f} mm², centroid error "
        f"{frames.mean('centroid', 'deformed'):.2f} -> {frames.mean('centroid', method):.2f} mm",
        f"volumes: vessel {vessel['deformed']:.0f} / {vessel['corrected']:.0f} / {vessel['truth']:.0f} mm³ "
        f"(deformed / corrected / truth), centre line {depth['deformed']:.2f} / {depth['corrected']:.2f} mm "
        "from the truth's",
        *filter(None, [effect_line(result)]),
        "time per stage: " + ", ".join(f"{stage} {seconds:.1f} s" for stage, seconds in result.timings_s.items()),
    ]


def _stiffness_figure(result: DemoResult) -> Figure:
    positions = result.config.palpation_positions_mm
    return stiffness_figure([m.stiffness for m in result.measured], [f"{position:g} mm" for position in positions])


def _field_figure(result: DemoResult) -> Figure:
    """The tracked displacements at the middle palpation's highest force, the model's field and the true one."""
    middle = len(result.measured) // 2
    recording, truth = result.palpations[middle]
    sampled = result.measured[middle]
    assert recording.force is not None  # a simulated palpation records its force
    tracked = sampled.tracked
    row = int(np.argmax(recording.force[tracked.frame_indices]))
    index = int(tracked.frame_indices[row])
    force = float(recording.force[index])
    valid = tracked.valid[row]
    shown = valid & (np.arange(len(valid)) % 3 == 0)  # every third track keeps the arrows legible
    points, moves = tracked.points_px[shown], tracked.displacements_px[row, shown]
    model_field = result.model.displacement(force, sampled.stiffness.profile, recording.shape)
    true_field = np.moveaxis(truth.displacement_px[index].astype(np.float64), -1, 0)
    figure = Figure(figsize=(13, 4.2))
    axes = figure.subplots(1, 3)
    axes[0].imshow(recording.frames[index], cmap="gray")
    axes[0].quiver(
        points[:, 0], points[:, 1], moves[:, 0], moves[:, 1], color="yellow", angles="xy", scale_units="xy", scale=1
    )
    axes[0].set_title(f"tracked ({valid.sum()} of {len(valid)} points kept), {force:.1f} N", fontsize=9)
    limit = float(np.nanpercentile(np.linalg.norm(true_field, axis=0), 99))
    for axis, values, title in (
        (axes[1], model_field, f"fitted model ({result.config.method})"),
        (axes[2], true_field, "simulator's truth"),
    ):
        image = axis.imshow(np.linalg.norm(values, axis=0), cmap="magma", vmin=0, vmax=limit)
        step = max(recording.shape[0] // 16, 1)
        y, x = np.mgrid[step // 2 : recording.shape[0] : step, step // 2 : recording.shape[1] : step]
        axis.quiver(
            x, y, values[0][y, x], values[1][y, x], color="white", angles="xy", scale_units="xy", scale=1, width=0.003
        )
        axis.set_title(f"{title}: |D| (px)", fontsize=9)
        figure.colorbar(image, ax=axis, fraction=0.046)
    for axis in axes:
        axis.axis("off")
    figure.tight_layout()
    return figure


def _contour(axis: Axes, mask: np.ndarray, colour: str, label: str) -> None:
    if mask.any():
        axis.contour(mask.astype(float), levels=[0.5], colors=[colour], linewidths=1.2)
    axis.plot([], [], color=colour, label=label)


def _overlay_figure(result: DemoResult) -> Figure:
    """Deformed, corrected and zero-force frames in the middle of the sweep with the three vessel boundaries."""
    truth, index = result.sweep_truth, len(result.sweep) // 2
    method = result.config.method
    corrected_mask = result.corrected_masks[method][index]
    boundaries = (
        (truth.vessel_mask[index], _COLOURS["deformed"], "deformed"),
        (corrected_mask, _COLOURS["corrected"], f"corrected ({method})"),
        (truth.zero_force_vessel_mask[index], _TRUTH_COLOUR, "zero-force truth"),
    )
    figure = Figure(figsize=(12, 4.2))
    axes = figure.subplots(1, 3)
    frames = (
        (result.sweep.frames[index], "deformed frame"),
        (result.corrected.frames[index], "corrected frame"),
        (truth.zero_force_frames[index], "zero-force frame (truth)"),
    )
    for axis, (frame, title) in zip(axes, frames, strict=True):
        axis.imshow(frame, cmap="gray")
        for mask, colour, label in boundaries:
            _contour(axis, mask, colour, label)
        axis.set_title(
            f"{title}, s = {truth.sweep_position_mm[index]:.1f} mm, {truth.force_n[index]:.1f} N", fontsize=9
        )
        axis.axis("off")
    axes[0].legend(fontsize=7, loc="lower left")
    figure.tight_layout()
    return figure


def _slices_figure(result: DemoResult) -> Figure:
    """Axial (across the sweep), coronal (at the vessel's depth) and longitudinal slices of the three volumes."""
    volumes = result.volumes
    grid = volumes["truth"].grid
    spacing, origin = grid.spacing, grid.origin  # (x, y, z), mm
    truth_lumen = result.vessel_volumes["truth"].image >= 127.5
    z_index, y_index, x_index = (round(float(np.mean(axis))) for axis in np.nonzero(truth_lumen))
    x_mm = origin[0] + spacing[0] * np.array([0, grid.shape[2] - 1])
    y_mm = origin[1] + spacing[1] * np.array([0, grid.shape[1] - 1])
    z_mm = origin[2] + spacing[2] * np.array([0, grid.shape[0] - 1])
    views = (
        ("axial (x-z) at the sweep's middle", lambda image: image[:, y_index, :], (*x_mm, *z_mm), ("x", "z")),
        ("coronal (x-y) at the true vessel depth", lambda image: image[z_index, :, :].T, (*x_mm, *y_mm), ("x", "y")),
        ("longitudinal (y-z) through the vessel", lambda image: image[:, :, x_index], (*y_mm, *z_mm), ("y", "z")),
    )
    figure = Figure(figsize=(12, 10))
    axes = figure.subplots(len(views), 3)
    high = float(np.percentile(volumes["truth"].image[volumes["truth"].image > 0], 99.5))
    for row, (view, cut, extent, labels) in enumerate(views):
        for column, name in enumerate(("deformed", "corrected", "truth")):
            axis = axes[row, column]
            left, right, bottom, top = extent
            axis.imshow(
                cut(volumes[name].image),
                cmap="gray",
                vmin=0,
                vmax=high,
                origin="lower",
                extent=(left, right, bottom, top),
                aspect="equal",
            )
            axis.contour(
                cut(result.vessel_volumes["truth"].image),
                levels=[127.5],
                colors=[_TRUTH_COLOUR],
                linewidths=0.8,
                origin="lower",
                extent=(left, right, bottom, top),
            )
            axis.set_title(f"{name}: {view}", fontsize=8)
            axis.set_xlabel(f"base {labels[0]} (mm)", fontsize=7)
            axis.set_ylabel(f"base {labels[1]} (mm)", fontsize=7)
            axis.tick_params(labelsize=6)
    figure.tight_layout()
    return figure


def _metrics_figure(result: DemoResult) -> Figure:
    """Per-frame Dice, area and centroid errors along the sweep, and the volumes' centre-line depth."""
    frames, volumes = result.frame_metrics, result.volume_metrics
    figure = Figure(figsize=(13, 6.4))
    axes = figure.subplots(2, 2).ravel()
    position = frames.sweep_position_mm
    for axis, values, label in (
        (axes[0], frames.dice, "Dice with the zero-force vessel"),
        (axes[1], frames.area_error_mm2, "area error (mm²), frame - truth"),
        (axes[2], frames.centroid_error_mm, "centroid error (mm)"),
    ):
        for name, series in values.items():
            suffix = " (used)" if name == result.config.method else ""
            axis.plot(position, series, color=_COLOURS[name], label=f"{name}{suffix}", linewidth=1.2)
        axis.set(xlabel="sweep position s (mm)", ylabel=label)
        axis.grid(alpha=0.3)
        axis.legend(fontsize=7)
    for name, colour in (
        ("deformed", _COLOURS["deformed"]),
        ("corrected", _COLOURS["corrected"]),
        ("truth", _TRUTH_COLOUR),
    ):
        axes[3].plot(volumes.slice_y_mm, volumes.depth_mm[name], color=colour, label=name)
    axes[3].set(xlabel="base y (mm)", ylabel="centre-line depth (mm)", title="vessel centre line in the volumes")
    axes[3].invert_yaxis()
    axes[3].grid(alpha=0.3)
    axes[3].legend(fontsize=7)
    figure.tight_layout()
    return figure


def _next_steps(result: DemoResult) -> str:
    """The same fit and correction as commands on the demo's own files, to try before one's own recordings."""
    palpations = " ".join(path.name for path in result.files.values() if path.name.startswith("palpation_"))
    commands = (
        f"usdeform fit {palpations} --output my_model.json --flexible-layer-mm "
        f"{result.phantom.base_section.depth_mm:g} --method {result.config.method}\n"
        "usdeform correct sweep.seq.nrrd --model my_model.json --output my_corrected.seq.nrrd "
        "--volume my_corrected.nrrd"
    )
    return (
        "<h2>Next</h2><p>The same fit and correction from the command line, in this folder (with your own PLUS "
        "recordings in place of these; <code>--flexible-layer-mm</code> is the depth of the compressible tissue):</p>"
        f"<pre>{html.escape(commands)}</pre>"
    )


def write_report(result: DemoResult, path: str | Path) -> Path:
    """Write the report (self-contained HTML) to ``path``, atomically; returns the path."""
    path = Path(path)
    config, frames, volumes = result.config, result.frame_metrics, result.volume_metrics
    settings = _table(
        ("settings", "basis", "coupling", "integration", "mean Dice", "mean |area error| (mm²)", "centroid error (mm)"),
        [
            (
                "deformed (no correction)",
                "",
                "",
                "",
                *(f"{frames.mean(m, 'deformed'):.3f}" for m in ("dice", "area", "centroid")),
            ),
            *(
                (
                    f"{name}{' (used for the volumes)' if name == config.method else ''}",
                    str(method.basis if isinstance(method.basis, str) else "{} {}x{}".format(*method.basis)),
                    method.coupling,
                    method.integration,
                    *(f"{frames.mean(m, name):.3f}" for m in ("dice", "area", "centroid")),
                )
                for name, method in FIT_METHODS.items()
            ),
        ],
    )
    volume_table = _table(
        ("volume", "vessel volume (mm³)", "mean centre-line depth (mm)", "mean |depth - truth| (mm)"),
        [
            (
                name,
                f"{volumes.vessel_volume_mm3[name]:.0f}",
                f"{volumes.mean_depth_mm(name):.2f}",
                f"{volumes.depth_error_mm[name]:.2f}",
            )
            for name in ("deformed", "corrected", "truth")
        ],
    )
    stiffness_rows = [
        (
            f"{position:g}",
            *(f"{m.stiffness.r_squared[order]:.4f}" for order in (1, 2, 3)),
            "{:.0f} ± {:.0f}".format(*m.stiffness.stiffness_mean_sd_n_per_m),
            f"{m.tracked.kept_fraction:.0%}",
        )
        for position, m in zip(config.palpation_positions_mm, result.measured, strict=True)
    ]
    timing_rows = [(stage, f"{seconds:.1f}") for stage, seconds in result.timings_s.items()]
    timing_rows.append(("total", f"{sum(result.timings_s.values()):.1f}"))
    files = "".join(
        f"<li><code>{html.escape(p.name)}</code>: {html.escape(label)}</li>" for label, p in result.files.items()
    )
    body = "".join(
        [
            "<h1>usdeform demo: deformation correction on the simulator</h1>",
            f'<p id="summary">{html.escape(summary_text(result))}</p>',
            *[f'<p id="effect">{html.escape(line)}</p>' for line in filter(None, [effect_line(result)])],
            "<h2>Settings and scores</h2>",
            "<p>Per-frame scores along the sweep against the zero-force truth, for each fitting setting "
            "(the vessel of a corrected frame is the simulator's lumen warped by that correction).</p>",
            settings,
            volume_table,
            _section(
                "Stiffness at the palpated positions",
                "Force against probe displacement with polynomial fits of order 1-3 (paper Fig. 4); the quadratic "
                "is the stiffness profile the model uses.",
                _stiffness_figure(result),
                "stiffness fits",
            ),
            _table(
                ("position (mm)", "R² order 1", "R² order 2", "R² order 3", "k (N/m)", "tracks kept"), stiffness_rows
            ),
            _section(
                "Displacement field at the highest force",
                "Optical-flow tracks from the lowest-force frame (arrows, pixels) at the middle palpation's highest "
                "force, and the displacement magnitude of the fitted model and of the simulator's truth.",
                _field_figure(result),
                "displacement field",
            ),
            _section(
                "Vessel boundaries",
                "The deformed (red), corrected (blue) and zero-force (green) lumen boundaries in the middle of the "
                "sweep. Black at the sides of the corrected frame: tissue the deformed frame did not image (the "
                "probe pushed it out of the view), so the correction has nothing to show there.",
                _overlay_figure(result),
                "vessel boundary overlay",
            ),
            _section(
                "Volumes",
                "Slices of the deformed, corrected and zero-force volumes (paper Fig. 9), with the true lumen in "
                "green. Black: voxels no frame reached (in the deformed volume, above the pressed-in surface).",
                _slices_figure(result),
                "volume slices",
            ),
            _section(
                "Along the sweep",
                "Per-frame scores against the zero-force truth, and the vessel's centre-line depth below the unloaded "
                "surface in each volume.",
                _metrics_figure(result),
                "per-frame metrics",
            ),
            "<h2>Timings</h2><p>Wall-clock seconds per stage on this machine. The FEM solves are loaded from the "
            "solution cache when it holds them: the package ships the default demo's; another preset or mesh "
            "solves once (about a minute on 2 cores) and is cached for the next runs.</p>",
            _table(("stage", "seconds"), timing_rows),
            "<h2>Files</h2><p>Volumes open in 3D Slicer (File > Add Data); the recordings are PLUS sequence files.</p>",
            f"<ul>{files}</ul>",
            _next_steps(result),
        ]
    )
    with atomic_output(path) as handle:
        handle.write(page("usdeform demo", body).encode("utf-8"))
    return path
