"""The live service's connections: a listening socket, a reader per connection, one sender.

:class:`Connections` accepts connections on the listening address (a robot node or
:func:`~usdeform.live.replay` pushing a scan, 3D Slicer's OpenIGTLinkIF connector, any number of each)
and, with ``connect``, keeps one to a PLUS Server. Every message read goes to :attr:`Connections.inbox`;
the outputs handed to :meth:`Connections.offer_outputs` or :meth:`Connections.queue_outputs` are packed
on the sending thread and go to every accepted connection that has sent no IMAGE (a viewer). A
connection that drops, a message that cannot be read and a viewer that goes away are logged (logger
``usdeform.live``) and the others go on.
"""

from __future__ import annotations

import logging
import math
import queue
import socket
import threading
import time
from collections.abc import Callable
from typing import Any

from ..errors import InputError, UsdeformError
from .transport import BrokenStream, MalformedMessage, UnsupportedMessage, receive_message

__all__ = ["Connections", "Peer", "socket_address"]

log = logging.getLogger("usdeform.live")

#: Socket timeout of the reading and accepting threads: how soon they notice a stop, s.
POLL_S = 0.1
#: Longest a viewer may take to take in one message before it is dropped, s.
_SEND_TIMEOUT_S = 5.0


def socket_address(text: str | tuple[str, int]) -> tuple[str, int]:
    """``HOST:PORT`` (or a pair) as a socket address; InputError otherwise."""
    if isinstance(text, tuple):
        return text
    host, _, port = text.rpartition(":")
    if not host or not port.isdigit() or int(port) > 65535:
        raise InputError(f"address {text!r}: expected HOST:PORT, e.g. 127.0.0.1:18945")
    return host, int(port)


class Peer:
    """One connection: its socket, a name for the log, and whether outputs go to it."""

    def __init__(self, connection: socket.socket, name: str, viewer: bool) -> None:
        self.connection, self.name, self.viewer = connection, name, viewer
        self.open = True
        self.lock = threading.Lock()

    def close(self) -> None:
        self.open = False
        try:
            self.connection.shutdown(socket.SHUT_RDWR)
        except OSError:
            pass
        self.connection.close()


