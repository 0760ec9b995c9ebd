"""The paper-2d experiments' run: the palpations, the fits and the evaluations in the paper's order."""

from __future__ import annotations

import time
from pathlib import Path

from tqdm import tqdm

from ...options import SOLVERS
from ...regression import DisplacementModel, fit_regression
from ...sim import soft_phantom, stiff_phantom
from .config import Paper2dConfig, Paper2dResults, methods_for
from .evaluation import configured_phantom, evaluate, fit_method, palpate, residuals_by_region
from .report import plot_overlays, plot_residuals, plot_stiffness, write_tables

__all__ = ["run_paper_2d"]


def run_paper_2d(
    output_dir: str | Path, config: Paper2dConfig | None = None, *, progress: bool = True
) -> Paper2dResults:
    """Run the four experiments of ``config`` (None: :class:`Paper2dConfig`'s defaults); write ``results.md``,
    ``results.json`` and the figures to ``output_dir``.

    ``progress``: a tqdm bar on stderr, one step per palpation (simulated, measured and evaluated; the
    first one solves the phantom's finite-element sections), per fitted method and for the figures.
    """
    config = Paper2dConfig() if config is None else config
    output = Path(output_dir)
    output.mkdir(parents=True, exist_ok=True)
    stiff, soft = configured_phantom(stiff_phantom(), config), configured_phantom(soft_phantom(), config)
    results = Paper2dResults()
    methods = methods_for(config)
    n_palpations = 3 + len(config.stiff_other_positions_mm) + len(config.soft_positions_mm)
    bar = tqdm(total=n_palpations + len(methods) + 1, desc="paper-2d", unit="step", disable=not progress)

    # Fitting position: three palpations of the stiff phantom; fit on two (TABLE I), validate on the third.
    fit_palpations = []
    for i in range(3):
        bar.set_postfix_str(f"palpation {i + 1} at the stiff phantom's fitting position")
        fit_palpations.append(
            palpate(stiff, config.stiff_fit_position_mm, config.stiff_max_force_n, config.seed + i, config)
        )
        bar.update()
    start = time.perf_counter()
    fits = {
        solver: fit_regression([p.sampled.observations for p in fit_palpations[:2]], solver=solver)
        for solver in SOLVERS
    }
    regression_seconds = time.perf_counter() - start
    results.fit_seconds_per_position = sum(p.sampled.seconds for p in fit_palpations[:2]) / 2 + regression_seconds / 2
    for solver, fit in fits.items():
        results.table_1[solver] = {
            "K_lateral": fit.model.coefficients[0].tolist(),
            "K_axial": fit.model.coefficients[1].tolist(),
            "loss": fit.loss,
            "iterations": fit.iterations,
        }
    models: dict[str, DisplacementModel] = {}
    for m in methods:
        bar.set_postfix_str(f"fit {m.name}")
        models[m.name] = (
            fits[config.solver].model if m.name == "paper" else fit_method(m, fit_palpations[:2], config.solver)
        )
        bar.update()

    figures: dict[str, tuple] = {}
    validation = fit_palpations[2]
    for force in config.stiff_forces_n:
        case, index, masks = evaluate("same position", "stiff", config.stiff_fit_position_mm, force, validation, models)
        results.cases.append(case)
        figures["same position"] = (validation, index, masks)
    results.diagnosis["stiff, same position, highest force"] = {
        name: residuals_by_region(model, validation, figures["same position"][1]) for name, model in models.items()
    }

    palpations = {("stiff", config.stiff_fit_position_mm): fit_palpations[0]}
    for number, position in enumerate(config.stiff_other_positions_mm):
        bar.set_postfix_str(f"stiff phantom at {position:g} mm")
        palpated = palpate(stiff, position, config.stiff_max_force_n, config.seed + 10 + number, config)
        palpations[("stiff", position)] = palpated
        for force in config.stiff_forces_n:
            case, index, masks = evaluate("other position", "stiff", position, force, palpated, models)
            results.cases.append(case)
            figures[f"other position {position:g} mm"] = (palpated, index, masks)
        bar.update()
    for number, position in enumerate(config.soft_positions_mm):
        bar.set_postfix_str(f"soft phantom at {position:g} mm")
        palpated = palpate(soft, position, config.soft_max_force_n, config.seed + 20 + number, config)
        palpations[("soft", position)] = palpated
        for force in config.soft_forces_n:
            case, index, masks = evaluate("unseen soft tissue", "soft", position, force, palpated, models)
            results.cases.append(case)
            figures["unseen soft tissue"] = (palpated, index, masks)
        results.diagnosis[f"soft {position:g} mm, highest force"] = {
            name: residuals_by_region(model, palpated, figures["unseen soft tissue"][1])
            for name, model in models.items()
        }
        bar.update()
    for (name, position), palpated in palpations.items():
        stiffness = palpated.sampled.stiffness
        mean, sd = stiffness.stiffness_mean_sd_n_per_m
        results.stiffness[f"{name} {position:g} mm"] = {
            "mean_n_per_m": mean,
            "sd_n_per_m": sd,
            "r2": {str(k): v for k, v in stiffness.r_squared.items()},
            "max_force_n": float(palpated.force.max()),
            "tracks_kept": palpated.sampled.tracked.kept_fraction,
            "tracks": len(palpated.sampled.tracked.points_px),
        }

    bar.set_postfix_str("tables and figures")
    write_tables(results, config, methods, output)
    plot_stiffness(palpations, output / "fig4_stiffness.png")
    plot_overlays(figures, output / "fig6-8_vessel_boundaries.png")
    plot_residuals(models, validation, figures["same position"][1], output / "residual_maps.png")
    bar.update()
    bar.close()
    return results
