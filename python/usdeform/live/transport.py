"""OpenIGTLink messages over TCP: pyigtl packs and unpacks them, this module moves them.

pyigtl's own client and server keep only the newest message of each device name (a frame would be
lost whenever two arrive between polls), serve one connection at a time and install signal handlers,
so the live service reads and writes the sockets itself and leaves the message formats to pyigtl.

A message whose body fails its CRC or does not unpack is :class:`MalformedMessage`: it is skipped and
the connection goes on (its length was read, the next header is where it should be). A header that
cannot be a message (unreadable type or name, an absurd body size) is :class:`BrokenStream`: the
framing is lost, and the connection is closed.
"""

from __future__ import annotations

import importlib
import socket
import struct
from typing import Any

import numpy as np

from .. import _core
from ..errors import UsdeformError

__all__ = [
    "HEADER_SIZE",
    "MAX_BODY_BYTES",
    "BrokenStream",
    "CommandMessage",
    "MalformedMessage",
    "UnsupportedMessage",
    "crc64",
    "pack_message",
    "pyigtl_module",
    "receive_message",
]

#: Bytes of an OpenIGTLink header (version, type, device name, timestamp, body size, CRC).
HEADER_SIZE = 58
#: Largest body accepted, bytes (a 1024^3 uint8 volume is 1 GiB; a B-mode frame is far below this).
MAX_BODY_BYTES = 1 << 30


class MalformedMessage(UsdeformError):
    """A message that cannot be read (bad CRC, a body that does not unpack): skipped, the stream goes on."""


class UnsupportedMessage(UsdeformError):
    """A well-formed message of a type pyigtl does not read (e.g. STATUS, CAPABILITY): ignored."""


class BrokenStream(UsdeformError):
    """The byte stream is not OpenIGTLink (or was cut inside a message): the connection is closed."""


def pyigtl_module() -> Any:
    """The pyigtl module (imported by name: it ships no type information)."""
    try:
        return importlib.import_module("pyigtl")
    except ImportError:  # pragma: no cover - the 'live' extra is missing
        raise UsdeformError("the live service needs pyigtl: pip install 'usdeform[live]'") from None


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


def crc64(data: bytes | memoryview, crc: int = 0) -> int:
    """The OpenIGTLink CRC-64 of ``data`` (any bytes-like object, not copied) continued from ``crc``
    (the CRC of the bytes before it; 0 to start): pyigtl's ``CRC64``, computed in the Rust core
    without the interpreter lock, so that the other threads run meanwhile."""
    return _core.crc64(np.frombuffer(data, dtype=np.uint8), crc)


def _read_exact(connection: socket.socket, size: int, *, at_start: bool = False) -> bytes | None:
    """``size`` bytes from ``connection``; None if it closed cleanly before the first byte (``at_start``)."""
    chunks, received = [], 0
    while received < size:
        try:
            chunk = connection.recv(min(size - received, 1 << 20))
        except TimeoutError:
            if at_start and received == 0:
                raise
            continue
        if not chunk:
            if at_start and received == 0:
                return None
            raise BrokenStream(f"connection closed inside a message ({received} of {size} bytes)")
        chunks.append(chunk)
        received += len(chunk)
    return b"".join(chunks)


