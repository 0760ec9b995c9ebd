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

import struct
from dataclasses import dataclass, field
from typing import Any
from xml.etree import ElementTree
from xml.sax.saxutils import quoteattr

from .transport import pyigtl_module

__all__ = ["COMMAND_NAMES", "CommandMessage", "PlusCommand", "parse_command", "reply_message"]

#: PLUS's volume-reconstruction commands that the live service answers.
COMMAND_NAMES = (
    "StartVolumeReconstruction",
    "SuspendVolumeReconstruction",
    "ResumeVolumeReconstruction",
    "StopVolumeReconstruction",
    "GetVolumeReconstructionSnapshot",
)

_MessageBase: Any = pyigtl_module().MessageBase


class CommandMessage(_MessageBase):
    """An OpenIGTLink v3 COMMAND (or RTS_COMMAND) message: an id, a name (128 bytes) and text content."""

    def __init__(
        self, kind: str = "COMMAND", command_id: int = 0, name: str = "", content: str = "", device_name: str = ""
    ) -> None:
        _MessageBase.__init__(self, device_name=device_name)
        self._message_type = kind
        self.header_version = 2
        self.command_id, self.command_name, self.content = command_id, name, content
        self._valid_message = True

    def _pack_content(self) -> bytes:
        encoded, encoding = _MessageBase.encode_text(self.content)
        name = self.command_name.encode("ascii")[:128]
        return struct.pack(">I128sHI", self.command_id, name, encoding, len(encoded)) + encoded

    def _unpack_content(self, content: bytes) -> None:
        self.command_id, name, encoding, length = struct.unpack(">I128sHI", content[:138])
        self.command_name = name.rstrip(b"\0").decode("ascii", "replace")
        self.content = _MessageBase.decode_text(content[138 : 138 + length], encoding)


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
