"""PLUS Server's volume-reconstruction commands, as Slicer's Plus Remote sends them, and PLUS's replies.

A command comes as an OpenIGTLink v3 COMMAND message (Plus Remote) whose content is
``<Command Name="..." .../>``, or as a STRING named ``CMD_<id>`` holding the same XML (OpenIGTLink v1/v2
clients). The reply follows PLUS's ``vtkPlusOpenIGTLinkServer``: an RTS_COMMAND of the same id and name
holding ``<CommandReply Name="..." Status="SUCCESS|FAIL" [Error="..."] Message="..."></CommandReply>``, with
the metadata ``Status``, ``Message`` (and ``Error``); or a STRING ``ACK_<id>`` holding
``<CommandReply Status="..." Message="..." />``. The names, attributes and messages are those of PLUS's
``vtkPlusReconstructVolumeCommand`` (the live reconstruction) and ``vtkPlusStartStopRecordingCommand``
(a recording: :mod:`usdeform.live.capture`); :class:`usdeform.live.LiveServer` carries them out.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Protocol
from xml.etree import ElementTree
from xml.sax.saxutils import quoteattr

import numpy as np

from ..errors import InputError, UsdeformError
from ..io import write_volume
from ..validation import MAX_AXIS_SIZE
from ..volume import BYTES_PER_VOXEL, DEFAULT_MAX_BYTES, ReconstructionSettings, Volume
from .capture import Capture, default_recording_name, output_file
from .transport import CommandMessage, pyigtl_module

__all__ = [
    "COMMAND_NAMES",
    "RECORDING_COMMAND_NAMES",
    "CommandMessage",
    "PlusCommand",
    "answer",
    "parse_command",
    "reply_message",
    "volume_reply",
]

log = logging.getLogger("usdeform.live")

#: PLUS's volume-reconstruction commands that the live service answers.
COMMAND_NAMES = (
    "StartVolumeReconstruction",
    "SuspendVolumeReconstruction",
    "ResumeVolumeReconstruction",
    "StopVolumeReconstruction",
    "GetVolumeReconstructionSnapshot",
)
#: PLUS's recording commands (vtkPlusStartStopRecordingCommand) that the live service answers.
RECORDING_COMMAND_NAMES = ("StartRecording", "SuspendRecording", "ResumeRecording", "StopRecording")


@dataclass
class PlusCommand:
    """A command read: its name and attributes, and how to reply (``v3``: RTS_COMMAND; else STRING ACK_id)."""

    name: str
    command_id: int
    device_name: str
    v3: bool
    attributes: dict[str, str] = field(default_factory=dict)


def parse_command(message: Any) -> PlusCommand | None:
    """The command in ``message`` (a COMMAND, or a STRING ``CMD_<id>``); None if it is none. A command whose
    XML does not parse comes with the name it was sent under and no attributes (answered FAIL)."""
    if message.message_type == "COMMAND":
        text, command_id, name, v3 = message.content, message.command_id, message.command_name, True
    elif message.message_type == "STRING" and message.device_name.upper().startswith("CMD_"):
        uid = message.device_name[4:]
        text, command_id, name, v3 = message.string, int(uid) if uid.isdigit() else 0, "", False
    else:
        return None
    try:
        element = ElementTree.fromstring(text)
        attributes = dict(element.attrib)
    except ElementTree.ParseError:
        attributes = {}
    return PlusCommand(attributes.pop("Name", name), command_id, message.device_name, v3, attributes)


def reply_message(command: PlusCommand, succeeded: bool, message: str, error: str = "") -> Any:
    """PLUS Server's reply to ``command``."""
    status = "SUCCESS" if succeeded else "FAIL"
    if not command.v3:
        text = f"<CommandReply Status={quoteattr(status)} Message={quoteattr(message)} />"
        return pyigtl_module().StringMessage(text, device_name=f"ACK_{command.command_id}")
    failed = f" Error={quoteattr(error)}" if not succeeded else ""
    content = (
        f"<CommandReply Name={quoteattr(command.name)} Status={quoteattr(status)}{failed} "
        f"Message={quoteattr(message)}></CommandReply>"
    )
    reply = CommandMessage("RTS_COMMAND", command.command_id, command.name, content, command.device_name)
    reply.metadata = {"Message": message, "Status": status, **({"Error": error} if not succeeded else {})}
    return reply


class _FrameCount(Protocol):
    frames_corrected: int


class Reconstruction(Protocol):
    """What a command acts on: the live service's reconstruction state (:class:`usdeform.live.LiveServer`)."""

    suspended: bool
    volume_name: str
    volume_file: Path | None
    volume_options: dict[str, Any]
    capture: Capture | None
    output_dir: Path

    @property
    def result(self) -> _FrameCount: ...

    @property
    def frames_stored(self) -> int: ...

    def stop(self, command: tuple[Any, PlusCommand] | None = None) -> None: ...

    def snapshot(self) -> tuple[Volume, int] | None: ...

    def send_volume(self, peer: Any, snapshot: tuple[Volume, int] | None = None) -> None: ...

    def in_background(self, peer: Any, job: Callable[[], list[Any]]) -> None: ...

    def write_capture(self, capture: Capture) -> int: ...


