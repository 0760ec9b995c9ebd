"""The paper's 2D experiments (Section IV-A: TABLES I and II, Figs. 4 and 6-8) on the simulated phantoms.

1. Same position: the model is fitted on two palpations of the stiff phantom and corrects a third
   at 5-25 N (paper: Dice 0.69 -> 0.92 at 25 N).
2. Other positions of the stiff phantom, more than 20 mm away, with only their stiffness
   (paper: corrected Dice 0.96 on average).
3. The unseen soft phantom at 2-8 N with the stiff phantom's model, against the force-based
   baseline (Sun et al. 2010) fitted at the same place (paper: 0.66 -> 0.89 by stiffness, 0.74 by force).
4. TABLE II: every position and force, for both methods.

Every experiment runs the methods of :func:`methods_for` side by side: the paper's quadratic model,
the force-based baseline, the cubic B-spline spatial basis with the same force and stiffness coupling
(issue 5), each optionally integrated over probe displacement instead of force, and "oracles" (a
model fitted to the simulator's true displacement field: no optical-flow error).

Dice compares the vessel segmented (:func:`usdeform.metrics.segment_vessel`) in the deformed or
corrected frame with the vessel segmented in the simulator's zero-force frame at the same probe
position. The diagnosis compares each fitted displacement with the true one by region, which
separates what a model cannot represent from what the tracking gets wrong.
"""

from __future__ import annotations

import json
import time
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path

import numpy as np
from matplotlib.figure import Figure
from tqdm import tqdm

from ..correction import correct_frames
from ..errors import InputError
from ..metrics import area_mm2, centroid_distance_mm, dice, pixel_size_mm, segment_vessel
from ..options import SOLVERS, Basis, Coupling, Integration, Solver
from ..recording import Recording
from ..regression import DisplacementModel, Observations, fit_regression
from ..sampling import SampledPosition, measure_palpation
from ..sim import GroundTruth, Phantom, simulate_palpation, soft_phantom, stiff_phantom

__all__ = ["QUICK", "Method", "Paper2dConfig", "methods_for", "run_paper_2d"]

#: Columns of K whose term in M contains h (h^2, xh, yh, h): the only ones a stiffness change affects.
H_TERMS = (2, 4, 5, 8)


@dataclass(frozen=True)
class Paper2dConfig:
    """What the experiments simulate: frame size, palpation length, positions (mm along the
    phantom) and evaluation forces (N). ``mesh_size_mm`` overrides the presets' mesh (quick runs)."""

    rows: int = 256
    cols: int = 256
    n_frames: int = 50
    stiff_fit_position_mm: float = 10.0
    stiff_other_positions_mm: tuple[float, ...] = (32.0, 54.0, 76.0)
    soft_positions_mm: tuple[float, ...] = (10.0, 35.0, 60.0)
    stiff_forces_n: tuple[float, ...] = (5.0, 10.0, 15.0, 20.0, 25.0)
    soft_forces_n: tuple[float, ...] = (2.0, 4.0, 6.0, 8.0)
    stiff_max_force_n: float = 30.0
    soft_max_force_n: float = 16.0
    solver: Solver = "exact"
    bspline_functions: tuple[int, int] = (8, 8)
    seed: int = 0
    mesh_size_mm: float | None = None


@dataclass(frozen=True)
class Method:
    """A correction method: the model's spatial ``basis``, ``coupling`` and ``integration``, and
    whether it is fitted to the tracked displacements or to the simulator's true field (``truth``)."""

    name: str
    basis: Basis | tuple[str, int, int]
    coupling: Coupling
    integration: Integration
    truth: bool
    description: str


def methods_for(config: Paper2dConfig) -> tuple[Method, ...]:
    """The compared methods; ``paper`` and ``force`` are the paper's comparison."""
    spline = ("bspline", *config.bspline_functions)
    size = "x".join(str(n) for n in config.bspline_functions)
    return (
        Method("paper", "quadratic", "stiffness", "force", False, "the paper's model (eq. 8, over force)"),
        Method("force", "quadratic", "force", "force", False, "force-based baseline of Sun et al. 2010 (h = F)"),
        Method(
            "paper-lambda",
            "quadratic",
            "stiffness",
            "displacement",
            False,
            "the paper's model integrated over probe displacement (dlambda = dF/k) instead of force",
        ),
        Method("spline", spline, "stiffness", "force", False, f"cubic B-spline basis {size}, coupled as the paper"),
        Method("spline-force", spline, "force", "force", False, f"cubic B-spline basis {size}, h = F"),
        Method(
            "spline-lambda",
            spline,
            "stiffness",
            "displacement",
            False,
            f"cubic B-spline basis {size}, integrated over probe displacement",
        ),
        Method("oracle", "quadratic", "stiffness", "force", True, "the paper's model fitted to the true field"),
        Method("oracle-spline", spline, "stiffness", "force", True, f"B-spline {size} fitted to the true field"),
    )


