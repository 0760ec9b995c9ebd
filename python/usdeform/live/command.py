"""``usdeform live`` and ``usdeform replay``: parsing and printing only (the work is in
:mod:`usdeform.live`)."""

from __future__ import annotations

import argparse
import logging
import signal
import sys
import threading
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import numpy as np

from ..correction import STIFFNESS_SOURCE_CHOICES
from ..errors import InputError, UsdeformError
from ..options import Number
from .pairing import MAX_IMAGE_DELAY_S

__all__ = ["add_live_command", "add_replay_command"]


def _bounded(unit: str, number: Number) -> Callable[[str], float]:
    """The ``argparse`` type of a number of ``unit`` within ``number``'s bounds; its message names the unit."""

    def parse(text: str) -> float:
        try:
            return number.parse_text(text)
        except InputError:
            expected = f"{'more than' if number.above else 'from'} {number.minimum:g} to {number.maximum:g}"
            raise argparse.ArgumentTypeError(f"expected {unit} {expected}, got {text!r}") from None

    parse.__name__ = number.name
    return parse


#: A rate: at least one frame in 1000 s (a longer wait is no stream), at most 1000 a second.
_rate = _bounded("a rate in Hz", Number("rate", 1e-3, 1e3))
_seconds = _bounded("a number of seconds", Number("seconds", 0.0, 1e7))
_short_seconds = _bounded("a number of seconds", Number("seconds", 0.0, 60.0))
_delay = _bounded("an image delay in seconds", Number("image_delay", 0.0, MAX_IMAGE_DELAY_S))
_loops = _bounded("a number of loops", Number("loops", 1, 1_000_000, integer=True))


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
    from ..volume.command import add_volume_options
    from .outputs import PLACEMENTS

    parser = commands.add_parser(
        "live",
        help="correct and compound a scan live from OpenIGTLink (PLUS Server, a robot node), send it to 3D Slicer",
        description="Read B-mode images, probe poses, contact force and probe displacement over OpenIGTLink, "
        "pair them by timestamp, correct each frame with MODEL, compound it into a growing volume and send the "
        "volume (CorrectedVolume), each corrected frame and its pose (CorrectedImage, CorrectedProbe) and "
        "each frame as received (Image_Reference, ProbeToReference) to every connection on --listen that sends no "
        "image. Ctrl-C or SIGTERM (or --idle-stop, --max-seconds) ends the scan: the final volume is sent and the "
        "files written.",
    )
    parser.add_argument("--model", type=Path, required=True, help="model file of 'usdeform fit'")
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
    parser.add_argument(
        "--output-dir",
        type=Path,
        metavar="DIR",
        help="write the files Plus Remote's commands name here (OutputFilename, OutputVolFilename; default: the "
        "working directory)",
    )
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
    parser.add_argument("--tolerance", type=_short_seconds, default=0.002, metavar="S", help="largest pairing gap, s")
    parser.add_argument("--wait", type=_short_seconds, default=0.25, metavar="S", help="longest wait for a match, s")
    parser.add_argument("--volume-rate", type=_rate, default=2.0, metavar="HZ", help="volumes sent per second at most")
    parser.add_argument(
        "--frame-rate", type=_rate, metavar="HZ", help="corrected frames sent per second at most (default: every one)"
    )
    parser.add_argument(
        "--placement",
        choices=PLACEMENTS,
        default="plus",
        help="where Slicer shows the outputs: plus (default) overlays PLUS Server's raw stream; files coincides with "
        "the saved volume files",
    )
    parser.add_argument("--no-relay", action="store_true", help="do not send the frames as received")
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
    where.add_argument(
        "--serve", metavar="HOST:PORT", help="serve clients here ('usdeform live --connect', 3D Slicer), as PLUS Server"
    )
    parser.add_argument("--rate", type=_rate, default=30.0, metavar="HZ", help="frames per second (default 30)")
    parser.add_argument("--loops", type=_loops, default=1, metavar="N", help="play the recording N times")
    parser.add_argument(
        "--recording-clock",
        action="store_true",
        help="stamp the frames with the recording's timestamps (default: the wall clock, as PLUS Server)",
    )
    parser.set_defaults(run=_replay)


