"""The paper-3d results: ``results.md``, ``results.json`` and the figures (Figs. 9 and 10)."""

from __future__ import annotations

import json
from dataclasses import asdict
from pathlib import Path

import numpy as np
from matplotlib.figure import Figure

from ..._files import atomic_output
from ..paper_2d import Method
from .config import SOURCES, VIEWED, Paper3dConfig, PhantomSweeps, SweepCase, Views
from .measures import centre_line_depth_mm

__all__ = ["plot_bars", "plot_views", "write_results"]


def _nanmax(values: list[float]) -> float:
    finite = [v for v in values if np.isfinite(v)]
    return float(max(finite)) if finite else float("nan")


def _nanmean_abs(values: list[float]) -> float:
    finite = [abs(v) for v in values if np.isfinite(v)]
    return float(np.mean(finite)) if finite else float("nan")


def write_results(
    cases: list[SweepCase], config: Paper3dConfig, methods: tuple[Method, ...], names: list[str], output: Path
) -> None:
    lines = [
        "# The paper's 3D experiments on the simulated phantoms",
        "",
        f"Frames {config.rows} x {config.cols}, {config.palpation_frames}-frame palpations, sweep frames every "
        f"{config.frame_spacing_mm:g} mm, voxels {config.voxel_mm:g} mm, {config.random_frames} random frames per "
        "sweep. Truth: the simulator's zero-force frames and lumen masks at the zero-force probe poses. "
        "Volumes: nearest-neighbour mean compounding (corrected pixels sampled from outside their frame left "
        "out), gaps between frames filled (STICK, sticks up to 4 voxels). "
        "Variants (`/sweep`: stiffness from the sweep's own force and probe displacement instead of the "
        "inverse-distance interpolation between palpations):",
        "",
        "- `deformed`: no correction, at the recorded poses",
    ]
    lines += [f"- `{m.name}`: {m.description}" for m in methods]
    lines += [
        "",
        "## Per frame (Fig. 10): max centroid distance (mm) / mean |area difference| (mm^2) / mean Dice",
        "",
        "| phantom | force (N) | " + " | ".join(names) + " |",
        "|---" * (len(names) + 2) + "|",
    ]
    for c in cases:
        cells = [
            f"{_nanmax(c.frames[n]['centroid_mm']):.2f} / {_nanmean_abs(c.frames[n]['area_diff_mm2']):.1f} / "
            f"{np.mean(c.frames[n]['dice']) if c.frames[n]['dice'] else float('nan'):.3f}"
            for n in names
        ]
        lines.append(f"| {c.phantom} | {c.target_force_n:g} | " + " | ".join(cells) + " |")
    lines += [
        "",
        "## Area reduction and spread across forces",
        "",
        "Area difference cut: 1 - mean |area diff| corrected / deformed over the phantom's frames; "
        "SD of the mean corrected area across forces (mm^2).",
        "",
        "| phantom | " + " | ".join(f"{n} cut / SD" for n in names[1:]) + " | deformed SD |",
        "|---" * (len(names) + 1) + "|",
    ]
    for phantom in dict.fromkeys(c.phantom for c in cases):
        rows = [c for c in cases if c.phantom == phantom]

        def spread(name: str, rows: list[SweepCase] = rows) -> float:
            means = [np.nanmean(c.frames[name]["area_mm2"]) for c in rows if c.frames[name]["area_mm2"]]
            return float(np.std(means)) if len(means) > 1 else float("nan")

        deformed = np.mean([_nanmean_abs(c.frames["deformed"]["area_diff_mm2"]) for c in rows])
        cells = []
        for name in names[1:]:
            corrected = np.mean([_nanmean_abs(c.frames[name]["area_diff_mm2"]) for c in rows])
            cells.append(f"{100 * (1 - corrected / deformed):.0f} % / {spread(name):.1f}")
        lines.append(f"| {phantom} | " + " | ".join(cells) + f" | {spread('deformed'):.1f} |")
    lines += [
        "",
        "## Volume (Fig. 9): lumen volume error (%) / centre-line depth error mean, max (mm) / 3-D Dice / "
        "coronal extent (fraction of the truth's)",
        "",
        "| phantom | force (N) | truth volume (mm^3) | " + " | ".join(names) + " |",
        "|---" * (len(names) + 3) + "|",
    ]
    for c in cases:
        cells = [
            f"{v['volume_error_pct']:+.0f} / {v['depth_error_mean_mm']:+.2f}, {v['depth_error_max_mm']:.2f} / "
            f"{v['dice']:.3f} / {v['coronal_extent_ratio']:.2f}"
            for v in (c.volume[n] for n in names)
        ]
        lines.append(
            f"| {c.phantom} | {c.target_force_n:g} | {c.volume['truth']['volume_mm3']:.0f} | "
            + " | ".join(cells)
            + " |"
        )
    lines += [
        "",
        "## Stiffness: |lambda at the recorded force - recorded lambda| over the sweep (mm), mean / max",
        "",
        "| phantom | force (N) | force range (N) | lambda range (mm) | interpolated | sweep |",
        "|---|---|---|---|---|---|",
    ]
    for c in cases:
        lines.append(
            f"| {c.phantom} | {c.target_force_n:g} | {c.force_range_n[0]:.1f}-{c.force_range_n[1]:.1f} | "
            f"{c.probe_displacement_range_mm[0]:.2f}-{c.probe_displacement_range_mm[1]:.2f} | "
            + " | ".join(f"{c.stiffness[s]['mean_mm']:.2f} / {c.stiffness[s]['max_mm']:.2f}" for s in SOURCES)
            + " |"
        )
    lines += [
        "",
        "## Why a lumen ends too small or large, by region (mean over the random frames, mm)",
        "",
        "Signed error of the displacement (model minus true) just outside each wall; a corrected wall "
        "lands at its true place minus that error, so the corrected lumen height is off by top - bottom "
        "and its width by left - right. `elsewhere`: mean error magnitude in the tissue more than two "
        "lumen radii from the vessel. `deformed`: no correction (the error is minus the true field).",
        "",
        "| phantom | force (N) | variant | top | bottom | left | right | height error | width error | elsewhere |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    for c in cases:
        for name in names:
            if name in c.walls:
                w = c.walls[name]
                lines.append(
                    f"| {c.phantom} | {c.target_force_n:g} | {name} | {w['top']:+.2f} | {w['bottom']:+.2f} | "
                    f"{w['left']:+.2f} | {w['right']:+.2f} | {w['height_error_mm']:+.2f} | "
                    f"{w['width_error_mm']:+.2f} | {w['elsewhere_mm']:.2f} |"
                )
    with atomic_output(output / "results.md") as handle:
        handle.write(("\n".join(lines) + "\n").encode())
    payload = {"config": asdict(config), "variants": names, "cases": [asdict(c) for c in cases]}
    with atomic_output(output / "results.json") as handle:
        handle.write(json.dumps(payload, indent=1, default=float).encode())


def plot_views(views: dict[str, Views], path: Path) -> None:
    """Fig. 9: axial (middle y slice) and coronal (true centre-line depth) views of truth, deformed and
    two corrections, per phantom at its highest force, lumen contours overlaid; as in the paper, a
    dashed line marks where the other view cuts (blue: the coronal plane, red: the axial one)."""
    figure = Figure(figsize=(3.0 * len(VIEWED), 2.8 * 2 * len(views)))
    axes = figure.subplots(2 * len(views), len(VIEWED), squeeze=False)
    for number, (title, view) in enumerate(views.items()):
        truth_depth = centre_line_depth_mm(view.lumens["truth"], view.grid)
        slices = np.flatnonzero(np.isfinite(truth_depth))
        y = int(slices[len(slices) // 2])
        origin, step = view.grid.index_to_world[2, 3], view.grid.index_to_world[2, 2]
        z = int(np.clip(np.rint((np.nanmean(truth_depth) - origin) / step), 0, view.grid.shape[0] - 1))
        for column, name in enumerate(VIEWED):
            for row, (image, lumen, kind, cut, colour) in enumerate(
                (
                    # axial rows flipped so that the probe is on top: the coronal plane is at row nz-1-z
                    (
                        view.images[name][::-1, y, :],
                        view.lumens[name][::-1, y, :],
                        "axial",
                        view.grid.shape[0] - 1 - z,
                        "C0",
                    ),
                    (view.images[name][z, :, :], view.lumens[name][z, :, :], "coronal", y, "C3"),
                )
            ):
                axis = axes[2 * number + row, column]
                axis.imshow(image, cmap="gray", vmin=0, vmax=255)
                if lumen.any():
                    axis.contour(lumen.astype(float), levels=[0.5], colors=["lime"], linewidths=0.8)
                axis.axhline(cut, color=colour, linestyle="--", linewidth=0.8)
                axis.set_title(f"{title}: {name}, {kind}", fontsize=7)
                axis.axis("off")
    figure.tight_layout()
    figure.savefig(path, dpi=110)


def plot_bars(cases: list[SweepCase], phantoms: list[PhantomSweeps], path: Path) -> None:
    """Fig. 10: per phantom and force, (left) the centroid distance of the deformed and corrected frames
    to the zero-force frame's, mean over the random frames with the maximum marked, and (right) the
    vessel cross-section area of the zero-force (truth), deformed and corrected frames, mean and SD."""
    shown = ("deformed", "paper", "spline-lambda")
    figure = Figure(figsize=(11, 3.4 * len(phantoms)))
    axes = figure.subplots(len(phantoms), 2, squeeze=False)
    for row, sweeps in enumerate(phantoms):
        rows = [c for c in cases if c.phantom == sweeps.label]
        forces = np.arange(len(rows))
        labels = [f"{c.target_force_n:g} N" for c in rows]
        centroid, area = axes[row]
        width = 0.8 / len(shown)
        for number, name in enumerate(shown):
            at = forces + (number - (len(shown) - 1) / 2) * width
            distances = [np.asarray(c.frames[name]["centroid_mm"], dtype=float) for c in rows]
            centroid.bar(at, [np.nanmean(d) for d in distances], width, label=f"{name} (mean)", color=f"C{number + 1}")
            centroid.plot(at, [np.nanmax(d) for d in distances], "v", color="k", markersize=4)
        centroid.plot([], [], "v", color="k", markersize=4, label="maximum")
        centroid.set_xticks(forces, labels)
        centroid.set(title=f"{sweeps.label} phantom: vessel centroid distance", ylabel="distance to truth (mm)")
        centroid.legend(fontsize=7)
        width = 0.8 / (len(shown) + 1)
        for number, name in enumerate(("truth", *shown)):
            at = forces + (number - len(shown) / 2) * width
            areas = [_areas(c, name) for c in rows]
            area.bar(
                at,
                [np.nanmean(a) for a in areas],
                width,
                yerr=[np.nanstd(a) for a in areas],
                capsize=2,
                label=name,
                color=f"C{number}",
            )
        area.set_xticks(forces, labels)
        area.set(title=f"{sweeps.label} phantom: vessel cross-section area", ylabel="area (mm$^2$)")
        area.legend(fontsize=7)
    figure.tight_layout()
    figure.savefig(path, dpi=110)


def _areas(case: SweepCase, name: str) -> np.ndarray:
    """Vessel areas (mm^2) over the random frames of ``name`` (a variant or ``"truth"``, the zero-force
    frames' area: any variant's area minus its difference to the truth)."""
    if name != "truth":
        return np.asarray(case.frames[name]["area_mm2"], dtype=float)
    deformed = case.frames["deformed"]
    return np.asarray(deformed["area_mm2"], dtype=float) - np.asarray(deformed["area_diff_mm2"], dtype=float)