#: A small, fast configuration for smoke tests (coarse mesh, small frames, one position each).
QUICK = Paper2dConfig(
    rows=128,
    cols=128,
    n_frames=30,
    stiff_other_positions_mm=(40.0,),
    soft_positions_mm=(40.0,),
    stiff_forces_n=(10.0, 25.0),
    soft_forces_n=(4.0, 8.0),
    mesh_size_mm=4.0,
)


@dataclass(frozen=True)
class CorrectionCase:
    """One evaluated frame: Dice, area error (mm^2, frame minus zero force) and centroid distance (mm)
    of the deformed frame and of the frame corrected by each method."""

    experiment: str
    phantom: str
    position_mm: float
    target_force_n: float
    force_n: float
    dice: dict[str, float]
    area_error_mm2: dict[str, float]
    centroid_error_mm: dict[str, float]


@dataclass
class Palpated:
    """A simulated palpation, its ground truth and what the pipeline measured from it."""

    recording: Recording
    truth: GroundTruth
    sampled: SampledPosition

    @property
    def force(self) -> np.ndarray:
        """Each frame's force, N (a simulated palpation always records it)."""
        if self.recording.force is None:
            raise InputError("recording: a palpation needs per-frame force")
        return self.recording.force


@dataclass
class Paper2dResults:
    """What :func:`run_paper_2d` measured: TABLE I per solver, the correction cases (TABLE II), the
    stiffness fits, the fitted-against-true diagnosis and the fitting time per position (s)."""

    table_1: dict[str, dict] = field(default_factory=dict)
    cases: list[CorrectionCase] = field(default_factory=list)
    stiffness: dict[str, dict] = field(default_factory=dict)
    diagnosis: dict[str, dict] = field(default_factory=dict)
    fit_seconds_per_position: float = 0.0


def _phantom(preset: Phantom, config: Paper2dConfig) -> Phantom:
    return preset if config.mesh_size_mm is None else preset.with_section_changes(mesh_size_mm=config.mesh_size_mm)


def _palpate(phantom: Phantom, position_mm: float, max_force_n: float, seed: int, config: Paper2dConfig) -> Palpated:
    recording, truth = simulate_palpation(
        phantom, position_mm, max_force_n, n_frames=config.n_frames, seed=seed, rows=config.rows, cols=config.cols
    )
    sampled = measure_palpation(recording, flexible_layer_mm=phantom.base_section.depth_mm)
    return Palpated(recording, truth, sampled)


def _segment(frame: np.ndarray, seed_px: tuple[float, float]) -> np.ndarray:
    """The vessel mask, or an empty mask when no anechoic lumen is found (a failed correction)."""
    try:
        return segment_vessel(frame, seed_px=seed_px).mask
    except InputError:
        return np.zeros(frame.shape, dtype=bool)


def _evaluate(
    experiment: str,
    phantom: str,
    position_mm: float,
    target_force_n: float,
    palpated: Palpated,
    models: dict[str, DisplacementModel],
) -> tuple[CorrectionCase, int, dict[str, np.ndarray]]:
    """Correct the palpation frame nearest ``target_force_n`` with each model; compare with zero force."""
    recording, truth = palpated.recording, palpated.truth
    index = int(np.argmin(np.abs(palpated.force - target_force_n)))
    pixel_size = pixel_size_mm(recording.image_to_probe)
    reference = segment_vessel(truth.zero_force_frames[index]).mask
    row, col = np.argwhere(reference).mean(axis=0)
    seed = (float(col), float(row))
    masks = {"deformed": _segment(recording.frames[index], seed)}
    for name, model in models.items():
        corrected = correct_frames(
            recording.frames[index], palpated.force[index], palpated.sampled.stiffness.profile, model
        )
        masks[name] = _segment(corrected, seed)
    scores = {name: dice(mask, reference) if mask.any() else 0.0 for name, mask in masks.items()}
    areas = {
        name: area_mm2(mask, pixel_size) - area_mm2(reference, pixel_size) if mask.any() else float("nan")
        for name, mask in masks.items()
    }
    centroids = {
        name: centroid_distance_mm(mask, reference, pixel_size) if mask.any() else float("nan")
        for name, mask in masks.items()
    }
    case = CorrectionCase(
        experiment, phantom, position_mm, target_force_n, float(palpated.force[index]), scores, areas, centroids
    )
    return case, index, {"reference": reference, **masks}