@contextmanager
def _log_to_stderr(command: str) -> Iterator[None]:
    """The service's log lines on stderr while ``command`` runs, each beginning ``usdeform COMMAND:``."""
    logger = logging.getLogger("usdeform.live")
    handler = logging.StreamHandler(sys.stderr)
    handler.setFormatter(logging.Formatter(f"usdeform {command}: %(message)s"))
    level = logger.level
    logger.addHandler(handler)
    logger.setLevel(logging.INFO)
    try:
        yield
    finally:
        logger.removeHandler(handler)
        logger.setLevel(level)


@contextmanager
def _stop_on_sigterm(stop: Callable[[], None]) -> Iterator[None]:
    """The first SIGTERM calls ``stop`` (the scan ends as on Ctrl-C: files written); a second one ends
    the command as any other (exit 143, no file written)."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    previous = signal.getsignal(signal.SIGTERM)

    def terminate(signum: int, frame: Any) -> None:
        signal.signal(signal.SIGTERM, previous)
        logging.getLogger("usdeform.live").info("terminated: sending the final volume and writing the files")
        stop()

    signal.signal(signal.SIGTERM, terminate)
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, previous)


def _percentile_ms(values: Sequence[float], q: float) -> str:
    return f"{1000 * float(np.percentile(values, q)):.1f}" if values else "-"


def _live(args: argparse.Namespace) -> None:
    from .._files import check_output_paths
    from ..io import load_model, read_plus_config, write_volume
    from ..io.sequence_file import SEQUENCE_SUFFIXES
    from ..io.volume_file import VOLUME_SUFFIXES
    from ..volume.command import volume_keywords
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
            image_delay = _delay(args.image_delay)
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
        outputs=OutputSettings(
            volume_rate_hz=args.volume_rate,
            frame_rate_hz=args.frame_rate,
            placement=args.placement,
            relay=not args.no_relay,
        ),
        record=args.record,
        output_dir=args.output_dir,
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
    with _log_to_stderr("live"):
        server.start()
        with _stop_on_sigterm(server.stop):
            result = server.run()
    if not result.frames_corrected and (args.record or args.volume):
        written = " and ".join(str(path) for path in (args.record, args.volume) if path)
        raise UsdeformError(f"no frame was corrected ({result.images_read} images read): {written} not written")
    if args.volume is not None and result.volume is not None:
        write_volume(args.volume, result.volume, weight_path=args.coverage, compression_level=args.compression_level)
    skipped = ", ".join(f"{k} {v}" for k, v in sorted(result.skipped.items())) or "none"
    print(
        f"corrected {result.frames_corrected} of {result.images_read} images in {result.seconds:.1f} s "
        f"(skipped: {skipped}; malformed messages {result.malformed}); latency to the volume median "
        f"{_percentile_ms(result.latency_s, 50)} ms, p99 {_percentile_ms(result.latency_s, 99)} ms; "
        f"{result.frames_sent} corrected frames and {result.volumes_sent} volumes sent"
        + (f"; wrote {args.record}" if result.recording else "")
        + (f"; wrote {args.volume}" if args.volume is not None and result.volume is not None else "")
    )


def _replay(args: argparse.Namespace) -> None:
    from .replay import replay

    with _log_to_stderr("replay"):
        address, listen = (args.to, False) if args.to else (args.serve, True)
        result = replay(
            args.recording,
            address,
            rate_hz=args.rate,
            loops=args.loops,
            listen=listen,
            clock="recording" if args.recording_clock else "wall",
        )
    rate = (result.frames_sent - 1) / result.seconds if result.seconds > 0 else 0.0  # intervals between frames
    clients = f" to {result.clients} clients" if listen else ""
    print(f"sent {result.frames_sent} frames{clients} in {result.seconds:.1f} s ({rate:.1f} frames/s)")