def receive_message(connection: socket.socket) -> tuple[Any, int] | None:
    """The next message on ``connection`` and its size in bytes, or None when the peer closed the
    connection between messages. ``TimeoutError`` when no message began within the socket's timeout.

    Raises
    ------
    MalformedMessage, UnsupportedMessage
        The message was read whole but is unusable; the next call reads the next one.
    BrokenStream
        The stream cannot be followed any further.
    """
    pyigtl = pyigtl_module()
    header = _read_exact(connection, HEADER_SIZE, at_start=True)
    if header is None:
        return None
    try:
        fields = pyigtl.MessageBase.parse_header(header)
    except (UnicodeDecodeError, struct.error) as error:
        raise BrokenStream(f"not an OpenIGTLink header ({error})") from None
    body_size = int(fields["body_size"])
    if body_size > MAX_BODY_BYTES:
        raise BrokenStream(f"{fields['message_type']!r} message announces a body of {body_size} bytes")
    body = _read_exact(connection, body_size) if body_size else b""
    assert body is not None
    (crc,) = struct.unpack(">Q", header[50:58])
    if crc64(body) != crc:
        raise MalformedMessage(f"{fields['message_type']} {fields['device_name']!r}: CRC mismatch")
    if fields["message_type"] in ("COMMAND", "RTS_COMMAND"):
        message = CommandMessage(fields["message_type"])
    else:
        message = pyigtl.MessageBase.create_message(fields["message_type"])
    if message is None:
        raise UnsupportedMessage(f"{fields['message_type']} {fields['device_name']!r}")
    try:
        message.unpack(fields, body)
    except Exception as error:  # pyigtl raises what the bytes make it raise
        raise MalformedMessage(
            f"{fields['message_type']} {fields['device_name']!r}: does not unpack ({type(error).__name__}: {error})"
        ) from None
    return message, HEADER_SIZE + body_size


def pack_message(message: Any) -> list[bytes | memoryview]:
    """The bytes of ``message.pack()``, as buffers to send one after the other. An IMAGE's voxels are
    not copied (a view of its array, C-contiguous) and their CRC is computed without the interpreter
    lock (:func:`crc64`), so that packing a volume of tens of MB does not stall the other threads
    (pyigtl's ``pack`` copies the voxels four times and computes the CRC, each holding the lock
    throughout)."""
    if message.message_type != "IMAGE" or message.image is None:
        return [message.pack()]
    pyigtl = pyigtl_module()
    image = np.ascontiguousarray(message.image)
    if not 1 <= image.ndim <= 4:
        raise ValueError("Image dimension must be between 1 and 4")
    # The (i, j, k) size as pyigtl reads the axes: (k, j, i[, components]), (j, i) or (i,).
    shape = image.shape
    if image.ndim == 1:
        size = (1, 1, shape[0])
    elif image.ndim == 2:
        size = (1, shape[1], shape[0])
    else:
        size = (shape[2], shape[1], shape[0])
    components = shape[3] if image.ndim == 4 else 1
    scalar_type = next(code for code, dtype in pyigtl.ImageMessage.scalar_types.items() if image.dtype == dtype)
    matrix = message.ijk_to_world_matrix
    center = matrix.dot(np.array([(size[0] - 1) / 2.0, (size[1] - 1) / 2.0, (size[2] - 1) / 2.0, 1.0]))
    content = struct.pack(
        ">H B B B B H H H 12f 6H",
        1,  # image header version
        components,
        scalar_type,
        1 if image.dtype.byteorder == ">" else 2,
        1 if message.world_coordinate_system == "ras" else 2,
        *size,
        *matrix[0:3, 0],
        *matrix[0:3, 1],
        *matrix[0:3, 2],
        *center[0:3],
        0,
        0,
        0,
        *size,
    )
    extended, metadata_header, metadata_body = b"", b"", b""
    if message.header_version > 1:
        metadata_header = struct.pack(">H", len(message.metadata))
        for key, value in message.metadata.items():
            encoded_key = key.encode("utf8")
            encoded_value, encoding = pyigtl.MessageBase.encode_text(value)
            metadata_header += struct.pack(">H H I", len(encoded_key), encoding, len(encoded_value))
            metadata_body += encoded_key + encoded_value
        extended = struct.pack(">H H I I", 12, len(metadata_header), len(metadata_body), message.message_id)
    voxels = image.data.cast("B") if image.size else memoryview(b"")
    prefix, suffix = extended + content, metadata_header + metadata_body
    crc = 0
    for part in (prefix, voxels, suffix):
        crc = crc64(part, crc)
    seconds = int(message.timestamp)
    fraction = pyigtl.messages._igtl_nanosec_to_frac(int((message.timestamp - seconds) * 10**9))
    header = struct.pack(
        ">H 12s 20s I I Q Q",
        message.header_version,
        message._message_type.encode("utf8"),
        message.device_name.encode("utf8"),
        seconds,
        fraction,
        len(prefix) + voxels.nbytes + len(suffix),
        crc,
    )
    return [header + prefix, voxels, suffix]
