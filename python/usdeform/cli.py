"""The ``usdeform`` command line.

usdeform demo [--output DIR] [--quick]      the whole method on the simulator, with report.html
usdeform reconstruct SEQUENCE --output FILE  compound a PLUS sequence file into a volume
usdeform fit PALPATION... --output MODEL     fit a deformation model to palpations, write a model file
usdeform correct SWEEP --model MODEL --output FILE [--volume FILE]
                                             correct a sweep to zero force (and compound it)
usdeform simulate palpation|sweep --output DIR [--effect NAME:P=V,...]
                                             simulated recordings with their ground truth
usdeform experiment paper-2d --output DIR    reproduce the paper's 2D experiments on the simulator
usdeform experiment paper-3d --output DIR    reproduce the paper's 3D experiments on the simulator
usdeform experiment clinical-3d --output DIR correct clinical-shaped sweeps (artery and vein) per vessel
usdeform batch MANIFEST --out DIR [--scheduler ADDRESS] [--workers N]
                                             fit, correct and reconstruct a cohort on a Dask cluster
usdeform diagnose RECORDING... --out DIR     diagnose the gap between recordings and the simulator
usdeform gap-benchmark --cases N --out DIR   score the diagnosis on cases with a withheld effect
usdeform compensation-benchmark --cases N --out DIR
                                             what an effect costs the corrected volume, what --compensate recovers
usdeform live --model MODEL --listen HOST:PORT
                                             correct and compound a scan live from OpenIGTLink, send it to 3D Slicer
usdeform replay RECORDING --to HOST:PORT     play a sequence file over OpenIGTLink as PLUS Server would
"""

from __future__ import annotations

# Only light imports here: every command imports what it needs when it runs, inside main()'s handlers,
# so that Ctrl-C at any moment of a run is "usdeform: interrupted" and "usdeform --help" imports no
# command's dependencies (SciPy's statistics, Matplotlib, Dask, OpenCV, the simulator).
import argparse
import importlib
import shlex
import signal
import sys
import threading
import time
import warnings
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from types import FrameType
from typing import TYPE_CHECKING, Any

from .errors import InputError, UsdeformError
from .options import NUMBERS
from .validation import ForceClampWarning

if TYPE_CHECKING:
    from .pipeline import PipelineSettings

__all__ = ["build_parser", "main"]


def _reconstruct(args: argparse.Namespace) -> None:
    from ._files import check_output_paths
    from .io import read_plus_config, read_sequence, write_volume
    from .io.volume_file import VOLUME_SUFFIXES
    from .pipeline import volume_keywords
    from .volume import compound_recording

    check_output_paths(
        {"--output": (args.output, VOLUME_SUFFIXES), "--coverage": (args.coverage, VOLUME_SUFFIXES)},
        {"SEQUENCE": args.sequence, "--config": args.config},
    )
    config = read_plus_config(args.config) if args.config else None
    recording = read_sequence(args.sequence, config=config)
    start = time.perf_counter()
    volume, n_compounded = compound_recording(
        recording,
        settings=config.reconstruction if config else None,
        name=str(args.sequence),
        **volume_keywords(args),
    )
    write_volume(args.output, volume, weight_path=args.coverage, compression_level=args.compression_level)
    print(
        f"compounded {n_compounded} of {len(recording)} frames into {volume.grid.shape} voxels "
        f"in {time.perf_counter() - start:.2f} s; wrote {args.output}"
    )


def _experiment(args: argparse.Namespace) -> None:
    start = time.perf_counter()
    results = "results.md"
    if args.name == "paper-3d":
        from .experiments import paper_3d

        results = paper_3d.run_command(args.output, quick=args.quick, nuisances=args.nuisance)
    elif args.nuisance is not None:
        raise InputError("--nuisance: only for paper-3d")
    elif args.name == "clinical-3d":
        from .experiments import clinical_3d

        results = clinical_3d.run_command(args.output, quick=args.quick)
    else:
        from .experiments import paper_2d

        paper_2d.run_paper_2d(args.output, paper_2d.QUICK if args.quick else paper_2d.Paper2dConfig())
    print(f"wrote {args.output / results} and figures in {time.perf_counter() - start:.0f} s")


