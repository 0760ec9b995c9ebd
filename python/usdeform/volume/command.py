"""``usdeform reconstruct``: compound a PLUS sequence file into a volume; the volume options it shares with
``usdeform correct`` and ``usdeform live``."""

from __future__ import annotations

import argparse
import time
from pathlib import Path
from typing import Any

from ..options import NUMBERS

__all__ = ["add_reconstruct_command", "add_volume_options", "volume_keywords"]


def _reconstruct(args: argparse.Namespace) -> None:
    from .._files import check_output_paths
    from ..io import read_plus_config, read_sequence, write_volume
    from ..io.volume_file import VOLUME_SUFFIXES
    from ._recording import compound_recording

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


def add_reconstruct_command(commands: argparse._SubParsersAction) -> None:
    """Register ``usdeform reconstruct SEQUENCE --output FILE ...``."""
    reconstruct = commands.add_parser("reconstruct", help="compound a PLUS sequence file into a volume")
    reconstruct.add_argument("sequence", type=Path, help="PLUS sequence file (.mha, .seq.nrrd)")
    reconstruct.add_argument("--output", type=Path, required=True, help="volume file (.nrrd, .mha)")
    reconstruct.add_argument("--config", type=Path, help="PLUS XML configuration (calibration, settings)")
    add_volume_options(reconstruct, from_config=True)
    reconstruct.set_defaults(run=_reconstruct)


def volume_keywords(args: argparse.Namespace) -> dict[str, Any]:
    """:func:`compounding_keywords` of the volume options :func:`add_volume_options` parsed into ``args``."""
    from ..pipeline import VOLUME_FIELDS, compounding_keywords

    return compounding_keywords(**{name: getattr(args, name) for name in VOLUME_FIELDS})


def add_volume_options(parser: argparse.ArgumentParser, from_config: bool) -> None:
    """The volume options of ``usdeform reconstruct``, ``correct`` and ``live``, with the pipeline's defaults;
    ``from_config``: the options a PLUS configuration sets default to None, its own value when one is given
    (:func:`compounding_keywords`)."""
    from ..pipeline import CHOICES, PipelineSettings

    defaults = PipelineSettings()

    def add(flag: str, name: str, help: str, *, configured: bool = False, **kwargs: Any) -> None:
        value = getattr(defaults, name)
        if from_config and configured:
            parser.add_argument(flag, dest=name, help=f"{help} (default: the configuration's, or {value})", **kwargs)
        else:
            parser.add_argument(flag, dest=name, default=value, help=f"{help} (default: {value})", **kwargs)

    parser.add_argument("--coverage", type=Path, metavar="FILE", help="also write the coverage (weight) volume here")
    add(
        "--spacing",
        "spacing_mm",
        "voxel size, mm",
        configured=True,
        type=NUMBERS["spacing_mm"].argument(),
        metavar="MM",
    )
    add("--interpolation", "interpolation", "splat of each pixel", configured=True, choices=CHOICES["interpolation"])
    add("--compounding", "compounding", "voxel value", configured=True, choices=CHOICES["compounding"])
    add("--max-gib", "max_gib", "memory limit of the volume, GiB", type=NUMBERS["max_gib"].argument())
    add(
        "--fill-holes",
        "fill_holes",
        "fill the voxels no pixel reached with one step of this PLUS HoleFillingElement type",
        configured=True,
        choices=CHOICES["fill_holes"],
    )
    add("--voxel-type", "voxel_type", "voxel type of the volume (PLUS: uint8)", choices=CHOICES["voxel_type"])
    add(
        "--compression-level",
        "compression_level",
        "compression level of the volume files: 1 (fastest, ISA-L's deflate) to 9 (smallest, zlib)",
        type=NUMBERS["compression_level"].argument(),
        metavar="N",
    )