def answer(server: Reconstruction, peer: Any, command: PlusCommand) -> Any | None:
    """Carry out ``command`` on ``server`` (the connection ``peer`` sent it) and return PLUS Server's reply
    (None when it goes out later: StopVolumeReconstruction's after the final volume, StopRecording's and a
    snapshot's once their file is written)."""
    if command.name in RECORDING_COMMAND_NAMES:
        return _answer_recording(server, peer, command)
    name, attributes = command.name, command.attributes
    device = attributes.get("VolumeReconstructorDeviceId") or "VolumeReconstructor"
    base = f"{name}({device})"
    requested = attributes.get("OutputVolDeviceName", "")
    if name not in COMMAND_NAMES:
        return _failed(command, f"{base}Unknown command name: {name}.")
    if attributes.get("OutputVolFilename"):
        try:
            server.volume_file = output_file(server.output_dir, attributes["OutputVolFilename"], "OutputVolFilename")
        except InputError as error:
            return _failed(command, f"{base} {error}.")
    if name == "StartVolumeReconstruction":
        if server.result.frames_corrected > 0 and not server.suspended:
            return _failed(
                command,
                base + " Reconstruction starting from live frames failed: live volume reconstruction is in progress.",
            )
        try:
            server.volume_options.update(
                _output_grid(attributes, server.volume_options, server.result.frames_corrected)
            )
        except InputError as error:
            return _failed(command, f"{base} {error}.")
        server.volume_name, server.suspended = requested or server.volume_name, False
        return reply_message(command, True, base + " Volume reconstruction from live frames started.")
    if name in ("SuspendVolumeReconstruction", "ResumeVolumeReconstruction"):
        suspend = name.startswith("Suspend")
        if server.suspended == suspend:
            state = "not in progress" if suspend else "already in progress"
            verb = "suspend" if suspend else "resume"
            return _failed(
                command, f"{base} Reconstruction {verb} from live frames failed: live volume reconstruction is {state}."
            )
        server.suspended = suspend
        done = f"suspended, device: {device}" if suspend else "resumed."
        return reply_message(
            command, True, ("" if suspend else base + " ") + f"Volume reconstruction from live frames {done}"
        )
    if not server.result.frames_corrected:
        return _failed(command, base + " Reconstruction from live frames failed: no frame was corrected.")
    server.volume_name = requested or server.volume_name
    if name == "StopVolumeReconstruction":
        server.stop(command=(peer, command))  # the reply goes out after the final volume (volume_reply)
        return None
    snapshot, path = server.snapshot(), server.volume_file
    if snapshot is None:
        return _failed(command, base + " Reconstruction snapshot request failed, device: no frame is in the volume.")
    server.send_volume(peer, snapshot)
    if path is None:
        return volume_reply(command, snapshot[0], None, server.volume_name)
    server.in_background(peer, lambda: [volume_reply(command, snapshot[0], path, server.volume_name)])
    return None


def volume_reply(command: PlusCommand, volume: Volume, path: Path | None, volume_name: str) -> Any:
    """PLUS's reply to StopVolumeReconstruction or GetVolumeReconstructionSnapshot once ``volume`` is sent as
    ``volume_name`` and, with ``path``, written there (a failure to write is logged and answered FAIL)."""
    device = command.attributes.get("VolumeReconstructorDeviceId") or "VolumeReconstructor"
    parts, succeeded = [], True
    if path is not None:
        try:
            write_volume(path, volume)
            log.info("wrote %s", path)
            parts.append(f"saved reconstructed volume to file: {path}")
        except (OSError, UsdeformError) as error:
            log.warning("could not write %s: %s", path, error)
            parts.append(f"saving reconstructed volume to {path} failed")
            succeeded = False
    parts.append(f"image sent as: {volume_name}")
    detail = " Reconstruction from live frames completed: " if command.name == "StopVolumeReconstruction" else " "
    message = "Command succeeded." if succeeded else "Command failed. See error message."
    return reply_message(command, succeeded, message, f"{command.name}({device}){detail}{', '.join(parts)}")


def _failed(command: PlusCommand, error: str) -> Any:
    return reply_message(command, False, "Command failed. See error message.", error)


