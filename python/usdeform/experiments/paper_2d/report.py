"""The paper-2d experiments' tables (``results.md``, ``results.json``) and figures."""

from __future__ import annotations

import json
from dataclasses import asdict
from pathlib import Path

import numpy as np
from matplotlib.figure import Figure

from ...regression import DisplacementModel
from .config import CorrectionCase, Method, Paper2dConfig, Paper2dResults
from .evaluation import Palpated

__all__ = ["plot_overlays", "plot_residuals", "plot_stiffness", "write_tables"]


def _summary(cases: list[CorrectionCase], experiment: str, force: float, method: str, metric: str) -> float:
    """Mean Dice, or mean absolute area error (mm^2), of ``method`` over the cases at one force."""
    values = [
        c.dice[method] if metric == "dice" else abs(c.area_error_mm2[method])
        for c in cases
        if c.experiment == experiment and c.target_force_n == force
    ]
    return float(np.mean(values)) if values else float("nan")


def write_tables(results: Paper2dResults, config: Paper2dConfig, methods: tuple[Method, ...], output: Path) -> None:
    """Write ``results.md`` (TABLES I and II, stiffness, diagnosis) and ``results.json`` to ``output``."""
    names = ("deformed", *(m.name for m in methods))
    lines = [
        "# The paper's 2D experiments on the simulated phantoms",
        "",
        f"Frames {config.rows} x {config.cols}, {config.n_frames}-frame palpations, solver `{config.solver}` "
        "(B-spline models: exact, smoothness by cross-validation). Every model is fitted on two palpations "
        "at the stiff phantom's first position and propagated by the local stiffness. Dice of the vessel "
        "segmented in the deformed / corrected frame against the one in the zero-force frame. Methods:",
        "",
        "- `deformed`: no correction",
    ]
    lines += [f"- `{m.name}`: {m.description}" for m in methods]
    lines += [
        "",
        "## TABLE I: regression parameters of the paper's model at the fitting position",
        "",
        "| solver | K^x | K^y | loss | iterations |",
        "|---|---|---|---|---|",
    ]
    for solver, row in results.table_1.items():
        lines.append(
            f"| {solver} | {np.array2string(np.array(row['K_lateral']), precision=3, max_line_width=200)} | "
            f"{np.array2string(np.array(row['K_axial']), precision=3, max_line_width=200)} | "
            f"{row['loss']:.3e} | {row['iterations']} |"
        )
    lines += [
        "",
        f"Time to fit one sampling position (tracking + stiffness + regression share): "
        f"{results.fit_seconds_per_position:.2f} s (paper cites 186 s for the previous method).",
        "",
    ]
    for metric, title in (("dice", "mean Dice"), ("area", "mean |area error| (mm^2)")):
        for experiment, forces in (
            ("same position", config.stiff_forces_n),
            ("other position", config.stiff_forces_n),
            ("unseen soft tissue", config.soft_forces_n),
        ):
            lines += [
                f"## {experiment}: {title} over positions",
                "",
                "| force (N) | " + " | ".join(names) + " |",
                "|---" * (len(names) + 1) + "|",
            ]
            for force in forces:
                lines.append(
                    f"| {force:g} | "
                    + " | ".join(f"{_summary(results.cases, experiment, force, m, metric):.3f}" for m in names)
                    + " |"
                )
            lines.append("")
    lines += [
        "## TABLE II: every position and force (Dice)",
        "",
        "| phantom | position (mm) | force (N) | " + " | ".join(names) + " |",
        "|---" * (len(names) + 3) + "|",
    ]
    for c in results.cases:
        lines.append(
            f"| {c.phantom} | {c.position_mm:g} | {c.force_n:.1f} | "
            + " | ".join(f"{c.dice[m]:.3f}" for m in names)
            + " |"
        )
    lines += [
        "",
        "## TABLE II: area error (mm^2, corrected minus zero force) and centroid error (mm)",
        "",
        "| phantom | position (mm) | force (N) | "
        + " | ".join(f"area {m}" for m in names[:5])
        + " | "
        + " | ".join(f"centroid {m}" for m in names[:5])
        + " |",
        "|---" * 13 + "|",
    ]
    for c in results.cases:
        lines.append(
            f"| {c.phantom} | {c.position_mm:g} | {c.force_n:.1f} | "
            + " | ".join(f"{c.area_error_mm2[m]:.1f}" for m in names[:5])
            + " | "
            + " | ".join(f"{c.centroid_error_mm[m]:.2f}" for m in names[:5])
            + " |"
        )
    lines += [
        "",
        "## Stiffness at the palpated positions (Fig. 4)",
        "",
        "| phantom, position | k mean (N/m) | k SD (N/m) | R^2 order 1 / 2 / 3 | max force (N) | LK tracks kept |",
        "|---|---|---|---|---|---|",
    ]
    for name, row in results.stiffness.items():
        r2 = row["r2"]
        lines.append(
            f"| {name} | {row['mean_n_per_m']:.0f} | {row['sd_n_per_m']:.0f} | "
            f"{r2['1']:.4f} / {r2['2']:.4f} / {r2['3']:.4f} | {row['max_force_n']:.1f} | "
            f"{row['tracks_kept']:.0%} of {row['tracks']} |"
        )
    lines += [
        "",
        "## Diagnosis: fitted displacement against the true field (pixels)",
        "",
        "`h share`: norm of the displacement the h terms of M give, over the norm of the whole "
        "displacement; the rest integrates to a multiple of F whatever the stiffness, so it cannot "
        "follow a change of tissue (not defined over lambda, where every term follows the stiffness).",
        "",
        "| case | model | mean error near vessel | mean error elsewhere | R^2 lateral | R^2 axial | h share |",
        "|---|---|---|---|---|---|---|",
    ]
    for case, models in results.diagnosis.items():
        for model, row in models.items():
            lines.append(
                f"| {case} | {model} | {row['near_vessel_px']:.2f} | {row['elsewhere_px']:.2f} | "
                f"{row['r2_lateral']:.3f} | {row['r2_axial']:.3f} | {row['h_terms_share']:.3f} |"
            )
    (output / "results.md").write_text("\n".join(lines) + "\n")
    payload = {
        "config": asdict(config),
        "table_1": results.table_1,
        "stiffness": results.stiffness,
        "diagnosis": results.diagnosis,
        "fit_seconds_per_position": results.fit_seconds_per_position,
        "cases": [asdict(c) for c in results.cases],
    }
    (output / "results.json").write_text(json.dumps(payload, indent=1))


