"""A client of the live service, as 3D Slicer's OpenIGTLinkIF connector is one: for scripts, tests
and the benchmark."""

from __future__ import annotations

import socket
import threading
import time
from array import array
from typing import Any

from .transport import BrokenStream, MalformedMessage, UnsupportedMessage, receive_message

__all__ = ["LiveClient"]


class LiveClient:
    """Connects to a live service (``usdeform live --listen``) and keeps what it sends, in a thread.

    Parameters
    ----------
    address : (host, port)
        The service's listening address.
    keep : int
        Messages kept (the oldest are dropped beyond it; :attr:`counts` counts them all).
    keep_pixels : bool
        Keep the voxels of the IMAGE messages; False: only their header, geometry and metadata
        (``image`` None), for a client that watches rates and metadata for a long time.
    max_seconds : float
        The reading thread ends after this long at most.
    timing : bool
        Also keep every message's timestamp and arrival time (:attr:`timestamps`, :attr:`arrivals`): 16
        bytes a message, and no Python object a message. A client holding the messages themselves pauses
        for Python's full garbage collections, longer the more it holds (0.1 to 0.2 s with the 70,000
        messages of 10 minutes at 30 frames/s), and would take its own pauses for the service's.

    Attributes
    ----------
    messages : list
        ``(arrival time.perf_counter(), pyigtl message)``, oldest first.
    counts : dict of str to int
        Messages received per device name.
    timestamps, arrivals : dict of str to array of float
        With ``timing``, per device name: every message's timestamp, s, and its arrival
        (``time.perf_counter()``, s), in the order received.
    """

    def __init__(
        self,
        address: tuple[str, int],
        *,
        keep: int = 1000,
        keep_pixels: bool = True,
        max_seconds: float = 3600.0,
        timing: bool = False,
    ) -> None:
        self.connection = socket.create_connection(address, timeout=5.0)
        self.connection.settimeout(0.1)
        self.keep, self.keep_pixels, self.max_seconds, self.timing = keep, keep_pixels, max_seconds, timing
        self.messages: list[tuple[float, Any]] = []
        self.counts: dict[str, int] = {}
        self.timestamps: dict[str, array[float]] = {}
        self.arrivals: dict[str, array[float]] = {}
        self._done = threading.Event()
        self._lock = threading.Lock()
        self._thread = threading.Thread(target=self._read, name="usdeform-live-client", daemon=True)
        self._thread.start()

    def _read(self) -> None:
        deadline = time.monotonic() + self.max_seconds
        while not self._done.is_set() and time.monotonic() < deadline:
            try:
                received = receive_message(self.connection)
            except (TimeoutError, MalformedMessage, UnsupportedMessage):
                continue
            except (BrokenStream, OSError):
                return
            if received is None:
                return
            arrived, message = time.perf_counter(), received[0]
            if not self.keep_pixels and message.message_type == "IMAGE":
                message.image = None
            name = message.device_name
            with self._lock:
                self.messages.append((arrived, message))
                del self.messages[: max(0, len(self.messages) - self.keep)]
                self.counts[name] = self.counts.get(name, 0) + 1
                if self.timing:
                    self.timestamps.setdefault(name, array("d")).append(float(message.timestamp))
                    self.arrivals.setdefault(name, array("d")).append(arrived)

    def named(self, name: str) -> list[Any]:
        """The messages kept of device ``name``, oldest first."""
        with self._lock:
            return [message for _, message in self.messages if message.device_name == name]

    def close(self) -> None:
        """Stop reading and close the connection."""
        self._done.set()
        self._thread.join(timeout=5.0)
        self.connection.close()
