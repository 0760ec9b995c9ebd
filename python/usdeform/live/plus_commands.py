"""PLUS Server's volume-reconstruction commands, as Slicer's Plus Remote sends them, and PLUS's replies.

A command comes as an OpenIGTLink v3 COMMAND message (Plus Remote) whose content is
``<Command Name="..." .../>``, or as a STRING named ``CMD_<id>`` holding the same XML (OpenIGTLink v1/v2
clients). The reply follows PLUS's ``vtkPlusOpenIGTLinkServer``: an RTS_COMMAND of the same id and name
holding ``<CommandReply Name="..." Status="SUCCESS|FAIL" [Error="..."] Message="..."></CommandReply>``, with
the metadata ``Status``, ``Message`` (and ``Error``); or a STRING ``ACK_<id>`` holding
``<CommandReply Status="..." Message="..." />``. The names and messages are those of PLUS's
``vtkPlusReconstructVolumeCommand``; :class:`usdeform.live.LiveServer` carries them out.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Protocol
from xml.etree import ElementTree
from xml.sax.saxutils import quoteattr

from .transport import CommandMessage, pyigtl_module

__all__ = ["COMMAND_NAMES", "CommandMessage", "PlusCommand", "answer", "parse_command", "reply_message"]

#: PLUS's volume-reconstruction commands that the live service answers.
COMMAND_NAMES = (
    "StartVolumeReconstruction",
    "SuspendVolumeReconstruction",
    "ResumeVolumeReconstruction",
    "StopVolumeReconstruction",
    "GetVolumeReconstructionSnapshot",
)


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
    volume_options: dict[str, Any]

    @property
    def result(self) -> _FrameCount: ...

    def stop(self, reply: tuple[Any, Any] | None = None) -> None: ...

    def send_volume(self, peer: Any) -> None: ...


def answer(server: Reconstruction, peer: Any, command: PlusCommand) -> Any | None:
    """Carry out ``command`` on ``server`` (the connection ``peer`` sent it) and return PLUS Server's reply
    (None for StopVolumeReconstruction: its reply goes out after the final volume)."""
    name, attributes = command.name, command.attributes
    device = attributes.get("VolumeReconstructorDeviceId") or "VolumeReconstructor"
    base = f"{name}({device})"
    reply: Any = None
    requested = attributes.get("OutputVolDeviceName", "")
    if name == "StartVolumeReconstruction":
        spacing = attributes.get("OutputSpacing", "").split()
        if server.result.frames_corrected > 0 and not server.suspended:
            why = " Reconstruction starting from live frames failed: live volume reconstruction is in progress."
        elif spacing and (server.result.frames_corrected > 0 or len(set(spacing)) != 1 or _spacing(spacing[0]) is None):
            why = f" OutputSpacing {' '.join(spacing)}: one spacing for all three axes, before the first frame."
        else:
            why = ""
            if spacing:
                server.volume_options["spacing_mm"] = _spacing(spacing[0])
            server.volume_name, server.suspended = requested or server.volume_name, False
            reply = reply_message(command, True, base + " Volume reconstruction from live frames started.")
        reply = reply or reply_message(command, False, "Command failed. See error message.", base + why)
    elif name in ("SuspendVolumeReconstruction", "ResumeVolumeReconstruction"):
        suspend = name.startswith("Suspend")
        if server.suspended == suspend:
            state = "not in progress" if suspend else "already in progress"
            verb = "suspend" if suspend else "resume"
            why = f" Reconstruction {verb} from live frames failed: live volume reconstruction is {state}."
            reply = reply_message(command, False, "Command failed. See error message.", base + why)
        else:
            server.suspended = suspend
            done = f"suspended, device: {device}" if suspend else "resumed."
            reply = reply_message(
                command, True, ("" if suspend else base + " ") + f"Volume reconstruction from live frames {done}"
            )
    elif name in ("StopVolumeReconstruction", "GetVolumeReconstructionSnapshot"):
        if not server.result.frames_corrected:
            why = " Reconstruction from live frames failed: no frame was corrected."
            reply = reply_message(command, False, "Command failed. See error message.", base + why)
        else:
            server.volume_name = requested or server.volume_name
            detail = " Reconstruction from live frames completed:" if name.startswith("Stop") else ""
            reply = reply_message(
                command, True, "Command succeeded.", f"{base}{detail} image sent as: {server.volume_name}"
            )
            if name.startswith("Stop"):
                server.stop(reply=(peer, reply))  # the reply goes out after the final volume
                return None
            server.send_volume(peer)
    else:
        why = f"Unknown command name: {name}."
        reply = reply_message(command, False, "Command failed. See error message.", base + why)
    return reply


def _spacing(text: str) -> float | None:
    """A voxel spacing of a command, mm (from 0.01 to 100), or None."""
    try:
        value = float(text)
    except ValueError:
        return None
    return value if 0.01 <= value <= 100.0 else None