def _output_grid(attributes: dict[str, str], options: dict[str, Any], frames_corrected: int) -> dict[str, Any]:
    """The volume options that StartVolumeReconstruction's OutputSpacing, OutputOrigin and OutputExtent set
    (none without them); InputError naming the attribute at fault."""
    texts = {key: attributes.get(key, "").split() for key in ("OutputSpacing", "OutputOrigin", "OutputExtent")}
    given = " and ".join(key for key, text in texts.items() if text)
    if not given:
        return {}
    if frames_corrected:
        raise InputError(f"{given}: set before the first frame only")
    spacing = [_number(text, "OutputSpacing", 0.01, 100.0) for text in texts["OutputSpacing"]]
    if spacing and len(spacing) != 3:
        raise InputError(f"OutputSpacing {' '.join(texts['OutputSpacing'])}: expected 3 spacings, mm")
    if bool(texts["OutputOrigin"]) != bool(texts["OutputExtent"]):
        raise InputError("OutputOrigin and OutputExtent: give both (a fixed grid) or neither (a grid that grows)")
    if not texts["OutputOrigin"]:
        if len(set(spacing)) != 1:
            raise InputError(f"OutputSpacing {' '.join(texts['OutputSpacing'])}: one spacing for all three axes")
        return {"spacing_mm": spacing[0]}
    origin = [_number(text, "OutputOrigin", -1e6, 1e6) for text in texts["OutputOrigin"]]
    extent = [
        int(_number(text, "OutputExtent", -MAX_AXIS_SIZE, MAX_AXIS_SIZE, integer=True))
        for text in texts["OutputExtent"]
    ]
    if len(origin) != 3 or len(extent) != 6 or any(extent[2 * i + 1] < extent[2 * i] for i in range(3)):
        raise InputError(
            f"OutputOrigin {' '.join(texts['OutputOrigin'])} OutputExtent {' '.join(texts['OutputExtent'])}: "
            "expected 'x y z' (mm) and 'i0 i1 j0 j1 k0 k1' with i0 <= i1, j0 <= j1, k0 <= k1"
        )
    spacing = spacing or [options["spacing_mm"]] * 3
    settings = ReconstructionSettings(
        np.array(spacing, dtype=float),
        options["interpolation"],
        options["compounding"],
        False,
        output_origin_mm=np.array(origin, dtype=float),
        output_extent=(extent[0], extent[1], extent[2], extent[3], extent[4], extent[5]),
    )
    grid = settings.voxel_grid()
    max_bytes = options.get("max_bytes", DEFAULT_MAX_BYTES)
    if int(np.prod(grid.shape)) * BYTES_PER_VOXEL > max_bytes:
        raise InputError(
            f"OutputExtent {' '.join(texts['OutputExtent'])}: {grid.shape} voxels exceed {max_bytes} bytes"
        )
    return {"grid": grid}


def _number(text: str, attribute: str, low: float, high: float, *, integer: bool = False) -> float:
    """A number of ``attribute``, from ``low`` to ``high``; InputError naming it otherwise."""
    try:
        value = int(text) if integer else float(text)
    except ValueError:
        value = math.nan
    if not low <= value <= high:
        raise InputError(f"{attribute}: {text!r} is not a {'whole ' if integer else ''}number from {low:g} to {high:g}")
    return value


def _answer_recording(server: Reconstruction, peer: Any, command: PlusCommand) -> Any | None:
    """PLUS's vtkPlusStartStopRecordingCommand: start, suspend, resume or stop a recording of the frames
    taken in (:class:`~usdeform.live.capture.Capture`); StopRecording's reply goes out once the file is written."""
    name, capture = command.name, server.capture
    device = command.attributes.get("CaptureDeviceId") or "CaptureDevice"
    base = f"VirtualCapture ({device}) {name} "
    filename = command.attributes.get("OutputFilename", "")
    capturing = capture is not None and capture.capturing
    if name == "StartRecording":
        if capturing:
            return _failed(command, base + "Recording to file is already in progress.")
        try:
            path = output_file(server.output_dir, filename or default_recording_name(), "OutputFilename")
        except InputError as error:
            log.warning("StartRecording: %s", error)
            return _failed(command, base + f"Failed to open file {filename or '(undefined)'}.")
        server.capture = Capture(path, server.frames_stored)
    elif name in ("SuspendRecording", "ResumeRecording"):
        suspend = name == "SuspendRecording"
        if capture is None or capturing == (not suspend):
            state = "is not in progress" if suspend else ("is already in progress" if capturing else "was not started")
            return _failed(
                command, base + f"{'Suspend' if suspend else 'Resume'} recording failed: recording to file {state}."
            )
        (capture.suspend if suspend else capture.resume)(server.frames_stored)
    else:
        if capture is None or (not capturing and not capture.frames(server.frames_stored)):
            return _failed(command, base + "Recording to file is already stopped.")
        try:
            capture.path = output_file(server.output_dir, filename, "OutputFilename") if filename else capture.path
        except InputError as error:
            log.warning("StopRecording: %s", error)
        server.capture = None
        server.in_background(peer, lambda: [_recorded(server, command, capture, base)])
        return None
    return reply_message(command, True, base + "successful.")


def _recorded(server: Reconstruction, command: PlusCommand, capture: Capture, base: str) -> Any:
    """Write ``capture`` (in the background) and return StopRecording's reply."""
    try:
        frames = server.write_capture(capture)
    except (OSError, UsdeformError) as error:
        log.warning("StopRecording: could not write %s: %s", capture.path, error)
        return _failed(command, base + f"Failed to finalize file: {capture.path}")
    return reply_message(command, True, base + f"Recording {frames} frames successful to file {capture.path}")
