"""``usdeform fit``: fit a deformation model to one position's palpations and write the model file."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from ..compensation import add_compensation_options
from ..errors import InputError
from ..options import NUMBERS
from ._palpations import FIT_METHODS, parse_basis

__all__ = ["add_fit_command"]


def _basis(text: str) -> str:
    """An argparse type: the basis notation of :func:`usdeform.fitting.parse_basis`, checked."""
    try:
        parse_basis(text)
    except InputError as error:
        raise argparse.ArgumentTypeError(str(error).removeprefix("basis: ")) from None
    return text


def _check_report_folder(report: Path, output: Path) -> None:
    """Refuse, before the fit, a --report folder that is the --output file, or whose report.html or report.json
    is a folder or the --output file (the model would be written, the report not)."""
    from .._files import check_output_folder

    check_output_folder(report, "--report")
    if report.resolve() == output.resolve():
        raise InputError(f"--report: {report} is the --output file; give the report a folder of its own")
    for name in ("report.html", "report.json"):
        path = report / name
        if path.is_dir():
            raise InputError(f"--report: {path} is a folder; the report writes a file there")
        if path.resolve() == output.resolve():
            raise InputError(f"--report: {path} is the --output file; it would be overwritten")


def _fit(args: argparse.Namespace) -> None:
    from tqdm import tqdm

    from .._files import check_output_paths
    from ..pipeline import PipelineSettings, fit_model

    labels = [f"PALPATION {index + 1}" for index in range(len(args.palpations))]
    check_output_paths({"--output": (args.output, (".json",))}, dict(zip(labels, args.palpations, strict=True)))
    if args.report is not None:
        _check_report_folder(Path(args.report), Path(args.output))
    settings = PipelineSettings.from_arguments(args)
    # One bar over the stages: reading each palpation, then measuring them (stiffness, optical flow,
    # vessel wall) and the regression.
    with tqdm(total=len(args.palpations) + 1, desc="fit", unit="step", leave=False) as progress:

        def step(description: str) -> None:  # a step starts: the one before it is done
            if progress.postfix is not None:
                progress.update()
            progress.set_postfix_str(description)

        run = fit_model(args.palpations, settings, args.output, report_dir=args.report, labels=labels, progress=step)
        progress.update()
    fitted, method = run.fitted, run.fitted.method
    for path, position, measured, phases in zip(
        args.palpations, fitted.sampled.positions_mm, fitted.measured, fitted.phases, strict=True
    ):
        mean, sd = measured.stiffness.stiffness_mean_sd_n_per_m
        print(
            f"{path}: stiffness {mean:.0f} +/- {sd:.0f} N/m (R^2 {measured.stiffness.r_squared[2]:.4f}) "
            f"at ({', '.join(f'{v:.1f}' for v in position)}) mm in the base frame; vessel wall {measured.wall_note}"
        )
        print(f"{path}: {phases.summary()}")
    for note in fitted.provenance.get("compensation", {}).get("notes", []):
        print(note)
    fit = fitted.fit
    smoothness = f", smoothness {fit.smoothness:.3g}" if fit.smoothness > 0 else ""
    anchored = (
        "anchored to the vessel"
        if fitted.provenance["anchor"] == "vessel"
        else "in image coordinates" + (" (no palpation shows a lumen)" if method.anchor == "vessel" else "")
    )
    print(
        f"fitted the {args.method} method ({method.description}; {anchored}) on {fit.n_samples} samples "
        f"({fit.solver}{smoothness}): loss {fit.loss:.4g}; wrote {', '.join(str(path) for path in run.written)}"
    )
    for warning in run.report.warnings:
        print(f"usdeform: warning: {warning}", file=sys.stderr)


def add_fit_command(commands: argparse._SubParsersAction) -> None:
    """Register ``usdeform fit PALPATION... --output MODEL ...``."""
    fit = commands.add_parser("fit", help="fit a deformation model to palpations, write a model file (JSON)")
    fit.add_argument(
        "palpations",
        type=Path,
        nargs="+",
        metavar="PALPATION",
        help="PLUS sequence file of a palpation, with ContactForce and ProbeDisplacement fields",
    )
    fit.add_argument("--output", type=Path, required=True, metavar="MODEL", help="model file to write (.json)")
    _add_fit_options(fit)
    fit.add_argument(
        "--report",
        type=Path,
        metavar="DIR",
        help="also write DIR/report.html (tracks per depth band, fitted against tracked field, stiffness fits, "
        "cross-validated residual by region, warnings) and DIR/report.json with its numbers",
    )
    add_compensation_options(fit)
    fit.set_defaults(run=_fit)


def _add_fit_options(fit: argparse.ArgumentParser) -> None:
    """The fit's settings, with the pipeline's defaults."""
    from ..pipeline import CHOICES, PipelineSettings

    defaults = PipelineSettings()
    fit.add_argument(
        "--flexible-layer-mm",
        type=NUMBERS["flexible_layer_mm"].argument(),
        required=True,
        metavar="MM",
        help="thickness of the compressible tissue under the probe, mm (paper eq. 10)",
    )
    fit.add_argument(
        "--method",
        choices=CHOICES["method"],
        default=defaults.method,
        help="; ".join(f"{name}: {method.description}" for name, method in FIT_METHODS.items())
        + f" (default: {defaults.method}; the options below change single settings)",
    )
    fit.add_argument(
        "--basis",
        type=_basis,
        metavar="quadratic|bspline:NXxNY",
        help="'quadratic' (the paper) or 'bspline:NXxNY' cubic B-splines along x and y (default: the method's)",
    )
    fit.add_argument(
        "--solver",
        choices=CHOICES["solver"],
        default=defaults.solver,
        help=f"the regression's solver: exact least squares or the paper's ADAM (default: {defaults.solver})",
    )
    fit.add_argument(
        "--coupling",
        choices=CHOICES["coupling"],
        help="stiffness: h = F/k (the paper); force: h = F (the force-based baseline) (default: the method's)",
    )
    fit.add_argument(
        "--integration",
        choices=CHOICES["integration"],
        help="integrate the displacement rate over force (the paper) or probe displacement (default: the method's)",
    )
    fit.add_argument(
        "--smoothness",
        type=NUMBERS["smoothness"].argument(),
        metavar="S",
        help="B-spline second-difference penalty weight (default: chosen by cross-validation)",
    )
    fit.add_argument(
        "--wall",
        choices=CHOICES["wall"],
        help="fit the vessel wall's measured displacements too: where a lumen is found (auto), always (require: "
        "an error without one) or never (off) (default: the method's)",
    )
    fit.add_argument(
        "--anchor",
        choices=CHOICES["anchor"],
        help="tie the model to the image, or in part to the vessel's lumen, which it then follows along the sweep "
        "(needs the wall) (default: the method's)",
    )
    fit.add_argument(
        "--wall-weight",
        type=NUMBERS["wall_weight"].argument(),
        default=defaults.wall_weight,
        metavar="W",
        help=f"weight of the wall's mean squared error against the tracks' (default: {defaults.wall_weight:g})",
    )
