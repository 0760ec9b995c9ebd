"""The live service's connections: a listening socket, a reader per connection, a packing thread and
a sending thread per viewer.

:class:`Connections` accepts connections on the listening address (a robot node or
:func:`~usdeform.live.replay` pushing a scan, 3D Slicer's OpenIGTLinkIF connector, any number of each)
and, with ``connect``, keeps one to a PLUS Server. Every message read goes to :attr:`Connections.inbox`,
and so does the end of a connection (its message None). The outputs handed to
:meth:`Connections.offer_outputs` or :meth:`Connections.queue_outputs` are packed once, on the packing
thread, (the frames are packed by the caller: :meth:`Connections.send_outputs`) and go to every accepted connection
that has sent no IMAGE (a viewer). Each viewer has its own
bounded queue and sending thread: a viewer that does not keep up holds up no other. When its queue is
full it gets no more outputs, and its connection is closed unless it sends messages of its own (a robot
node that also listens keeps its input). A connection that drops, a message that cannot be read and a
viewer that goes away are logged (logger ``usdeform.live``) and the others go on.
"""

from __future__ import annotations

import logging
import math
import queue
import select
import socket
import threading
import time
from collections import deque
from collections.abc import Callable
from typing import Any

from ..errors import InputError, UsdeformError
from .transport import BrokenStream, MalformedMessage, UnsupportedMessage, receive_message

__all__ = ["Connections", "Peer", "socket_address"]

log = logging.getLogger("usdeform.live")

#: How soon the reading and accepting threads notice a stop, s.
POLL_S = 0.1
#: Longest a viewer may take to take in one message before it gets no more outputs, s.
SEND_TIMEOUT_S = 5.0
#: Batches of outputs that may wait for one viewer (about 2 s of frames at 30 frames/s).
VIEWER_QUEUE = 64
#: Batches of outputs that may wait to be packed.
OUTBOX = 64


def socket_address(text: str | tuple[str, int], option: str = "address") -> tuple[str, int]:
    """``HOST:PORT`` (or a pair) as a socket address; InputError naming ``option`` otherwise."""
    if isinstance(text, tuple):
        return text
    host, _, port = text.rpartition(":")
    if not host or not port.isdigit() or int(port) > 65535:
        raise InputError(f"{option} {text!r}: expected HOST:PORT, e.g. 127.0.0.1:18945")
    return host, int(port)


def bind_listener(address: tuple[str, int], option: str) -> socket.socket:
    """A listening TCP socket on ``address``; UsdeformError naming ``option`` and the address if it cannot be had."""
    listener = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
    listener.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
    try:
        listener.bind(address)
    except OSError as error:
        listener.close()
        reason = error.strerror or str(error)
        raise UsdeformError(f"{option} {address[0]}:{address[1]}: cannot listen there ({reason})") from None
    listener.listen(16)
    listener.settimeout(POLL_S)
    return listener


class ViewerQueue:
    """The outputs waiting for one viewer: at most ``size`` batches, in two lanes, each in the order put.

    Those put ``ahead`` (the frames) go first. While frames flow, the others (volumes, status, replies)
    go only right after a frame (within ``AFTER_FRAME_S``), so that a volume of megabytes is taken in
    during the gap before the next frame instead of holding it up; once no frame came for twice the
    frames' interval (``HOLD_MAX_S`` at most), they go at once. None ends the sending thread.
    """

    #: How soon after a frame a batch of the other lane may follow it, s.
    AFTER_FRAME_S = 0.005
    #: Longest a batch of the other lane waits for a frame to follow, s.
    HOLD_MAX_S = 0.5

    def __init__(self, size: int) -> None:
        self.size = size
        self._ahead: deque[list[bytes | memoryview] | None] = deque()
        self._behind: deque[list[bytes | memoryview] | None] = deque()
        self._changed = threading.Condition()
        self._last_frame = -math.inf  # time.perf_counter() when the last frame taken was sent
        self._sent_frame = False  # the last batch taken was a frame
        self._frame_interval = math.inf  # the frames' interval, s (a running mean)

    def qsize(self) -> int:
        with self._changed:
            return len(self._ahead) + len(self._behind)

    def put(self, data: list[bytes | memoryview] | None, *, ahead: bool = False, timeout: float | None = 0.0) -> bool:
        """Queue ``data``, waiting up to ``timeout`` s for room (None: no limit); False if there was none."""
        with self._changed:
            if not self._changed.wait_for(lambda: len(self._ahead) + len(self._behind) < self.size, timeout):
                return False
            (self._ahead if ahead else self._behind).append(data)
            self._changed.notify_all()
        return True

    def get(self) -> list[bytes | memoryview] | None:
        """The next batch to send, waiting for one (see the class's notes)."""
        with self._changed:
            if self._sent_frame:  # the sending thread is back from sending a frame
                self._last_frame, self._sent_frame = time.perf_counter(), False
            while True:
                now = time.perf_counter()
                if self._ahead:
                    interval = now - self._last_frame
                    if interval < self.HOLD_MAX_S:
                        mean = self._frame_interval
                        self._frame_interval = interval if math.isinf(mean) else 0.9 * mean + 0.1 * interval
                    self._sent_frame = True
                    data = self._ahead.popleft()
                    break
                since_frame = now - self._last_frame
                hold = min(2.0 * self._frame_interval, self.HOLD_MAX_S)
                if self._behind and (since_frame <= self.AFTER_FRAME_S or since_frame >= hold):
                    data = self._behind.popleft()
                    break
                self._changed.wait(timeout=hold - since_frame if self._behind else None)
            self._changed.notify_all()
            return data