def _true_observations(palpated: Palpated, spacing_px: int = 8) -> Observations:
    """The simulator's true displacement from zero force on a grid, as regression observations."""
    truth, recording = palpated.truth, palpated.recording
    rows, cols = recording.frames.shape[1:]
    y, x = np.mgrid[spacing_px // 2 : rows : spacing_px, spacing_px // 2 : cols : spacing_px]
    displacements = truth.displacement_px[:, y.ravel(), x.ravel(), :].astype(np.float64)
    valid = np.all(np.isfinite(displacements), axis=2)
    points = np.stack([x.ravel(), y.ravel()], axis=1).astype(np.float64)
    return Observations(
        points,
        np.where(valid[..., None], displacements, np.nan),
        valid,
        palpated.force,
        0.0,
        palpated.sampled.stiffness.profile,
        (rows, cols),
    )


def _stiffness_independent_part_removed(model: DisplacementModel) -> DisplacementModel:
    """``model`` without the terms that integrate to a multiple of F whatever the stiffness: the
    quadratic's columns without h, the B-spline's force term ``1``."""
    coefficients = model.coefficients.copy()
    if coefficients.ndim == 2:
        coefficients[:, [t for t in range(10) if t not in H_TERMS]] = 0.0
    else:
        coefficients[:, 0] = 0.0
    return replace(model, coefficients=coefficients)


def _residuals_by_region(model: DisplacementModel, palpated: Palpated, index: int) -> dict[str, float]:
    """Mean |fitted - true| displacement (pixels) near the vessel and elsewhere, and R^2 per component."""
    truth = palpated.truth
    true_field = np.moveaxis(truth.displacement_px[index].astype(np.float64), -1, 0)
    fitted = model.displacement(palpated.force[index], palpated.sampled.stiffness.profile, true_field.shape[1:])
    tissue = np.all(np.isfinite(true_field), axis=0)
    lumen = truth.zero_force_vessel_mask[index]
    rows, cols = lumen.shape
    y, x = np.mgrid[0:rows, 0:cols]
    centre = np.argwhere(lumen).mean(axis=0) if lumen.any() else np.array([rows / 2, cols / 2])
    radius = np.sqrt(lumen.sum() / np.pi) if lumen.any() else rows / 8
    distance = np.hypot(y - centre[0], x - centre[1])
    near = tissue & (distance < 2 * radius)
    error = np.linalg.norm(fitted - np.nan_to_num(true_field), axis=0)
    r_squared = {}
    for component, name in enumerate(("lateral", "axial")):
        values = true_field[component][tissue]
        r_squared[name] = float(
            1 - np.sum((fitted[component][tissue] - values) ** 2) / np.sum((values - values.mean()) ** 2)
        )
    # The terms without h integrate to a multiple of F whatever the stiffness; only the h terms
    # respond to a new stiffness profile. Their share of the displacement bounds how much
    # propagation by stiffness can change the prediction.
    h_only = _stiffness_independent_part_removed(model)
    from_h = h_only.displacement(palpated.force[index], palpated.sampled.stiffness.profile, true_field.shape[1:])
    share = (
        float(np.linalg.norm(from_h[:, tissue]) / np.linalg.norm(fitted[:, tissue]))
        if model.integration == "force"
        else float("nan")
    )  # integrated over lambda, every term follows k
    return {
        "near_vessel_px": float(error[near].mean()),
        "elsewhere_px": float(error[tissue & ~near].mean()),
        "r2_lateral": r_squared["lateral"],
        "r2_axial": r_squared["axial"],
        "h_terms_share": share,
    }


def _fit(method: Method, palpations: list[Palpated], solver: Solver) -> DisplacementModel:
    observations = [_true_observations(p) if method.truth else p.sampled.observations for p in palpations]
    return fit_regression(
        observations,
        solver=solver if method.basis == "quadratic" else "exact",
        coupling=method.coupling,
        integration=method.integration,
        basis=method.basis,
    ).model


def run_paper_2d(
    output_dir: str | Path, config: Paper2dConfig = Paper2dConfig(), *, progress: bool = True
) -> Paper2dResults:
    """Run the four experiments; write ``results.md``, ``results.json`` and the figures to ``output_dir``.

    ``progress``: a tqdm bar on stderr, one step per palpation (simulated, measured and evaluated; the
    first one solves the phantom's finite-element sections), per fitted method and for the figures.
    """
    output = Path(output_dir)
    output.mkdir(parents=True, exist_ok=True)
    stiff, soft = _phantom(stiff_phantom(), config), _phantom(soft_phantom(), config)
    results = Paper2dResults()
    methods = methods_for(config)
    n_palpations = 3 + len(config.stiff_other_positions_mm) + len(config.soft_positions_mm)
    bar = tqdm(total=n_palpations + len(methods) + 1, desc="paper-2d", unit="step", disable=not progress)

    # Fitting position: three palpations of the stiff phantom; fit on two (TABLE I), validate on the third.
    fit_palpations = []
    for i in range(3):
        bar.set_postfix_str(f"palpation {i + 1} at the stiff phantom's fitting position")
        fit_palpations.append(
            _palpate(stiff, config.stiff_fit_position_mm, config.stiff_max_force_n, config.seed + i, config)
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
        models[m.name] = fits[config.solver].model if m.name == "paper" else _fit(m, fit_palpations[:2], config.solver)
        bar.update()

    figures: dict[str, tuple] = {}
    validation = fit_palpations[2]
    for force in config.stiff_forces_n:
        case, index, masks = _evaluate(
            "same position", "stiff", config.stiff_fit_position_mm, force, validation, models
        )
        results.cases.append(case)
        figures["same position"] = (validation, index, masks)
    results.diagnosis["stiff, same position, highest force"] = {
        name: _residuals_by_region(model, validation, figures["same position"][1]) for name, model in models.items()
    }

    palpations = {("stiff", config.stiff_fit_position_mm): fit_palpations[0]}
    for number, position in enumerate(config.stiff_other_positions_mm):
        bar.set_postfix_str(f"stiff phantom at {position:g} mm")
        palpated = _palpate(stiff, position, config.stiff_max_force_n, config.seed + 10 + number, config)
        palpations[("stiff", position)] = palpated
        for force in config.stiff_forces_n:
            case, index, masks = _evaluate("other position", "stiff", position, force, palpated, models)
            results.cases.append(case)
            figures[f"other position {position:g} mm"] = (palpated, index, masks)
        bar.update()
    for number, position in enumerate(config.soft_positions_mm):
        bar.set_postfix_str(f"soft phantom at {position:g} mm")
        palpated = _palpate(soft, position, config.soft_max_force_n, config.seed + 20 + number, config)
        palpations[("soft", position)] = palpated
        for force in config.soft_forces_n:
            case, index, masks = _evaluate("unseen soft tissue", "soft", position, force, palpated, models)
            results.cases.append(case)
            figures["unseen soft tissue"] = (palpated, index, masks)
        results.diagnosis[f"soft {position:g} mm, highest force"] = {
            name: _residuals_by_region(model, palpated, figures["unseen soft tissue"][1])
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
    _write_tables(results, config, methods, output)
    _plot_stiffness(palpations, output / "fig4_stiffness.png")
    _plot_overlays(figures, output / "fig6-8_vessel_boundaries.png")
    _plot_residuals(models, validation, figures["same position"][1], output / "residual_maps.png")
    bar.update()
    bar.close()
    return results


def _summary(cases: list[CorrectionCase], experiment: str, force: float, method: str, metric: str) -> float:
    """Mean Dice, or mean absolute area error (mm^2), of ``method`` over the cases at one force."""
    values = [
        c.dice[method] if metric == "dice" else abs(c.area_error_mm2[method])
        for c in cases
        if c.experiment == experiment and c.target_force_n == force
    ]
    return float(np.mean(values)) if values else float("nan")


def _write_tables(results: Paper2dResults, config: Paper2dConfig, methods: tuple[Method, ...], output: Path) -> None:
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


def _plot_stiffness(palpations: dict, path: Path) -> None:
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


def _plot_overlays(figures: dict, path: Path) -> None:
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


def _plot_residuals(models: dict[str, DisplacementModel], palpated: Palpated, index: int, path: Path) -> None:
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
