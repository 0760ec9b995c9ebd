"""Play a PLUS sequence file over OpenIGTLink as PLUS Server sends a tracked scan: for tests, demos
and users without a robot.

Per frame, all stamped with the wall clock when the frame is sent (as PLUS Server stamps a frame when it
is acquired), or with the recording's own timestamps: TRANSFORM
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
import threading
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

import numpy as np

from ..errors import InputError, UsdeformError
from ..io import read_sequence
from ..recording import Recording
from .connections import Connections, socket_address
from .transport import pack_message, pyigtl_module

__all__ = ["ReplayResult", "replay", "replay_messages"]

log = logging.getLogger("usdeform.live")


@dataclass
class ReplayResult:
    """Frames sent, when each frame's messages left (``time.perf_counter()``, s), the time from the
    first to the last frame sent, s, and the clients served (``listen``; 1 otherwise)."""

    frames_sent: int
    sent_at: list[float]
    seconds: float
    clients: int = 1


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
        world_coordinate_system="ras",  # as PLUS Server flags its Reference coordinates
        timestamp=timestamp,
        device_name="Image_Reference",
    )
    messages.append(v3(image))
    for name, values in (("ContactForce", recording.force), ("ProbeDisplacement", recording.probe_displacement)):
        if values is not None:
            messages.append(v3(pyigtl.StringMessage(repr(float(values[frame])), timestamp=timestamp, device_name=name)))
    return messages


def _connect(address: tuple[str, int], timeout_s: float) -> socket.socket:
    try:
        return socket.create_connection(address, timeout=timeout_s)
    except OSError as error:
        raise UsdeformError(f"--to {address[0]}:{address[1]}: cannot connect ({error})") from None


def _serve(address: tuple[str, int], rate_hz: float | None, timeout_s: float) -> Connections:
    """Clients served on ``address`` (``--serve``), once the first has connected (``timeout_s`` at most)."""
    clients = Connections(
        address, None, threading.Event(), pack=pack_message, listen_option="--serve", wait_for_viewers=rate_hz is None
    )
    clients.start()
    log.info("waiting for a client on %s:%d", address[0], clients.port)
    deadline = time.perf_counter() + timeout_s
    while not clients.viewers:
        if time.perf_counter() > deadline:
            clients.close()
            raise UsdeformError(f"--serve {address[0]}:{clients.port}: no client within {timeout_s:g} s")
        time.sleep(0.01)
    return clients


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
    clock: Literal["wall", "recording"] = "wall",
) -> ReplayResult:
    """Send a recording as PLUS Server would (see the module's notes).

    Parameters
    ----------
    recording : Recording or path
        The scan (a PLUS sequence file).
    to : str or (host, port)
        ``HOST:PORT`` to connect to (a ``usdeform live --listen`` service), or with ``listen`` to
        serve clients on (``usdeform live --connect``, 3D Slicer), as PLUS Server does.
    rate_hz : float, optional
        Frames per second; None: as fast as the connection takes them.
    loops : int
        Times the recording is played; each loop's timestamps continue after the last one's.
    listen : bool
        Serve clients at ``to`` instead of connecting: the frames start once the first has connected,
        every client connected meanwhile gets them from its arrival on, and one too slow to take them
        is dropped alone.
    timeout_s : float
        Longest wait to connect (or for the first client).
    frames : int, optional
        Stop after this many frames.
    clock : {"wall", "recording"}
        ``wall``: each frame stamped with the wall clock (UTC seconds) when it is sent, as PLUS Server
        stamps a frame when it is acquired, so that a recording played again continues the scan's time;
        ``recording``: the recording's own timestamps, each loop's after the last one's.

    Returns
    -------
    ReplayResult
    """
    if not isinstance(recording, Recording):
        recording = read_sequence(recording)
    if rate_hz is not None and not (math.isfinite(rate_hz) and 1e-3 <= rate_hz <= 1e3):
        raise InputError(f"rate_hz: expected a rate from 0.001 to 1000 Hz, got {rate_hz}")
    if loops < 1:
        raise InputError(f"loops: expected at least 1, got {loops}")
    times = recording.timestamps
    step = float(np.median(np.diff(times))) if len(times) > 1 else 1.0
    period = float(times[-1] - times[0]) + max(step, 1e-3)  # each loop's timestamps follow the last one's
    total = len(recording) * loops if frames is None else min(frames, len(recording) * loops)
    sent_at: list[float] = []
    address = socket_address(to, "--serve" if listen else "--to")
    if listen:
        return _replay_to_clients(recording, address, rate_hz, total, period, timeout_s, clock)
    connection = _connect(address, timeout_s)
    start = time.perf_counter()
    try:
        for count in range(total):
            _wait_for_turn(start, count, rate_hz)
            loop, frame = divmod(count, len(recording))
            timestamp = time.time() if clock == "wall" else float(times[frame] + loop * period)
            data = b"".join(message.pack() for message in replay_messages(recording, frame, timestamp))
            try:
                connection.sendall(data)
            except OSError as error:
                raise UsdeformError(f"replay: the connection dropped after {count} frames ({error})") from None
            sent_at.append(time.perf_counter())
        seconds = (sent_at[-1] if sent_at else start) - start
        _close_gracefully(connection)
    finally:
        connection.close()
    return ReplayResult(len(sent_at), sent_at, seconds)


def _wait_for_turn(start: float, count: int, rate_hz: float | None) -> None:
    """Sleep until frame ``count`` is due at ``rate_hz`` frames per second (None: at once)."""
    if rate_hz is not None:
        delay = start + count / rate_hz - time.perf_counter()
        if delay > 0:
            time.sleep(delay)


def _replay_to_clients(
    recording: Recording,
    address: tuple[str, int],
    rate_hz: float | None,
    total: int,
    period: float,
    timeout_s: float,
    clock: str,
) -> ReplayResult:
    """:func:`replay` with ``listen``: every client connected meanwhile gets the frames from its arrival on;
    a client too slow to take them is dropped alone."""
    clients = _serve(address, rate_hz, timeout_s)
    sent_at: list[float] = []
    served: set[str] = set()
    start = time.perf_counter()
    try:
        for count in range(total):
            _wait_for_turn(start, count, rate_hz)
            loop, frame = divmod(count, len(recording))
            timestamp = time.time() if clock == "wall" else float(recording.timestamps[frame] + loop * period)
            clients.queue_outputs(replay_messages(recording, frame, timestamp))
            sent_at.append(time.perf_counter())
            served.update(clients.viewer_names())
            while not clients.inbox.empty():  # what the clients send is not read
                clients.inbox.get_nowait()
        seconds = (sent_at[-1] if sent_at else start) - start
        clients.end_outputs(timeout_s=30.0)
    finally:
        clients.close()
    return ReplayResult(len(sent_at), sent_at, seconds, clients=len(served))