def plot_stiffness(palpations: dict, path: Path) -> None:
    """Fig. 4: force against probe displacement (mm) and the polynomial fits, stiff and soft phantom."""
    figure = Figure(figsize=(9, 3.6))
    axes = figure.subplots(1, 2)
    for axis, name in zip(axes, ("stiff", "soft"), strict=False):
        key = next(k for k in palpations if k[0] == name)
        fit = palpations[key].sampled.stiffness
        lam = np.linspace(fit.probe_displacement_mm.min(), fit.probe_displacement_mm.max(), 200)
        axis.plot(fit.probe_displacement_mm, fit.force_n, ".", color="0.5", label="samples")
        for order, coefficients in fit.polynomials.items():
            axis.plot(lam, np.polyval(coefficients, lam), label=f"Poly{order} (R$^2$ = {fit.r_squared[order]:.4f})")
        mean, sd = fit.stiffness_mean_sd_n_per_m
        axis.set(
            title=f"{name} phantom: k = {mean:.0f} $\\pm$ {sd:.0f} N/m", xlabel="$\\lambda_z$ (mm)", ylabel="force (N)"
        )
        axis.legend(fontsize=7)
    figure.tight_layout()
    figure.savefig(path, dpi=120)


def _contour(axis, mask: np.ndarray, color: str, label: str) -> None:
    if mask.any():
        axis.contour(mask.astype(float), levels=[0.5], colors=[color], linewidths=1.2)
        axis.plot([], [], color=color, label=label)


def plot_overlays(figures: dict, path: Path) -> None:
    """Figs. 6-8: each case's frame with the vessel boundary at zero force, deformed and corrected."""
    figure = Figure(figsize=(3.4 * len(figures), 3.6))
    axes = figure.subplots(1, len(figures))
    for axis, (title, (palpated, index, masks)) in zip(np.atleast_1d(axes), figures.items(), strict=False):
        axis.imshow(palpated.recording.frames[index], cmap="gray")
        for name, color in (
            ("reference", "lime"),
            ("deformed", "red"),
            ("paper", "deepskyblue"),
            ("force", "yellow"),
            ("spline", "magenta"),
            ("spline-lambda", "orange"),
        ):
            _contour(axis, masks[name], color, "zero force" if name == "reference" else name)
        axis.set_title(f"{title}, {palpated.force[index]:.1f} N", fontsize=8)
        axis.axis("off")
    np.atleast_1d(axes)[0].legend(fontsize=7, loc="lower left")
    figure.tight_layout()
    figure.savefig(path, dpi=120)


def plot_residuals(models: dict[str, DisplacementModel], palpated: Palpated, index: int, path: Path) -> None:
    """|D| of the true field and |fitted - true| of the paper's model, the B-spline model and both oracles."""
    true_field = np.moveaxis(palpated.truth.displacement_px[index].astype(np.float64), -1, 0)
    profile = palpated.sampled.stiffness.profile
    force = palpated.force[index]
    maps = [("true |D| (px)", np.linalg.norm(true_field, axis=0))]
    for name in ("paper", "spline", "oracle", "oracle-spline"):
        error = models[name].displacement(force, profile, true_field.shape[1:]) - true_field
        maps.append((f"|{name} - true| (px)", np.linalg.norm(error, axis=0)))
    figure = Figure(figsize=(3.6 * len(maps), 3.4))
    axes = figure.subplots(1, len(maps))
    error_limit = max(np.nanpercentile(values, 99) for _, values in maps[1:])  # one scale for all error maps
    for number, (axis, (title, values)) in enumerate(zip(axes, maps, strict=False)):
        image = axis.imshow(values, cmap="magma", vmin=0, vmax=None if number == 0 else error_limit)
        _contour(axis, palpated.truth.zero_force_vessel_mask[index], "cyan", "lumen at zero force")
        axis.set_title(f"{title}, {force:.1f} N", fontsize=8)
        axis.axis("off")
        figure.colorbar(image, ax=axis, fraction=0.046)
    figure.tight_layout()
    figure.savefig(path, dpi=120)