def _basis(text: str) -> str:
    """An argparse type: the basis notation of :func:`usdeform.fitting.parse_basis`, checked."""
    from .fitting import parse_basis

    try:
        parse_basis(text)
    except InputError as error:
        raise argparse.ArgumentTypeError(str(error).removeprefix("basis: ")) from None
    return text


def _settings(args: argparse.Namespace) -> PipelineSettings:
    """The pipeline's settings from the options of ``fit`` or ``correct`` (the other command's at their defaults);
    a diagnosis to compensate is read here, so that a refused one is named by its flag before any work."""
    from .pipeline import SETTINGS_FIELDS, PipelineSettings

    settings = PipelineSettings(**{name: getattr(args, name) for name in SETTINGS_FIELDS if hasattr(args, name)})
    settings.compensation(option="--compensate", force_option="--force-compensation")
    return settings


def _fit(args: argparse.Namespace) -> None:
    from tqdm import tqdm

    from ._files import check_output_folder, check_output_paths
    from .pipeline import fit_model

    labels = [f"PALPATION {index + 1}" for index in range(len(args.palpations))]
    check_output_paths({"--output": (args.output, (".json",))}, dict(zip(labels, args.palpations, strict=True)))
    if args.report is not None:
        check_output_folder(args.report, "--report")
    settings = _settings(args)
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


def _correct(args: argparse.Namespace) -> None:
    from ._files import check_output_paths
    from .io.sequence_file import SEQUENCE_SUFFIXES
    from .io.volume_file import VOLUME_SUFFIXES
    from .pipeline import correct_sweep

    if args.coverage is not None and args.volume is None:
        raise InputError("--coverage: needs --volume")
    check_output_paths(
        {
            "--output": (args.output, SEQUENCE_SUFFIXES),
            "--volume": (args.volume, VOLUME_SUFFIXES),
            "--coverage": (args.coverage, VOLUME_SUFFIXES),
        },
        {"SWEEP": args.sweep, "--model": args.model},
    )
    run = correct_sweep(args.sweep, args.model, _settings(args), args.output, args.volume, args.coverage)
    if run.compensation is not None:
        print(*run.compensation["notes"], sep="\n")
    force = run.recording.force
    assert force is not None  # checked by correct_sweep
    chosen = {
        "sweep": " (auto: every frame records ContactForce and ProbeDisplacement)",
        "interpolated": " (auto: the sweep does not record ProbeDisplacement)",
    }
    print(
        f"corrected {len(run.recording)} frames at {force.min():.2f}-{force.max():.2f} N with "
        f"stiffness from {len(run.sampled.profiles)} sampled positions"
        + (", rescaled to each frame's force and displacement" if run.stiffness_source == "sweep" else "")
        + f"; stiffness source {run.stiffness_source}"
        + (chosen[run.stiffness_source] if args.stiffness_source == "auto" else "")
        + f"; wrote {args.output}"
    )
    if run.volume is not None:
        print(
            f"compounded {run.n_compounded} corrected frames into {run.volume.grid.shape} voxels; wrote {args.volume}"
        )


def _add_compensation_options(parser: argparse.ArgumentParser) -> None:
    """``--compensate`` and ``--force-compensation`` of ``fit`` and ``correct``."""
    parser.add_argument(
        "--compensate",
        type=Path,
        metavar="DIAGNOSIS",
        help="undo the recording effects a diagnosis.json ('usdeform diagnose') attributes the gap to, with its "
        "fitted parameters, before the method sees the recordings: image or force delay (frames re-paired in "
        "time), force-sensor offset and drift (subtracted), sound-speed mismatch (depth axis rescaled)",
    )
    parser.add_argument(
        "--force-compensation",
        action="store_true",
        help="compensate even where the diagnosis does not support it (verdict not 'explained' or "
        "'explained_in_part', effect not significant)",
    )


def _add_compounding_options(parser: argparse.ArgumentParser, from_config: bool) -> None:
    """The volume options (:func:`usdeform.pipeline.add_volume_options`); none on a command not run."""
    if isinstance(parser, _Unused):
        return
    from .pipeline import add_volume_options

    add_volume_options(parser, from_config)


