"""``usdeform experiment``: reproduce the paper's experiments (and the clinical-shaped one) on the simulator."""

from __future__ import annotations

import argparse
import time
from pathlib import Path

from ..errors import InputError

__all__ = ["add_experiment_command"]


def _experiment(args: argparse.Namespace) -> None:
    start = time.perf_counter()
    results = "results.md"
    if args.name == "paper-3d":
        from . import paper_3d

        results = paper_3d.run_command(args.output, quick=args.quick, nuisances=args.nuisance)
    elif args.nuisance is not None:
        raise InputError("--nuisance: only for paper-3d")
    elif args.name == "clinical-3d":
        from . import clinical_3d

        results = clinical_3d.run_command(args.output, quick=args.quick)
    else:
        from . import paper_2d

        paper_2d.run_paper_2d(args.output, paper_2d.QUICK if args.quick else paper_2d.Paper2dConfig())
    print(f"wrote {args.output / results} and figures in {time.perf_counter() - start:.0f} s")


def add_experiment_command(commands: argparse._SubParsersAction) -> None:
    """Register ``usdeform experiment NAME --output DIR ...``."""
    experiment = commands.add_parser("experiment", help="reproduce the paper's experiments on the simulator")
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
