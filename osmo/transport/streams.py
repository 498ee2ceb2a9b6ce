"""Byte streams between a client and a node over zenoh: framed, encrypted, kept alive.

An interactive session (``osmo workflow exec``, ``osmo workflow port-forward``) is a pair of
keys under the cluster's prefix, ``stream/<session id>/up`` (client → node) and
``stream/<session id>/down`` (node → client). Each :class:`Frame` is one put: its
attachment is a header — sequence number (u64), kind (u8), channel (u32) — and its payload
the frame's bytes sealed with AES-256-GCM (``osmo.transport.seal.Aead``) under the
direction's key (derived from the session's 32-byte random key), the nonce being the
sequence number and the associated data the header and the direction's key expression.

Trust: the session id (128 random bits) and key travel only in sealed replies and orders
(``osmo.server.sessions``), never in clear. A zenoh peer of the cluster that sees the frames
(any peer can subscribe to any key) reads only ciphertext, and cannot forge, replay or
reflect a frame: a frame that does not open under the direction's key ends the session
(like a bad record in TLS), one whose sequence number is not above the last one accepted is
dropped.

Liveness: each end sends a heartbeat every :data:`BEAT_EVERY` seconds and calls
``on_lost`` when nothing valid came for ``timeout`` seconds (while it was not itself busy
delivering a frame, so a slow local reader is not taken for a dead peer).
"""

from __future__ import annotations

import enum
import hashlib
import hmac
import json
import logging
import re
import struct
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

from osmo.errors import UsageError
from osmo.transport.seal import Aead
from osmo.transport.zenoh_link import Link, Subscription

__all__ = ["BEAT_EVERY", "CHUNK", "MAX_COMMAND", "MAX_PORTS", "Frame", "Kind", "SessionGrant",
           "Stream"]

CHUNK = 128 << 10
"""Largest frame payload (bytes); FACTS.md: 64–256 KiB puts move fastest."""
BEAT_EVERY = 1.0
TIMEOUT = 8.0
"""Seconds without a valid frame after which the peer counts as gone."""

_HEADER = struct.Struct(">QBI")
_SESSION_ID = re.compile(r"[0-9a-f]{32}")
MAX_COMMAND = 256
"""Most words of an exec command (the server checks requests, the node grants)."""
MAX_PORTS = 1024
"""Most ports one port-forward session may open."""


log = logging.getLogger("osmo.streams")


def _direction_key(key: bytes, direction: bytes) -> bytes:
    return hmac.new(key, b"osmo stream v1 " + direction, hashlib.sha256).digest()


def _nonce(seq: int) -> bytes:
    return struct.pack(">xxxxQ", seq)


class Kind(enum.IntEnum):
    """What a frame says."""

    HELLO = 0  # client: I am listening (repeated until READY)
    READY = 1  # node: the session runs
    DATA = 2  # bytes on a channel (exec: 0 stdin, 1 stdout, 2 stderr; forward: connection)
    EOF = 3  # no more bytes from this side on a channel
    OPEN = 4  # client: open a channel (forward: JSON {"port": R, "udp": bool})
    CLOSE = 5  # a channel is gone (payload: why, may be empty)
    RESIZE = 6  # client: the terminal's size, JSON [rows, cols]
    BEAT = 7  # heartbeat
    END = 8  # node: the session is over, JSON {"code": int | null, "message": str}


@dataclass(frozen=True)
class Frame:
    """One message of a stream."""

    kind: Kind
    channel: int = 0
    data: bytes = b""


@dataclass(frozen=True)
class SessionGrant:
    """What the server grants a session: who runs it where, and its secrets.

    ``kind`` is ``exec`` (``command``, ``tty``, ``term``, ``size``) or ``forward``
    (``ports``: the task ports the client may open, ``udp``).
    """

    session_id: str
    key: bytes = field(repr=False)
    kind: str
    attempt_id: str
    command: tuple[str, ...] = ()
    tty: bool = False
    term: str = "xterm"
    size: tuple[int, int] = (24, 80)
    ports: tuple[int, ...] = ()
    udp: bool = False

    def to_dict(self) -> dict[str, Any]:
        """JSON form (for an authenticated reply only: it holds the key)."""
        return {"session_id": self.session_id, "key": self.key.hex(), "kind": self.kind,
                "attempt_id": self.attempt_id, "command": list(self.command), "tty": self.tty,
                "term": self.term, "size": list(self.size), "ports": list(self.ports),
                "udp": self.udp}

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> SessionGrant:
        """Parse and check a grant (from the server, or the client's session reply).

        Raises:
            UsageError: a field is missing or malformed.
        """
        try:
            sid, key = str(data["session_id"]), bytes.fromhex(str(data["key"]))
            command = tuple(str(w) for w in data.get("command") or ())
            rows, cols = (int(x) for x in data.get("size") or (24, 80))
            ports = tuple(int(p) for p in data.get("ports") or ())
            grant = cls(sid, key, str(data["kind"]), str(data["attempt_id"]), command,
                        bool(data.get("tty")), str(data.get("term") or "xterm")[:64],
                        (rows, cols), ports, bool(data.get("udp")))
        except (KeyError, TypeError, ValueError) as exc:
            raise UsageError(f"malformed session grant: {exc}") from None
        if (not _SESSION_ID.fullmatch(sid) or len(key) != 32
                or grant.kind not in ("exec", "forward") or len(command) > MAX_COMMAND
                or len(ports) > MAX_PORTS or not all(0 < p < 65536 for p in ports)):
            raise UsageError("malformed session grant")
        return grant