class Peer:
    """One connection: its socket, a name for the log, whether outputs go to it (``viewer``) and whether it
    sent any message (``source``); the outputs waiting for it and the thread that sends them."""

    def __init__(self, connection: socket.socket, name: str, viewer: bool) -> None:
        self.connection, self.name, self.viewer = connection, name, viewer
        self.source = False
        self.open = True
        self.outputs = ViewerQueue(VIEWER_QUEUE)
        self.sender: threading.Thread | None = None
        self.sender_lock = threading.Lock()  # outputs are handed from two threads: one sending thread starts

    def close(self) -> None:
        self.open = False
        self.viewer = False
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
        Turns one queued output into the buffers to send (called on the packing thread).
    listen_option : str
        The option that gave ``listen``, for messages.
    wait_for_viewers : bool
        Wait for a viewer's queue to have room instead of giving it up (a replay sending as fast as
        its clients take the frames).

    Attributes
    ----------
    inbox : queue.Queue
        (peer, pyigtl message or None at the connection's end, read time from ``time.perf_counter``, s).
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
        *,
        listen_option: str = "--listen",
        wait_for_viewers: bool = False,
    ) -> None:
        self.listen_address, self.connect_address = listen, connect
        self._stop, self._pack = stop, pack
        self.listen_option, self.wait_for_viewers = listen_option, wait_for_viewers
        self.inbox: queue.Queue[tuple[Peer, Any, float]] = queue.Queue()
        self.malformed = 0
        self.last_input = math.inf
        self.port = 0
        self._peers: list[Peer] = []
        self._peers_lock = threading.Lock()
        self._threads: list[threading.Thread] = []
        self._outbox: queue.Queue[tuple[list[Any], Peer | None] | None] = queue.Queue(maxsize=OUTBOX)
        self._listener: socket.socket | None = None
        self._closed = False

    @property
    def started(self) -> bool:
        """Whether :meth:`start` bound the listening address."""
        return self._listener is not None

    @property
    def viewers(self) -> int:
        """Connections the outputs go to."""
        return len(self.viewer_names())

    def viewer_names(self) -> list[str]:
        """Names (``host:port``) of the connections the outputs go to."""
        with self._peers_lock:
            return [peer.name for peer in self._peers if peer.viewer]

    def start(self) -> None:
        """Bind the listening address and start the accepting, connecting and packing threads."""
        self._listener = bind_listener(self.listen_address, self.listen_option)
        self.port = self._listener.getsockname()[1]
        log.info("listening on %s:%d", self.listen_address[0], self.port)
        self._spawn(self._accept, "accept")
        if self.connect_address is not None:
            self._spawn(self._connect, "connect")
        self._spawn(self._pack_outputs, "pack")

    def _spawn(self, target: Any, name: str, *args: Any) -> threading.Thread:
        thread = threading.Thread(target=target, args=args, name=f"usdeform-live-{name}", daemon=True)
        self._threads.append(thread)
        thread.start()
        return thread

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
        # One timeout serves both directions of a socket: the long one of sending; reads wait in select.
        peer.connection.settimeout(SEND_TIMEOUT_S)
        reason = "closed by the peer"
        while not self._stop.is_set() and peer.open:
            try:
                if not select.select([peer.connection], [], [], POLL_S)[0]:
                    continue
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
            except (OSError, ValueError) as error:  # ValueError: select on a socket closed meanwhile
                reason = f"dropped ({error})"
                break
            if received is None:
                break
            message = received[0]
            peer.source = True
            if peer.viewer and message.message_type == "IMAGE":
                peer.viewer = False  # a scan source: the outputs go to the other connections
            self.last_input = time.perf_counter()
            self.inbox.put((peer, message, self.last_input))
        if not self._stop.is_set() and peer.open:
            level = logging.INFO if reason == "closed by the peer" else logging.WARNING
            log.log(level, "connection %s %s; the service goes on", peer.name, reason)
        self.inbox.put((peer, None, time.perf_counter()))
        self._drop(peer)

    def _drop(self, peer: Peer) -> None:
        with self._peers_lock:
            if peer in self._peers:
                self._peers.remove(peer)
        peer.close()
        peer.outputs.put(None, ahead=True)  # its sending thread ends (or, with a full queue, sees it closed)

    def _give_up(self, peer: Peer, why: str) -> None:
        """No more outputs for ``peer``; its connection closed unless it sends messages of its own."""
        if not peer.viewer:
            return
        peer.viewer = False
        if peer.source:
            log.warning("viewer %s %s: it gets no more outputs; its messages are still read", peer.name, why)
        else:
            log.warning("viewer %s %s: dropped; the service goes on", peer.name, why)
            self._drop(peer)

    def _pack_outputs(self) -> None:
        while True:
            try:
                item = self._outbox.get(timeout=POLL_S)
            except queue.Empty:
                if self._closed:
                    return
                continue
            if item is None:
                self._end_viewers()
                return
            self.send_outputs(*item)

    def send_outputs(self, outputs: list[Any], to: Peer | None = None, *, ahead: bool = False) -> None:
        """Pack ``outputs`` on the calling thread and queue them for every viewer (or for ``to`` alone),
        ``ahead`` of the volumes waiting (the frames); never waits (a viewer whose queue is full gets no
        more outputs)."""
        data: list[bytes | memoryview] = []
        for output in outputs:
            try:
                data += self._pack(output)
            except Exception:  # a bug: logged; the service goes on with the other outputs
                log.exception("could not pack an output (%s); it is not sent", type(output).__name__)
        if not data:
            return
        with self._peers_lock:
            viewers = [peer for peer in self._peers if peer.viewer] if to is None else [to]
        for peer in viewers:
            self._hand(peer, data, ahead=ahead)

    def _hand(self, peer: Peer, data: list[bytes | memoryview] | None, *, ahead: bool = False) -> None:
        """Queue ``data`` (None: the end) for ``peer``'s sending thread, started on the first."""
        with peer.sender_lock:
            if peer.sender is None:
                peer.sender = self._spawn(self._send, f"send-{peer.name}", peer)
        wait = SEND_TIMEOUT_S if self.wait_for_viewers or data is None else 0.0
        if not peer.outputs.put(data, ahead=ahead, timeout=wait) and data is not None:
            self._give_up(peer, f"is too slow ({VIEWER_QUEUE} batches of outputs waiting)")

    def _send(self, peer: Peer) -> None:
        while True:
            data = peer.outputs.get()
            if data is None or not peer.open:
                return
            try:
                for chunk in data:
                    peer.connection.sendall(chunk)
            except TimeoutError:
                self._give_up(peer, f"took no output for {SEND_TIMEOUT_S:g} s")
                return
            except OSError as error:
                if peer.viewer:
                    log.warning("viewer %s went away (%s); the service goes on", peer.name, error)
                    self._drop(peer)
                return

    def _end_viewers(self) -> None:
        """Queue the end for every viewer's sending thread, and wait (``SEND_TIMEOUT_S`` each at most)."""
        with self._peers_lock:
            viewers = [peer for peer in self._peers if peer.viewer]
        for peer in viewers:
            self._hand(peer, None)
        for peer in viewers:
            if peer.sender is not None:
                peer.sender.join(timeout=SEND_TIMEOUT_S)

    def offer_outputs(self, outputs: list[Any], to: Peer | None = None) -> bool:
        """Hand outputs for the viewers (or for the connection ``to`` alone) to the packing thread unless it
        is behind (``OUTBOX`` batches waiting); never waits. Returns whether they were taken."""
        try:
            self._outbox.put_nowait((outputs, to))
        except queue.Full:
            return False
        return True

    def queue_outputs(self, outputs: list[Any] | None, to: Peer | None = None) -> None:
        """Hand outputs for the viewers (or for the connection ``to`` alone; None: the end) to the packing
        thread; if it is behind, wait for it."""
        packer = next(thread for thread in self._threads if thread.name.endswith("-pack"))
        while packer.is_alive():
            try:
                self._outbox.put(None if outputs is None else (outputs, to), timeout=POLL_S)
                return
            except queue.Full:
                continue

    def end_outputs(self, timeout_s: float) -> None:
        """Queue the end of the outputs and wait up to ``timeout_s`` for them to be sent to the viewers."""
        self.queue_outputs(None)
        for thread in self._threads:
            if thread.name.endswith("-pack"):
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
            self._drop(peer)
        for thread in self._threads:
            thread.join(timeout=2.0)
