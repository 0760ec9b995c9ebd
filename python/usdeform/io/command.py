"""``usdeform import-bag``: a ROS1/ROS2 bag (images, wrench, pose) into a PLUS sequence file."""

from __future__ import annotations

import argparse
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from ..errors import InputError
from ..options import NUMBERS
from ..recording import image_to_probe_from_geometry

__all__ = ["add_import_bag_command"]


def _run_import_bag(args: argparse.Namespace) -> None:
    from .._files import check_output_paths
    from . import ros_bag
    from .plus_config import read_plus_config
    from .sequence_file import SEQUENCE_SUFFIXES, write_sequence

    check_output_paths(
        {"--output": (args.output, SEQUENCE_SUFFIXES)}, {"BAG": args.bag, "--calibration": args.calibration}
    )
    calibration: np.ndarray | Callable[[int, int], np.ndarray]
    if args.calibration is not None:
        calibration = read_plus_config(args.calibration).image_to_probe
    elif args.depth_mm is not None and args.width_mm is not None:
        depth_mm, width_mm = args.depth_mm, args.width_mm

        def calibration(rows: int, cols: int) -> np.ndarray:
            return image_to_probe_from_geometry(rows, cols, depth_mm=depth_mm, width_mm=width_mm)
    else:
        raise InputError("import-bag: give --calibration CONFIG.xml or both --depth-mm and --width-mm")
    imported = ros_bag.read_bag(
        args.bag,
        image_topic=args.image_topic,
        force_topic=args.force_topic,
        pose_topic=args.pose_topic,
        image_to_probe=calibration,
        pose_child_frame=args.pose_child_frame,
        force_axis=args.force_axis,
        tolerance_s=args.tolerance,
    )
    recording = imported.recording
    write_sequence(args.output, recording)
    dropped = ", ".join(f"{count} without {stream}" for stream, count in imported.dropped.items() if count)
    print(
        f"imported {len(recording)} of {imported.n_images} frames ({recording.shape[0]} x {recording.shape[1]}) "
        f"from {args.bag}" + (f"; dropped {dropped} within {args.tolerance} s" if dropped else "")
    )
    force, displacement = np.asarray(recording.force), np.asarray(recording.probe_displacement)
    print(
        f"force {force.min():.2f}-{force.max():.2f} N, probe displacement "
        f"{displacement.min():.2f}-{displacement.max():.2f} mm -> {args.output}"
    )
    for warning in imported.warnings:
        print(f"warning: {warning}")


def add_import_bag_command(commands: Any) -> None:
    """Register ``usdeform import-bag BAG --output SEQ ...``."""
    from . import ros_bag

    parser = commands.add_parser(
        "import-bag",
        help="convert a ROS1/ROS2 bag (images, wrench, pose) into a PLUS sequence file",
        description=ros_bag.__doc__.split("\n\n", 1)[1] if ros_bag.__doc__ else None,  # its docstring past the title
        formatter_class=argparse.RawDescriptionHelpFormatter,  # keeps the docstring's list of streams
    )
    parser.add_argument("bag", type=Path, help="ROS1 .bag file or ROS2 bag folder")
    parser.add_argument("--output", type=Path, required=True, help="PLUS sequence file to write (.seq.nrrd / .mha)")
    parser.add_argument("--image-topic", required=True, help="sensor_msgs/Image or CompressedImage topic")
    parser.add_argument("--force-topic", required=True, help="geometry_msgs/WrenchStamped topic")
    parser.add_argument("--pose-topic", required=True, help="PoseStamped, TransformStamped or TF topic of the probe")
    parser.add_argument("--pose-child-frame", help="probe frame id on a TF topic")
    parser.add_argument(
        "--force-axis", choices=sorted(ros_bag.AXES), default="z", help="wrench axis read as contact force"
    )
    parser.add_argument(
        "--tolerance",
        type=NUMBERS["tolerance_s"].argument(),
        default=0.05,
        help="largest gap to a force/pose sample, s",
    )
    parser.add_argument("--calibration", type=Path, help="PLUS configuration with the Image->Probe transform")
    parser.add_argument(
        "--depth-mm",
        type=NUMBERS["depth_mm"].argument(),
        help="imaging depth (with --width-mm, instead of --calibration)",
    )
    parser.add_argument("--width-mm", type=NUMBERS["width_mm"].argument(), help="transducer width (with --depth-mm)")
    parser.set_defaults(run=_run_import_bag)