#: The commands in the order of ``usdeform --help``: (module and function that registers the command, or
#: None for the commands of this module; the one-line help of the command's placeholder).
_COMMANDS: dict[str, tuple[tuple[str, str] | None, str]] = {
    "demo": ((".demo.command", "add_demo_command"), "the whole method on the simulator, with report.html"),
    "simulate": ((".simulate", "add_simulate_command"), "simulate palpations or sweeps with their ground truth"),
    "reconstruct": (None, "compound a PLUS sequence file into a volume"),
    "fit": (None, "fit a deformation model to palpations, write a model file (JSON)"),
    "correct": (None, "correct a sweep to zero force with a model file"),
    "experiment": (None, "reproduce the paper's experiments on the simulator"),
    "batch": ((".batch.command", "add_batch_command"), "fit, correct and reconstruct a cohort on a Dask cluster"),
    "diagnose": ((".gap.command", "add_diagnose_command"), "diagnose the sim-to-real gap of palpation recordings"),
    "gap-benchmark": ((".gap.command", "add_gap_benchmark_command"), "score the gap diagnosis on withheld effects"),
    "compensation-benchmark": (
        (".compensation_benchmark.command", "add_compensation_benchmark_command"),
        "what a recording effect costs the corrected volume and what --compensate gives back",
    ),
    "import-bag": ((".io.ros_bag", "add_import_bag_command"), "convert a ROS1/ROS2 bag into a PLUS sequence file"),
    "live": ((".live.command", "add_live_command"), "correct and compound a scan live from OpenIGTLink"),
    "replay": ((".live.command", "add_replay_command"), "play a sequence file over OpenIGTLink as PLUS Server would"),
}


class _Unused(argparse.ArgumentParser):
    """The parser of a command that is not run: what is added to it is dropped (its placeholder, with the
    command's help, stands in the command list)."""

    def add_argument(self, *args: Any, **kwargs: Any) -> Any:
        return None

    def set_defaults(self, **kwargs: Any) -> None:
        return None


def _chosen_command(argv: list[str] | None) -> str:
    """The command named in ``argv`` (its first argument that is not an option), or "" if none."""
    return next((part for part in (sys.argv[1:] if argv is None else argv) if not part.startswith("-")), "")


def build_parser(command: str | None = None) -> argparse.ArgumentParser:
    """The ``usdeform`` parser; each command sets ``run``, the function that executes it.

    ``command``: only that command's parser is built in full (and only its modules imported); the others
    are placeholders with their help, enough for ``usdeform --help``. None: every command in full."""
    parser = argparse.ArgumentParser(prog="usdeform", description="Deformation-aware robotic 3D ultrasound.")
    commands = parser.add_subparsers(dest="command", required=True)

    def command_parser(name: str, **kwargs: Any) -> argparse.ArgumentParser:
        if command is None or name == command:
            return commands.add_parser(name, **kwargs)
        return _Unused()

    for name, (registration, help_text) in _COMMANDS.items():
        if command is not None and name != command:
            commands.add_parser(name, help=help_text)
        elif registration is not None:
            module, function = registration
            getattr(importlib.import_module(module, __package__), function)(commands)
        # else: a command of this module, added in full below

    reconstruct = command_parser("reconstruct", help="compound a PLUS sequence file into a volume")
    reconstruct.add_argument("sequence", type=Path, help="PLUS sequence file (.mha, .seq.nrrd)")
    reconstruct.add_argument("--output", type=Path, required=True, help="volume file (.nrrd, .mha)")
    reconstruct.add_argument("--config", type=Path, help="PLUS XML configuration (calibration, settings)")
    _add_compounding_options(reconstruct, from_config=True)
    reconstruct.set_defaults(run=_reconstruct)

    fit = command_parser("fit", help="fit a deformation model to palpations, write a model file (JSON)")
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
    _add_compensation_options(fit)
    fit.set_defaults(run=_fit)

    correct = command_parser("correct", help="correct a sweep to zero force with a model file")
    correct.add_argument(
        "sweep", type=Path, metavar="SWEEP", help="PLUS sequence file of the sweep, with ContactForce fields"
    )
    correct.add_argument(
        "--model", type=Path, required=True, metavar="MODEL", help="model file written by 'usdeform fit'"
    )
    correct.add_argument(
        "--output", type=Path, required=True, metavar="FILE", help="corrected sequence file (.seq.nrrd, .mha)"
    )
    correct.add_argument(
        "--volume", type=Path, metavar="FILE", help="also compound the corrected frames into this volume file"
    )
    _add_correction_options(correct)
    _add_compensation_options(correct)
    _add_compounding_options(correct, from_config=False)
    correct.set_defaults(run=_correct)

    experiment = command_parser("experiment", help="reproduce the paper's experiments on the simulator")
    experiment.add_argument(
        "name",
        choices=["paper-2d", "paper-3d", "clinical-3d"],
        help="paper-2d: TABLES I-II and Figs. 4, 6-8; paper-3d: Figs. 9-10; clinical-3d: an artery beside a vein, "
        "a curved path, a bone, deepening vessels, per vessel",
    )
    experiment.add_argument("--output", type=Path, default=Path("usdeform-experiments"), help="output folder")
    experiment.add_argument("--quick", action="store_true", help="small frames and a coarse mesh (a smoke run)")
    experiment.add_argument(
        "--nuisance",
        action="append",
        metavar="NAME",
        help="paper-3d: a sweep as a robot makes it, with the nuisance NAME (force, delay, jitter, path, vessel, "
        "stiffness; repeat to combine), all (every one together) or table (none, each alone, all together)",
    )
    experiment.set_defaults(run=_experiment)
    return parser


