"""``usdeform demo``: parse the options, run the demo, write the report, print the summary."""

from __future__ import annotations

import argparse
import shutil
from pathlib import Path

from .._files import new_output_folders
from ..options import NUMBERS

__all__ = ["add_demo_command"]


def _run(args: argparse.Namespace) -> None:
    from .config import DemoConfig
    from .pipeline import run_demo
    from .report import summary_lines, write_report

    output = Path(args.output)
    config = DemoConfig(
        preset=args.preset,
        force_n=args.force,
        method=args.method,
        seed=args.seed,
        quick=args.quick,
        effects=tuple(args.effect),
    )
    created = new_output_folders(output, "--output")
    try:
        result = run_demo(output, config)
        report = write_report(result, output / "report.html")
    except BaseException:  # errors, Ctrl-C, SIGTERM: a failed run leaves no folder it made
        if created:
            shutil.rmtree(created[-1], ignore_errors=True)
        raise
    print("\n".join(summary_lines(result)))
    print(f"report: {report}")


def add_demo_command(commands: argparse._SubParsersAction) -> None:
    """Add ``usdeform demo`` to the command line's subparsers."""
    from ..fitting import FIT_METHODS
    from .config import PRESETS

    parser = commands.add_parser(
        "demo",
        help="the whole method on the simulator: palpate, fit, sweep, correct, compound; write report.html",
        description="Palpate a simulated phantom at three positions, fit the deformation model, correct a "
        "constant-force sweep and compound deformed, corrected and zero-force volumes; write DIR/report.html "
        "with the scores against the simulator's truth, the volumes (.nrrd), the model file and the recordings.",
    )
    parser.add_argument("--output", type=Path, default=Path("usdeform-demo"), metavar="DIR", help="output folder")
    parser.add_argument("--preset", choices=sorted(PRESETS), default="soft", help="the phantom (default: soft)")
    parser.add_argument(
        "--force",
        type=NUMBERS["force_n"].argument(),
        metavar="N",
        help="sweep force, N (default: soft 8, stiff 20, compliant-vessel 12)",
    )
    parser.add_argument(
        "--method",
        choices=list(FIT_METHODS),
        default="recommended",
        help="; ".join(f"{name}: {method.description}" for name, method in FIT_METHODS.items())
        + " (default: recommended; the other is scored beside it)",
    )
    parser.add_argument(
        "--seed", type=NUMBERS["seed"].argument(), default=0, help="seed of the simulation (default: 0)"
    )
    parser.add_argument("--quick", action="store_true", help="smaller and fewer frames (a smoke run)")
    parser.add_argument(
        "--effect",
        action="append",
        default=[],
        metavar="NAME[:PARAMETER=VALUE,...]",
        help="simulate the palpations and the sweep with a physical effect, repeatable, as usdeform simulate "
        "--effect (e.g. force-sensor:bias_n=2); the palpations are then diagnosed blind (DIR/diagnosis.json) and "
        "the report says what the effect costs the corrected volume and what compensation gives back (adds the "
        "diagnosis: minutes)",
    )
    parser.set_defaults(run=_run)