class Stream:
    """One end of a session's stream (see the module docstring).

    Args:
        link: the zenoh link.
        grant: the session (its id and key).
        side: ``client`` or ``node``.
        on_frame: called with every valid frame but heartbeats, on a zenoh thread, in order.
        on_lost: called once when the peer went silent for ``timeout`` seconds.
    """

    def __init__(self, link: Link, grant: SessionGrant, side: str,
                 on_frame: Callable[[Frame], None], on_lost: Callable[[], None], *,
                 timeout: float = TIMEOUT) -> None:
        up, down = link.key("stream", grant.session_id, "up"), \
            link.key("stream", grant.session_id, "down")
        self._link = link
        self._out, inbound = (up, down) if side == "client" else (down, up)
        keys = {up: Aead(_direction_key(grant.key, b"up")),
                down: Aead(_direction_key(grant.key, b"down"))}
        self._seal, self._open = keys[self._out], keys[inbound]
        self._dir_out, self._dir_in = self._out.encode(), inbound.encode()
        self._on_frame, self._on_lost = on_frame, on_lost
        self._timeout = timeout
        self._send_lock = threading.Lock()
        self._seq_out = 0
        self._seq_in = 0
        self._last = time.monotonic()
        self._busy = 0
        self._closed = threading.Event()
        self._sub: Subscription = link.subscribe_raw(inbound, self._on_sample)
        self._beat = threading.Thread(target=self._beats, name="osmo-stream-beat", daemon=True)
        self._beat.start()

    def send(self, kind: Kind, channel: int = 0, data: bytes | memoryview = b"") -> bool:
        """Send one frame (``data`` split into :data:`CHUNK` pieces); False once closed."""
        if isinstance(data, bytes) and len(data) <= CHUNK:
            return self._send_one(kind, channel, data)  # most socket reads: no copy
        view = memoryview(data)
        while view:
            if not self._send_one(kind, channel, bytes(view[:CHUNK])):
                return False
            view = view[CHUNK:]
        return True

    def _send_one(self, kind: Kind, channel: int, piece: bytes) -> bool:
        # numbered and put under one lock: the receiver drops any frame older than the last
        with self._send_lock:
            if self._closed.is_set():
                return False
            self._seq_out += 1
            header = _HEADER.pack(self._seq_out, kind, channel)
            sealed = self._seal.seal(_nonce(self._seq_out), piece, self._dir_out + header)
            return self._link.put(self._out, sealed, header)

    def send_json(self, kind: Kind, channel: int, value: Any) -> bool:
        """Send a frame whose payload is ``value`` as JSON."""
        return self.send(kind, channel, json.dumps(value).encode())

    def _on_sample(self, _key: str, data: bytes, attachment: bytes | None) -> None:
        if self._closed.is_set():
            return
        if attachment is None or len(attachment) != _HEADER.size:
            return self._tampered()
        seq, kind, channel = _HEADER.unpack(attachment)
        plain = self._open.open(_nonce(seq), data, self._dir_in + attachment)
        if plain is None:
            return self._tampered()  # not sealed by the session's peer: end it
        if seq <= self._seq_in or kind not in Kind._value2member_map_:
            return  # a replay, or a kind this side does not know
        data = plain
        self._seq_in = seq
        self._last = time.monotonic()
        if kind == Kind.BEAT or self._closed.is_set():
            return
        self._busy += 1
        try:
            self._on_frame(Frame(Kind(kind), channel, data))
        finally:
            self._busy -= 1
            self._last = time.monotonic()

    def _tampered(self) -> None:
        """A frame on this session's key failed its integrity check: end the session."""
        with self._send_lock:
            if self._closed.is_set():
                return
            self._closed.set()
        log.warning("a frame of stream %s failed its integrity check: ending the session",
                    self._dir_in.decode(errors="replace"))
        # not on zenoh's thread: undeclaring a subscriber from its own callback may block
        threading.Thread(target=self._end, name="osmo-stream-end", daemon=True).start()

    def _end(self) -> None:
        self._sub.close()
        self._on_lost()

    def _beats(self) -> None:
        while not self._closed.wait(BEAT_EVERY):
            self.send(Kind.BEAT)
            if not self._busy and time.monotonic() - self._last > self._timeout:
                if not self._closed.is_set():
                    self._on_lost()
                return

    def close(self) -> None:
        """Stop sending and receiving (idempotent)."""
        with self._send_lock:
            self._closed.set()
        self._sub.close()