def _add_fit_options(fit: argparse.ArgumentParser) -> None:
    """The fit's settings, with the pipeline's defaults (imports the fitting code for the methods' descriptions:
    only when ``fit`` is built)."""
    if isinstance(fit, _Unused):
        return
    from .fitting import FIT_METHODS
    from .pipeline import CHOICES, PipelineSettings

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


def _add_correction_options(correct: argparse.ArgumentParser) -> None:
    """The correction's settings, with the pipeline's defaults (only when ``correct`` is built)."""
    if isinstance(correct, _Unused):
        return
    from .pipeline import CHOICES, PipelineSettings

    defaults = PipelineSettings()
    correct.add_argument(
        "--stiffness-source",
        choices=CHOICES["stiffness_source"],
        default=defaults.stiffness_source,
        help="each frame's stiffness: interpolated between the palpated positions (the paper, eqs. 12-14), "
        "the interpolated profile rescaled to the frame's own ContactForce and ProbeDisplacement (sweep), or "
        "sweep where every frame records both, else interpolated (auto); the choice is printed and written to "
        f"the corrected file's StiffnessSource field (default: {defaults.stiffness_source})",
    )
    correct.add_argument(
        "--clamp-force",
        action="store_true",
        help="clamp ContactForce values outside the model's fitted range into it, with a warning "
        "(default: refuse them)",
    )


class _Terminated(BaseException):
    """SIGTERM, raised in the main thread so that temporary files are removed on the way out."""


def _terminate(signum: int, frame: FrameType | None) -> None:
    raise _Terminated


@contextmanager
def _terminate_cleanly() -> Iterator[None]:
    """SIGTERM raises :class:`_Terminated` (from the main thread; kernels notice it every 64 frames)."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    previous = signal.signal(signal.SIGTERM, _terminate)
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, previous)


def _show_warning(message: Warning | str, category: type[Warning], *args: Any, **kwargs: Any) -> None:
    print(f"usdeform: warning: {message}", file=sys.stderr)


def main(argv: list[str] | None = None) -> int:
    """Run the command line on ``argv`` (None: ``sys.argv``); returns the exit status: 0, 2 on errors,
    130 on Ctrl-C and 143 on SIGTERM (both leave no partial output).

    The handlers are in place before anything else: building the parser imports the chosen command's
    modules, which takes a second or two, and Ctrl-C then must not print a traceback."""
    try:
        with _terminate_cleanly(), warnings.catch_warnings():
            args = build_parser(_chosen_command(argv)).parse_args(argv)
            args.command_line = "usdeform " + shlex.join(sys.argv[1:] if argv is None else argv)
            warnings.simplefilter("always", ForceClampWarning)
            warnings.showwarning = _show_warning
            args.run(args)
    except (UsdeformError, OSError) as error:
        print(f"usdeform: error: {error}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("usdeform: interrupted", file=sys.stderr)
        return 130
    except _Terminated:
        print("usdeform: terminated", file=sys.stderr)
        return 128 + signal.SIGTERM
    return 0


if __name__ == "__main__":
    sys.exit(main())
