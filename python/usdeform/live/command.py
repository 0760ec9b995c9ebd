"""``usdeform live`` and ``usdeform replay``: parsing and printing only (the work is in
:mod:`usdeform.live`)."""

from __future__ import annotations

import argparse
import logging
import sys
from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import numpy as np

from ..errors import InputError
from ..reconstruction import STIFFNESS_SOURCE_CHOICES

__all__ = ["add_live_command", "add_replay_command"]


def _seconds(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        value = float("nan")
    if not (np.isfinite(value) and value >= 0):
        raise argparse.ArgumentTypeError(f"expected a non-negative number of seconds, got {text!r}")
    return value


def _rate(text: str) -> float:
    value = _seconds(text)
    if value <= 0:
        raise argparse.ArgumentTypeError(f"expected a positive rate, got {text!r}")
    return value


def _scalar(text: str) -> Any:
    from .pairing import ScalarSource

    if text.lower() == "none":
        return None
    try:
        return ScalarSource.parse(text)
    except InputError as error:
        raise argparse.ArgumentTypeError(str(error)) from None


def add_live_command(commands: Any) -> None:
    """Add ``usdeform live`` to the command line's subparsers ``commands``."""
    from ..pipeline import add_volume_options

    parser = commands.add_parser(
        "live",
        help="correct and compound a scan live from OpenIGTLink (PLUS Server, a robot node), send it to 3D Slicer",
        description="Read B-mode images, probe poses, contact force and probe displacement over OpenIGTLink, "
        "pair them by timestamp, correct each frame with MODEL, compound it into a growing volume and send the "
        "volume (CorrectedVolume) and the latest corrected frame (CorrectedImage) to every connection on --listen. "
        "Ctrl-C (or --idle-stop, --max-seconds) ends the scan: the final volume is sent and the files written.",
    )
    parser.add_argument("--model", type=Path, required=True, help="model file of 'usdeform fit --anchor image'")
    parser.add_argument(
        "--listen",
        default="127.0.0.1:18945",
        metavar="HOST:PORT",
        help="accept connections here: scans pushed in, viewers such as 3D Slicer (default 127.0.0.1:18945)",
    )
    parser.add_argument("--connect", metavar="HOST:PORT", help="also read from this PLUS Server (e.g. 127.0.0.1:18944)")
    parser.add_argument("--config", type=Path, help="PLUS XML configuration holding the ImageToProbe calibration")
    parser.add_argument("--record", type=Path, metavar="FILE", help="write the paired frames to this sequence file")
    parser.add_argument("--volume", type=Path, metavar="FILE", help="write the final volume to this file")
    parser.add_argument("--image-name", default="Image_Reference", help="IMAGE device name (default Image_Reference)")
    parser.add_argument(
        "--pose",
        default="ProbeToReference",
        metavar="NAME[,REFERENCE]",
        help="probe pose TRANSFORM: ProbeToReference, or ProbeToTracker,ReferenceToTracker",
    )
    parser.add_argument("--calibration-name", default="ImageToProbe", help="calibration TRANSFORM (without --config)")
    parser.add_argument(
        "--force",
        type=_scalar,
        default="STRING:ContactForce",
        metavar="SOURCE",
        help="contact force (N): STRING:NAME, META:KEY (IMAGE metadata) or TRANSFORM:NAME:x|y|z "
        "(default STRING:ContactForce)",
    )
    parser.add_argument(
        "--displacement",
        type=_scalar,
        default="STRING:ProbeDisplacement",
        metavar="SOURCE",
        help="probe displacement (mm), as --force, or none (default STRING:ProbeDisplacement)",
    )
    parser.add_argument(
        "--image-delay",
        default="0",
        metavar="S|DIAGNOSIS",
        help="the images' delay behind pose and force, s, or the diagnosis.json (or folder) of 'usdeform diagnose' "
        "whose image_latency gives it (default 0)",
    )
    parser.add_argument("--tolerance", type=_seconds, default=0.002, metavar="S", help="largest pairing gap, s")
    parser.add_argument("--wait", type=_seconds, default=0.25, metavar="S", help="longest wait for a match, s")
    parser.add_argument("--volume-rate", type=_rate, default=2.0, metavar="HZ", help="volumes sent per second")
    parser.add_argument("--frame-rate", type=_rate, default=10.0, metavar="HZ", help="corrected frames sent per second")
    parser.add_argument("--stiffness-source", choices=STIFFNESS_SOURCE_CHOICES, default="auto")
    parser.add_argument("--clamp-force", action="store_true", help="clamp forces outside the model's range")
    parser.add_argument("--max-seconds", type=_seconds, metavar="S", help="stop after this long")
    parser.add_argument("--idle-stop", type=_seconds, metavar="S", help="stop after this long without a message")
    add_volume_options(parser, from_config=False)
    parser.set_defaults(run=_live)


def add_replay_command(commands: Any) -> None:
    """Add ``usdeform replay`` to the command line's subparsers ``commands``."""
    parser = commands.add_parser(
        "replay",
        help="play a PLUS sequence file over OpenIGTLink as PLUS Server would",
        description="Send each frame's ProbeToReference and ImageToProbe (TRANSFORM), Image_Reference (IMAGE) and "
        "ContactForce and ProbeDisplacement (STRING) at --rate frames per second.",
    )
    parser.add_argument("recording", type=Path, metavar="RECORDING", help="PLUS sequence file (.seq.nrrd, .mha)")
    where = parser.add_mutually_exclusive_group(required=True)
    where.add_argument("--to", metavar="HOST:PORT", help="connect to this 'usdeform live --listen' address")
    where.add_argument("--serve", metavar="HOST:PORT", help="wait here for one client ('usdeform live --connect')")
    parser.add_argument("--rate", type=_rate, default=30.0, metavar="HZ", help="frames per second (default 30)")
    parser.add_argument("--loops", type=int, default=1, metavar="N", help="play the recording N times")
    parser.set_defaults(run=_replay)


@contextmanager
def _log_to_stderr() -> Iterator[None]:
    """The service's log lines on stderr while the command runs."""
    logger = logging.getLogger("usdeform.live")
    handler = logging.StreamHandler(sys.stderr)
    handler.setFormatter(logging.Formatter("usdeform live: %(message)s"))
    level = logger.level
    logger.addHandler(handler)
    logger.setLevel(logging.INFO)
    try:
        yield
    finally:
        logger.removeHandler(handler)
        logger.setLevel(level)


def _percentile_ms(values: Sequence[float], q: float) -> str:
    return f"{1000 * float(np.percentile(values, q)):.1f}" if values else "-"


def _live(args: argparse.Namespace) -> None:
    from .._files import check_output_paths
    from ..io import load_model, read_plus_config, write_volume
    from ..io.sequence_file import SEQUENCE_SUFFIXES
    from ..io.volume_file import VOLUME_SUFFIXES
    from ..pipeline import volume_keywords
    from .pairing import StreamSettings, image_delay_from_diagnosis
    from .server import LiveServer, OutputSettings

    check_output_paths(
        {
            "--record": (args.record, SEQUENCE_SUFFIXES),
            "--volume": (args.volume, VOLUME_SUFFIXES),
            "--coverage": (args.coverage, VOLUME_SUFFIXES),
        },
        {"--model": args.model, "--config": args.config},
    )
    if args.coverage is not None and args.volume is None:
        raise InputError("--coverage: needs --volume")
    model_file = load_model(args.model)
    if model_file.sampled is None:
        raise InputError(f"{args.model}: sampled_positions: the live service needs the palpations' positions")
    options = volume_keywords(args)
    try:
        float(args.image_delay)
    except ValueError:  # not a number: a diagnosis
        image_delay, note = image_delay_from_diagnosis(args.image_delay)
        print(f"usdeform live: {note}", file=sys.stderr)
    else:
        try:
            image_delay = _seconds(args.image_delay)
        except argparse.ArgumentTypeError as error:
            raise InputError(f"--image-delay: {error}") from None
    streams = StreamSettings(
        image_name=args.image_name,
        pose=tuple(part.strip() for part in args.pose.split(",")),
        calibration_name=args.calibration_name,
        force=_scalar(args.force) if isinstance(args.force, str) else args.force,
        displacement=_scalar(args.displacement) if isinstance(args.displacement, str) else args.displacement,
        image_delay_s=image_delay,
        tolerance_s=args.tolerance,
        wait_s=args.wait,
    )
    if streams.force is None:
        raise InputError("--force: the contact force is needed to correct a frame")
    server = LiveServer(
        model_file.model,
        model_file.sampled,
        listen=args.listen,
        connect=args.connect,
        streams=streams,
        calibration=read_plus_config(args.config).image_to_probe if args.config else None,
        outputs=OutputSettings(volume_rate_hz=args.volume_rate, frame_rate_hz=args.frame_rate),
        record=args.record,
        stiffness_source=args.stiffness_source,
        clamp_force=args.clamp_force,
        spacing_mm=options["spacing_mm"],
        interpolation=options["interpolation"],
        compounding=options["compounding"],
        hole_filling=options["hole_filling"] or (),
        voxel_type=options["voxel_type"],
        max_bytes=options["max_bytes"],
        max_seconds=args.max_seconds,
        idle_stop_s=args.idle_stop,
    )
    with _log_to_stderr():
        result = server.start().run()
    if args.volume is not None and result.volume is not None:
        write_volume(args.volume, result.volume, weight_path=args.coverage, compression_level=args.compression_level)
    skipped = ", ".join(f"{k} {v}" for k, v in sorted(result.skipped.items())) or "none"
    print(
        f"corrected {result.frames_corrected} of {result.images_read} images in {result.seconds:.1f} s "
        f"(skipped: {skipped}; malformed messages {result.malformed}); latency to the volume median "
        f"{_percentile_ms(result.latency_s, 50)} ms, p99 {_percentile_ms(result.latency_s, 99)} ms; "
        f"{result.volumes_sent} volumes sent"
        + (f"; wrote {args.record}" if result.recording else "")
        + (f"; wrote {args.volume}" if args.volume is not None and result.volume is not None else "")
    )


def _replay(args: argparse.Namespace) -> None:
    from .replay import replay

    if args.loops < 1:
        raise InputError(f"--loops: expected at least 1, got {args.loops}")
    with _log_to_stderr():
        address, listen = (args.to, False) if args.to else (args.serve, True)
        result = replay(args.recording, address, rate_hz=args.rate, loops=args.loops, listen=listen)
    rate = result.frames_sent / max(result.seconds, 1e-9)
    print(f"sent {result.frames_sent} frames in {result.seconds:.1f} s ({rate:.1f} frames/s)")
