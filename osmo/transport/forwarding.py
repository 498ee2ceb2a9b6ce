"""Sockets carried over a session's stream: the two ends of ``osmo workflow port-forward``.

A forward session multiplexes connections on one :class:`~osmo.transport.streams.Stream`,
one channel each. The client opens a channel (``OPEN`` with ``{"port": R, "udp": bool}``)
for every accepted TCP connection or every new UDP sender; the node connects to the task's
port R off the stream's thread (a :class:`Deferred` end holds what the client sends
meanwhile, so a port that does not answer stalls only its own channel) and answers ``CLOSE``
(with the reason) if it cannot. Bytes go both ways as
``DATA``; a TCP side that reads end-of-file sends ``EOF`` and the other side shuts down
its write half; a channel is closed when both halves ended, or at once on ``CLOSE``.

:class:`Channels` is the bookkeeping both ends share: which socket a channel is, a reader
thread per socket, and delivery of the peer's frames. Writes happen on the stream's
receiving thread, so a local reader that does not read slows every channel of the session
(the price of one ordered stream; documented as a limit).
"""

from __future__ import annotations

import logging
import socket
import threading
from collections.abc import Callable
from typing import Protocol

from osmo.transport.streams import CHUNK, Frame, Kind

__all__ = ["Channels", "Deferred", "TcpEnd", "UdpConnected", "UdpPeer"]

log = logging.getLogger("osmo.forward")

Send = Callable[[Kind, int, bytes], bool]
MAX_CHANNELS = 4096
"""Channels one session may have open at once."""
_DATAGRAM = 65535
_PENDING_BYTES = 4 * CHUNK
"""What a channel still connecting holds for the task; more ends the channel."""


class End(Protocol):
    """One local end of a channel."""

    def write(self, data: bytes) -> None:
        """Deliver the peer's bytes."""

    def eof(self) -> None:
        """The peer will send no more."""

    def close(self) -> None:
        """Let go of the socket (idempotent)."""


class TcpEnd:
    """A connected TCP socket."""

    def __init__(self, sock: socket.socket) -> None:
        self.sock = sock

    def write(self, data: bytes) -> None:
        """Send all of ``data``."""
        self.sock.sendall(data)

    def eof(self) -> None:
        """Shut down the write half (the reader sees end-of-file)."""
        self.sock.shutdown(socket.SHUT_WR)

    def close(self) -> None:
        """Close the socket (a reader blocked on it wakes up)."""
        try:
            self.sock.shutdown(socket.SHUT_RDWR)
        except OSError:
            pass
        self.sock.close()


class UdpConnected(TcpEnd):
    """A UDP socket connected to the task's port (the node's end of a UDP channel)."""

    def eof(self) -> None:
        """UDP has no end-of-file."""


class UdpPeer:
    """A UDP sender on the client's listening socket: replies go back to its address."""

    def __init__(self, sock: socket.socket, addr: tuple[str, int]) -> None:
        self.sock, self.addr = sock, addr

    def write(self, data: bytes) -> None:
        """Send ``data`` to the sender as one datagram."""
        self.sock.sendto(data, self.addr)

    def eof(self) -> None:
        """UDP has no end-of-file."""

    def close(self) -> None:
        """The listening socket is shared: nothing to close."""


class Deferred:
    """A channel's end while the node still connects to the task's port.

    It keeps what the peer sends (up to a few frames: a client sends its request, then
    waits for an answer) and hands it over, in order, to the connected end.
    """

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._pending: list[bytes] = []
        self._size = 0
        self._eof = False
        self._closed = False
        self._end: End | None = None

    def write(self, data: bytes) -> None:
        """Pass ``data`` on, or keep it until connected.

        Raises:
            OSError: more than the channel may hold arrived before the connection.
        """
        with self._lock:
            if self._end is None:
                self._size += len(data)
                if self._size > _PENDING_BYTES:
                    raise OSError("too much data before the task's port answered")
                self._pending.append(data)
                return
            end = self._end
        end.write(data)

    def eof(self) -> None:
        """Pass end-of-file on, or remember it until connected."""
        with self._lock:
            if self._end is None:
                self._eof = True
                return
            end = self._end
        end.eof()

    def attach(self, end: End) -> bool:
        """Hand what was kept to ``end`` and pass everything on from now.

        Returns:
            False when the channel was closed meanwhile (``end`` is then closed).

        Raises:
            OSError: ``end`` refused what was kept.
        """
        with self._lock:
            if not self._closed:
                for data in self._pending:
                    end.write(data)
                if self._eof:
                    end.eof()
                self._pending, self._end = [], end
                return True
        end.close()
        return False

    def close(self) -> None:
        """Close the connected end, or refuse the one still coming."""
        with self._lock:
            self._closed, end = True, self._end
        if end is not None:
            end.close()


class Channels:
    """The open channels of one session (see the module docstring)."""

    def __init__(self, send: Send) -> None:
        self._send = send
        self._lock = threading.Lock()
        self._ends: dict[int, End] = {}
        self._halves: dict[int, int] = {}  # channel -> halves ended (2: close it)

    def __len__(self) -> int:
        with self._lock:
            return len(self._ends)

    def add(self, channel: int, end: End) -> bool:
        """Register ``end`` as ``channel``; False (and ``end`` closed) when too many are open."""
        with self._lock:
            if len(self._ends) >= MAX_CHANNELS or channel in self._ends:
                full = True
            else:
                full = False
                self._ends[channel], self._halves[channel] = end, 0
        if full:
            end.close()
        return not full

    def pump(self, channel: int, sock: socket.socket, *, datagrams: bool = False) -> None:
        """Read ``sock`` on a thread of its own and send what it reads on ``channel``."""
        threading.Thread(target=self._read, args=(channel, sock, datagrams),
                         name="osmo-forward", daemon=True).start()

    def _read(self, channel: int, sock: socket.socket, datagrams: bool) -> None:
        size = _DATAGRAM if datagrams else CHUNK
        try:
            while data := sock.recv(size):
                if not self._send(Kind.DATA, channel, data):
                    break
            else:
                if not datagrams:
                    self._send(Kind.EOF, channel, b"")
                    self._half(channel)
                    return
        except OSError:
            pass
        if self.drop(channel):
            self._send(Kind.CLOSE, channel, b"")

    def deliver(self, frame: Frame) -> None:
        """Act on the peer's ``DATA``, ``EOF`` or ``CLOSE`` for an open channel."""
        with self._lock:
            end = self._ends.get(frame.channel)
        if end is None:
            return
        try:
            if frame.kind is Kind.DATA:
                end.write(frame.data)
            elif frame.kind is Kind.EOF:
                end.eof()
                self._half(frame.channel)
            elif frame.kind is Kind.CLOSE:
                self.drop(frame.channel)
        except OSError:
            if self.drop(frame.channel):
                self._send(Kind.CLOSE, frame.channel, b"")

    def _half(self, channel: int) -> None:
        with self._lock:
            if channel not in self._halves:
                return
            self._halves[channel] += 1
            done = self._halves[channel] >= 2
        if done:
            self.drop(channel)

    def drop(self, channel: int) -> bool:
        """Close ``channel``'s socket; False if it was not open."""
        with self._lock:
            end = self._ends.pop(channel, None)
            self._halves.pop(channel, None)
        if end is None:
            return False
        end.close()
        return True

    def close(self) -> None:
        """Close every channel."""
        with self._lock:
            channels = list(self._ends)
        for channel in channels:
            self.drop(channel)
