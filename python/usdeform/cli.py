"""The ``usdeform`` command line.

    usdeform demo [--output DIR]                 correct and compound a synthetic sweep, write volumes
    usdeform reconstruct SEQUENCE --output FILE  compound a PLUS sequence file into a volume
    usdeform experiment paper-2d --output DIR    reproduce the paper's 2D experiments on the simulator
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

from .compounding import COMPOUNDINGS, INTERPOLATIONS, Compounder, grid_for_frames
from .errors import UsdeformError

__all__ = ["main"]


def _demo(args: argparse.Namespace) -> None:
    from .demo import run_demo

    result = run_demo(args.output, n_frames=args.frames, size=args.size, seed=args.seed)
    print(f"wrote {result.corrected_path}, {result.deformed_path}, {result.coverage_path} "
          f"in {result.seconds:.1f} s")
    print(f"vessel area in the middle frame: zero force {result.area_zero_force_mm2:.1f} mm^2, "
          f"deformed {result.area_deformed_mm2:.1f} mm^2, corrected {result.area_corrected_mm2:.1f} mm^2")


def _reconstruct(args: argparse.Namespace) -> None:
    from .io import read_plus_config, read_sequence, write_volume

    config = read_plus_config(args.config) if args.config else None
    settings = config.reconstruction if config else None
    recording = read_sequence(args.sequence, config=config)
    valid = np.flatnonzero(recording.pose_valid)
    frames, image_to_base = recording.frames[valid], recording.image_to_base[valid]
    spacing = args.spacing or (float(settings.output_spacing_mm.min()) if settings else 0.5)
    if settings is not None and settings.output_extent is not None and args.spacing is None:
        grid = settings.voxel_grid()
    else:
        grid = grid_for_frames(image_to_base, frames.shape[1:], spacing)
    interpolation = args.interpolation or (settings.interpolation if settings else "nearest")
    compounding = args.compounding or (settings.compounding if settings else "mean")
    start = time.perf_counter()
    compounder = Compounder(grid, interpolation, compounding, max_bytes=int(args.max_gib * 1024**3))
    compounder.add_frames(frames, image_to_base)
    volume = compounder.volume()
    write_volume(args.output, volume, weight_path=args.coverage)
    print(f"compounded {len(valid)} of {len(recording)} frames into {grid.shape} voxels "
          f"({interpolation}, {compounding}) in {time.perf_counter() - start:.2f} s; wrote {args.output}")


def _experiment(args: argparse.Namespace) -> None:
    from .experiments.paper_2d import QUICK, Paper2dConfig, run_paper_2d

    start = time.perf_counter()
    run_paper_2d(args.output, QUICK if args.quick else Paper2dConfig())
    print(f"wrote {args.output / 'results.md'} and figures in {time.perf_counter() - start:.0f} s")


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="usdeform", description="Deformation-aware robotic 3D ultrasound.")
    commands = parser.add_subparsers(dest="command", required=True)

    demo = commands.add_parser("demo", help="correct and compound a synthetic sweep, write NRRD volumes")
    demo.add_argument("--output", type=Path, default=Path("usdeform-demo"), help="output folder")
    demo.add_argument("--frames", type=int, default=200)
    demo.add_argument("--size", type=int, default=128, help="frame rows = columns, pixels")
    demo.add_argument("--seed", type=int, default=0)
    demo.set_defaults(run=_demo)

    reconstruct = commands.add_parser("reconstruct", help="compound a PLUS sequence file into a volume")
    reconstruct.add_argument("sequence", type=Path, help="PLUS sequence file (.mha, .seq.nrrd)")
    reconstruct.add_argument("--output", type=Path, required=True, help="volume file (.nrrd, .mha)")
    reconstruct.add_argument("--config", type=Path, help="PLUS XML configuration (calibration, settings)")
    reconstruct.add_argument("--coverage", type=Path, help="also write the coverage (weight) volume here")
    reconstruct.add_argument("--spacing", type=float, help="voxel size, mm (default: the configuration's, or 0.5)")
    reconstruct.add_argument("--interpolation", choices=INTERPOLATIONS)
    reconstruct.add_argument("--compounding", choices=COMPOUNDINGS)
    reconstruct.add_argument("--max-gib", type=float, default=4.0, help="memory limit of the volume, GiB")
    reconstruct.set_defaults(run=_reconstruct)

    experiment = commands.add_parser("experiment", help="reproduce the paper's experiments on the simulator")
    experiment.add_argument("name", choices=["paper-2d"], help="paper-2d: TABLES I-II and Figs. 4, 6-8")
    experiment.add_argument("--output", type=Path, default=Path("usdeform-experiments"), help="output folder")
    experiment.add_argument("--quick", action="store_true", help="small frames and a coarse mesh (a smoke run)")
    experiment.set_defaults(run=_experiment)
    return parser


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        args.run(args)
    except (UsdeformError, OSError) as error:
        print(f"usdeform: error: {error}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
