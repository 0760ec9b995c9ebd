"""Play a PLUS sequence file over OpenIGTLink as PLUS Server sends a tracked scan: for tests, demos
and users without a robot.

Per frame, all stamped with the frame's timestamp (plus the loop's offset): TRANSFORM
``ProbeToReference`` (left out, as PLUS Server's default ``SendValidTransformsOnly`` does, where the
pose is invalid), TRANSFORM ``ImageToProbe``, IMAGE ``Image_Reference`` (its ijk-to-world the
frame's ImageToReference, as PLUS embeds it) and STRING ``ContactForce`` and ``ProbeDisplacement``
(where the recording has them), as PLUS Server sends a frame's custom fields listed as
``<String Name="..."/>``. Messages use OpenIGTLink v3 headers (PLUS 2.8 and later); transforms carry
``TransformStatus`` metadata.
"""

from __future__ import annotations

import logging
import math
import socket
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from ..errors import InputError, UsdeformError
from ..io import read_sequence
from ..recording import Recording
from .connections import socket_address
from .transport import pyigtl_module

__all__ = ["ReplayResult", "replay", "replay_messages"]

log = logging.getLogger("usdeform.live")


@dataclass
class ReplayResult:
    """Frames sent, and when each frame's messages left (``time.perf_counter()``, s)."""

    frames_sent: int
    sent_at: list[float]
    seconds: float


def replay_messages(recording: Recording, frame: int, timestamp: float) -> list[Any]:
    """The messages PLUS Server sends for ``recording``'s frame ``frame``, stamped ``timestamp``."""
    pyigtl = pyigtl_module()

    def v3(message: Any, **metadata: str) -> Any:
        message.header_version = 2
        message.metadata = metadata
        return message

    messages = []
    if recording.pose_valid[frame]:
        pose = recording.probe_to_base[frame]
        messages.append(
            v3(pyigtl.TransformMessage(pose, timestamp=timestamp, device_name="ProbeToReference"), TransformStatus="OK")
        )
    calibration = pyigtl.TransformMessage(recording.image_to_probe, timestamp=timestamp, device_name="ImageToProbe")
    messages.append(v3(calibration, TransformStatus="OK"))
    image_to_reference = recording.probe_to_base[frame] @ recording.image_to_probe
    if not recording.pose_valid[frame] or not np.all(np.isfinite(image_to_reference)):
        image_to_reference = np.eye(4)
    image = pyigtl.ImageMessage(
        recording.frames[frame][np.newaxis],
        ijk_to_world_matrix=image_to_reference,
        timestamp=timestamp,
        device_name="Image_Reference",
    )
    messages.append(v3(image))
    for name, values in (("ContactForce", recording.force), ("ProbeDisplacement", recording.probe_displacement)):
        if values is not None:
            messages.append(v3(pyigtl.StringMessage(repr(float(values[frame])), timestamp=timestamp, device_name=name)))
    return messages


def _open(address: tuple[str, int], listen: bool, timeout_s: float) -> socket.socket:
    if not listen:
        try:
            return socket.create_connection(address, timeout=timeout_s)
        except OSError as error:
            raise UsdeformError(f"--to {address[0]}:{address[1]}: cannot connect ({error})") from None
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as listener:
        listener.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        listener.bind(address)
        listener.listen(1)
        listener.settimeout(timeout_s)
        log.info("replay: waiting for a client on %s:%d", *listener.getsockname()[:2])
        try:
            connection, _ = listener.accept()
        except TimeoutError:
            raise UsdeformError(f"--listen {address[0]}:{address[1]}: no client within {timeout_s:g} s") from None
        return connection


def _close_gracefully(connection: socket.socket, timeout_s: float = 2.0) -> None:
    """End the sending side and read until the peer closes (or ``timeout_s``): closing a socket with
    unread bytes resets the connection, and the peer would lose what it has not read yet."""
    connection.shutdown(socket.SHUT_WR)
    connection.settimeout(timeout_s)
    deadline = time.perf_counter() + timeout_s
    try:
        while time.perf_counter() < deadline and connection.recv(1 << 16):
            pass
    except OSError:
        pass


def replay(
    recording: Recording | str | Path,
    to: str | tuple[str, int],
    *,
    rate_hz: float | None = 30.0,
    loops: int = 1,
    listen: bool = False,
    timeout_s: float = 30.0,
    frames: int | None = None,
) -> ReplayResult:
    """Send a recording as PLUS Server would (see the module's notes).

    Parameters
    ----------
    recording : Recording or path
        The scan (a PLUS sequence file).
    to : str or (host, port)
        ``HOST:PORT`` to connect to (a ``usdeform live --listen`` service), or with ``listen`` to
        wait on for one client (a ``usdeform live --connect``).
    rate_hz : float, optional
        Frames per second; None: as fast as the connection takes them.
    loops : int
        Times the recording is played; each loop's timestamps continue after the last one's.
    listen : bool
        Wait for a client at ``to`` instead of connecting.
    timeout_s : float
        Longest wait to connect (or for a client).
    frames : int, optional
        Stop after this many frames.

    Returns
    -------
    ReplayResult
    """
    if not isinstance(recording, Recording):
        recording = read_sequence(recording)
    if rate_hz is not None and not (math.isfinite(rate_hz) and rate_hz > 0):
        raise InputError(f"rate: expected a positive number of frames per second, got {rate_hz}")
    if loops < 1:
        raise InputError(f"loops: expected at least 1, got {loops}")
    times = recording.timestamps
    step = float(np.median(np.diff(times))) if len(times) > 1 else 1.0
    period = float(times[-1] - times[0]) + max(step, 1e-3)  # each loop's timestamps follow the last one's
    total = len(recording) * loops if frames is None else min(frames, len(recording) * loops)
    sent_at: list[float] = []
    connection = _open(socket_address(to), listen, timeout_s)
    start = time.perf_counter()
    try:
        for count in range(total):
            loop, frame = divmod(count, len(recording))
            if rate_hz is not None:
                delay = start + count / rate_hz - time.perf_counter()
                if delay > 0:
                    time.sleep(delay)
            timestamp = float(times[frame] + loop * period)
            data = b"".join(message.pack() for message in replay_messages(recording, frame, timestamp))
            try:
                connection.sendall(data)
            except OSError as error:
                raise UsdeformError(f"replay: the connection dropped after {count} frames ({error})") from None
            sent_at.append(time.perf_counter())
        _close_gracefully(connection)
    finally:
        connection.close()
    return ReplayResult(len(sent_at), sent_at, time.perf_counter() - start)
