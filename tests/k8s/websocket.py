"""The server side of a WebSocket (RFC 6455), as the API server speaks it for ``pods/exec``.

Only what the Kubernetes exec protocol needs: the upgrade handshake with a chosen
subprotocol, binary frames out (unmasked), frames in (masked by the client, possibly
fragmented), ping answered with pong, close. Kubernetes' channel protocols (``v4`` and
``v5.channel.k8s.io``) put the channel number in each binary message's first byte: 0 stdin,
1 stdout, 2 stderr, 3 the error channel (a Status), 4 resize, and in v5 255 closes a channel.
"""

from __future__ import annotations

import base64
import hashlib
import struct
import threading
from typing import BinaryIO

__all__ = ["CLOSE", "WebSocket", "accept_key"]

_GUID = b"258EAFA5-E914-47DA-95CA-C5AB0DC85B11"
BINARY, CLOSE, PING, PONG = 0x2, 0x8, 0x9, 0xA


def accept_key(key: str) -> str:
    """The ``Sec-WebSocket-Accept`` value for a client's ``Sec-WebSocket-Key``."""
    return base64.b64encode(hashlib.sha1(key.encode() + _GUID).digest()).decode()


class WebSocket:
    """An upgraded connection: ``rfile``/``wfile`` of the HTTP handler (thread-safe sends)."""

    def __init__(self, rfile: BinaryIO, wfile: BinaryIO) -> None:
        self.rfile, self.wfile = rfile, wfile
        self._send_lock = threading.Lock()

    def send(self, data: bytes, opcode: int = BINARY) -> None:
        """One unmasked frame."""
        size = len(data)
        if size < 126:
            header = struct.pack("!BB", 0x80 | opcode, size)
        elif size < 1 << 16:
            header = struct.pack("!BBH", 0x80 | opcode, 126, size)
        else:
            header = struct.pack("!BBQ", 0x80 | opcode, 127, size)
        with self._send_lock:
            self.wfile.write(header + data)
            self.wfile.flush()

    def receive(self) -> tuple[int, bytes] | None:
        """The next message ``(opcode, payload)``; None when the connection ended."""
        opcode, parts = 0, []
        while True:
            head = self.rfile.read(2)
            if len(head) < 2:
                return None
            first, second = head
            size = second & 0x7F
            if size == 126:
                size = struct.unpack("!H", self.rfile.read(2))[0]
            elif size == 127:
                size = struct.unpack("!Q", self.rfile.read(8))[0]
            mask = self.rfile.read(4) if second & 0x80 else b"\0\0\0\0"
            data = bytearray(self.rfile.read(size))
            for i in range(len(data)):
                data[i] ^= mask[i % 4]
            code = first & 0x0F
            if code == PING:
                self.send(bytes(data), PONG)
                continue
            if code in (PONG,):
                continue
            if code != 0:
                opcode = code
            parts.append(bytes(data))
            if first & 0x80:
                return opcode, b"".join(parts)