class Connections:
    """The sockets and threads of a live service.

    Parameters
    ----------
    listen : (host, port)
        Address to accept connections on (port 0: any free port, see :attr:`port`).
    connect : (host, port), optional
        A PLUS Server to read from (reconnected to every second when it drops).
    stop : threading.Event
        Set when the service stops: the threads stop accepting and reading.
    pack : callable
        Turns one queued output into the buffers to send (called on the sending thread).
    sent : callable
        ``sent(outputs, delivered)`` after each batch of outputs went out, on the sending thread;
        ``delivered``: whether any viewer took it in.

    Attributes
    ----------
    inbox : queue.Queue
        (peer, pyigtl message, read time from ``time.perf_counter``, s) of every message read.
    malformed : int
        Messages that could not be read (skipped, or the end of their connection).
    last_input : float
        ``time.perf_counter`` of the latest message read, s (inf before the first).
    port : int
        The port listened on, once :meth:`start` returned.
    """

    def __init__(
        self,
        listen: tuple[str, int],
        connect: tuple[str, int] | None,
        stop: threading.Event,
        pack: Callable[[Any], list[bytes | memoryview]],
        sent: Callable[[list[Any], bool], None],
    ) -> None:
        self.listen_address, self.connect_address = listen, connect
        self._stop, self._pack, self._sent = stop, pack, sent
        self.inbox: queue.Queue[tuple[Peer, Any, float]] = queue.Queue()
        self.malformed = 0
        self.last_input = math.inf
        self.port = 0
        self._peers: list[Peer] = []
        self._peers_lock = threading.Lock()
        self._threads: list[threading.Thread] = []
        self._outbox: queue.Queue[list[Any] | None] = queue.Queue(maxsize=4)
        self._listener: socket.socket | None = None
        self._closed = False

    @property
    def started(self) -> bool:
        """Whether :meth:`start` bound the listening address."""
        return self._listener is not None

    def start(self) -> None:
        """Bind the listening address and start the accepting, connecting and sending threads."""
        listener = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        listener.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            listener.bind(self.listen_address)
        except OSError as error:
            listener.close()
            raise UsdeformError(f"--listen {self.listen_address[0]}:{self.listen_address[1]}: {error}") from None
        listener.listen(8)
        listener.settimeout(POLL_S)
        self._listener, self.port = listener, listener.getsockname()[1]
        log.info("listening on %s:%d", self.listen_address[0], self.port)
        self._spawn(self._accept, "accept")
        if self.connect_address is not None:
            self._spawn(self._connect, "connect")
        self._spawn(self._send, "send")

    def _spawn(self, target: Any, name: str, *args: Any) -> None:
        thread = threading.Thread(target=target, args=args, name=f"usdeform-live-{name}", daemon=True)
        self._threads.append(thread)
        thread.start()

    def _accept(self) -> None:
        assert self._listener is not None
        while not self._stop.is_set():
            try:
                connection, (host, port) = self._listener.accept()
            except TimeoutError:
                continue
            except OSError:
                return
            # Outputs go out as written (a message is several writes: no wait for the viewer's acknowledgement).
            connection.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            peer = Peer(connection, f"{host}:{port}", viewer=True)
            log.info("connection from %s", peer.name)
            with self._peers_lock:
                self._peers.append(peer)
            self._spawn(self._read, f"read-{peer.name}", peer)

    def _connect(self) -> None:
        assert self.connect_address is not None
        host, port = self.connect_address
        warned = False
        while not self._stop.is_set():
            try:
                connection = socket.create_connection((host, port), timeout=1.0)
            except OSError as error:
                if not warned:
                    log.warning("cannot connect to %s:%d (%s); retrying every second", host, port, error)
                    warned = True
                self._stop.wait(1.0)
                continue
            warned = False
            log.info("connected to %s:%d", host, port)
            self._read(Peer(connection, f"{host}:{port}", viewer=False))
            self._stop.wait(1.0)

    def _read(self, peer: Peer) -> None:
        peer.connection.settimeout(POLL_S)
        reason = "closed by the peer"
        while not self._stop.is_set() and peer.open:
            try:
                received = receive_message(peer.connection)
            except TimeoutError:
                continue
            except (MalformedMessage, UnsupportedMessage) as error:
                if isinstance(error, MalformedMessage):
                    self.malformed += 1
                    log.warning("%s: skipped a malformed message: %s", peer.name, error)
                else:
                    log.debug("%s: ignored an unsupported message: %s", peer.name, error)
                continue
            except BrokenStream as error:
                self.malformed += 1
                reason = f"dropped: {error}"
                break
            except OSError as error:
                reason = f"dropped ({error})"
                break
            if received is None:
                break
            message = received[0]
            if peer.viewer and message.message_type == "IMAGE":
                peer.viewer = False  # a scan source: the outputs go to the other connections
            self.last_input = time.perf_counter()
            self.inbox.put((peer, message, self.last_input))
        if not self._stop.is_set() and peer.open:
            level = logging.INFO if reason == "closed by the peer" else logging.WARNING
            log.log(level, "connection %s %s; the service goes on", peer.name, reason)
        self._drop(peer)

    def _drop(self, peer: Peer) -> None:
        with self._peers_lock:
            if peer in self._peers:
                self._peers.remove(peer)
        peer.close()

    def _send(self) -> None:
        while True:
            try:
                item = self._outbox.get(timeout=POLL_S)
            except queue.Empty:
                if self._closed:
                    return
                continue
            if item is None:
                return
            data: list[bytes | memoryview] = []
            for output in item:
                try:
                    data += self._pack(output)
                except Exception:  # a bug: logged; the service goes on with the other outputs
                    log.exception("could not pack an output (%s); it is not sent", type(output).__name__)
            with self._peers_lock:
                viewers = [peer for peer in self._peers if peer.viewer]
            delivered = False
            for peer in viewers:
                try:
                    peer.connection.settimeout(_SEND_TIMEOUT_S)
                    with peer.lock:
                        for chunk in data:
                            peer.connection.sendall(chunk)
                    delivered = True
                except OSError as error:
                    log.warning("viewer %s went away (%s); the service goes on", peer.name, error)
                    self._drop(peer)
                finally:
                    if peer.open:
                        peer.connection.settimeout(POLL_S)
            self._sent(item, delivered)

    def offer_outputs(self, outputs: list[Any]) -> bool:
        """Hand outputs to the sending thread unless it is behind (four batches waiting); never waits.
        Returns whether they were taken."""
        try:
            self._outbox.put_nowait(outputs)
        except queue.Full:
            return False
        return True

    def queue_outputs(self, outputs: list[Any] | None) -> None:
        """Hand outputs (None: the end) to the sending thread; if it is behind, wait for it (at most
        four batches wait)."""
        sender = next(thread for thread in self._threads if thread.name.endswith("send"))
        while sender.is_alive():
            try:
                self._outbox.put(outputs, timeout=POLL_S)
                return
            except queue.Full:
                continue

    def end_outputs(self, timeout_s: float) -> None:
        """Queue the end of the outputs and wait up to ``timeout_s`` for the sending thread to send the rest."""
        self.queue_outputs(None)
        for thread in self._threads:
            if thread.name.endswith("send"):
                thread.join(timeout=timeout_s)

    def close(self) -> None:
        """Stop the threads, close every connection and wait for the threads (2 s each at most)."""
        self._stop.set()
        self._closed = True
        if self._listener is not None:
            self._listener.close()
        with self._peers_lock:
            peers = list(self._peers)
        for peer in peers:
            peer.close()
        for thread in self._threads:
            thread.join(timeout=2.0)
