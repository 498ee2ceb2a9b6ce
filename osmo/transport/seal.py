"""End-to-end sealing: no message is believed because of the key it arrives on.

Any zenoh peer that reaches the router may publish, query, answer or subscribe on any key
expression, wildcards included (``osmo/local/*/w1`` reaches the subscriber of
``osmo/local/to-worker/w1``). So every message osmo acts on is sealed by its sender with an
AEAD (AES-256-GCM) under keys only the two ends hold, and opened, or dropped, by its
receiver: an order a worker obeys, a reply a client accepts, a report, a log batch, a blob
chunk. This module is the only one that imports ``cryptography``.

Keys. A token ``T`` (``osmo_...``) is known to its holder; the server stores only
``D = sha256(T)`` (``osmo.transport.auth.token_digest``). Both sides derive from ``D``
(HMAC-SHA256 with distinct labels, :class:`TokenKeys`):

- the token's **id** ``I`` (16 bytes): names the token on the wire and reveals nothing of it;
- the token's **key** ``L``: never leaves either side.

A token itself never crosses the bus, so there is nothing to harvest or replay.

Handshake (one query on ``api/hello``, in clear, :func:`hello` / :meth:`ChannelTable.accept`
/ :func:`finish`): the client sends ``I`` and a fresh nonce ``Nc``; the server, which finds
``L`` from ``I``, answers with a channel id ``C``, its own nonce ``Ns``, its signing key
``P`` (Ed25519, for broadcast notices) and ``proof = HMAC(L, I|Nc|Ns|C|P)``. Only the real
server (or the token's holder) can make that proof, so the client knows whom it talks to
before it sends anything else; an impostor's answer is dropped. Both derive the channel key
``K = HMAC(L, Nc|Ns|C)`` and from it one AES-GCM key per direction. The client proves itself
with its first sealed request (only a holder of ``L`` can seal one).

Sealed messages (:class:`Channel`). A sealed payload is the AES-GCM ciphertext; its
attachment is a 26-byte header: version, purpose, channel id, sequence number. The nonce is
(purpose, sequence number); the associated data is the header plus the zenoh key (relative to
the cluster prefix), so a sealed message cannot be moved to another key. Purposes:

- ``REQ`` client → server query (the API, blob requests); ``REP`` the server's reply,
  sealed with the request's number (a reply answers that request and no other);
- ``PUSH`` server → client put (a worker's orders);
- ``SQ`` server → client query (the server pulling a worker's outputs or an upload);
  ``SR`` the client's reply.

Messages that start an exchange (``REQ``, ``PUSH``, ``SQ``) pass a replay window of
:data:`WINDOW` numbers: a message seen before, or older than the window, is dropped. A
tampered message fails the AEAD and is dropped.

Broadcast notices (``events/<workflow>``) are signed with the server's Ed25519 key
(:class:`Signer`), which clients learn in the handshake; a peer cannot forge one.

What a peer on the bus still sees: which keys carry traffic (verb names, workflow ids in
notice keys, worker names, blob digests), sizes and timing. What it cannot do: read a body,
a token, a secret or a blob, or make any side act on a message of its own.
"""

from __future__ import annotations

import enum
import hashlib
import hmac
import json
import os
import secrets
import struct
import threading
import time
from collections import OrderedDict
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from cryptography.exceptions import InvalidSignature, InvalidTag
from cryptography.hazmat.primitives import serialization
from cryptography.hazmat.primitives.asymmetric.ed25519 import Ed25519PrivateKey, Ed25519PublicKey
from cryptography.hazmat.primitives.ciphers.aead import AESGCM

__all__ = ["HEADER", "WINDOW", "Aead", "Channel", "ChannelTable", "Handshake", "HelloError",
           "Purpose", "ReplayWindow", "Signer", "TokenKeys", "Verifier", "finish", "hello",
           "parse_header", "seal_json"]

VERSION = 1
HEADER = struct.Struct(">BB16sQ")
"""A sealed message's attachment: version, purpose, channel id, sequence number."""
WINDOW = 4096
"""Sequence numbers a receiver remembers (messages may arrive out of order: threads)."""
_ID = 16


class Purpose(enum.IntEnum):
    """What a sealed message is (see the module docstring)."""

    REQ = 1
    REP = 2
    PUSH = 3
    SQ = 4
    SR = 5


_FROM_CLIENT = frozenset({Purpose.REQ, Purpose.SR})


def _mac(key: bytes, label: bytes, *parts: bytes) -> bytes:
    h = hmac.new(key, label, hashlib.sha256)
    for part in parts:
        h.update(struct.pack(">I", len(part)))
        h.update(part)
    return h.digest()


@dataclass(frozen=True)
class TokenKeys:
    """What both ends derive from a token's digest: its public id and its secret key."""

    id: bytes
    key: bytes

    @classmethod
    def from_digest(cls, digest_hex: str) -> TokenKeys:
        """The keys of the token whose sha256 is ``digest_hex`` (what the server stores)."""
        d = bytes.fromhex(digest_hex)
        return cls(_mac(d, b"osmo token id v1")[:_ID], _mac(d, b"osmo token key v1"))

    @classmethod
    def from_token(cls, token: str | bytes) -> TokenKeys:
        """The keys of ``token`` (what its holder derives)."""
        raw = token.encode() if isinstance(token, str) else token
        return cls.from_digest(hashlib.sha256(raw.strip()).hexdigest())


class Aead:
    """AES-256-GCM under one key; nonces are the caller's (never reuse one per key)."""

    def __init__(self, key: bytes) -> None:
        self._aes = AESGCM(key)

    def seal(self, nonce: bytes, data: bytes, aad: bytes) -> bytes:
        """Encrypt and authenticate ``data`` (the tag is appended)."""
        return self._aes.encrypt(nonce, data, aad)

    def open(self, nonce: bytes, data: bytes, aad: bytes) -> bytes | None:
        """The plaintext, or None when ``data`` was not sealed under this key and ``aad``."""
        try:
            return self._aes.decrypt(nonce, data, aad)
        except (InvalidTag, ValueError):
            return None


class ReplayWindow:
    """Accepts each sequence number once, within the newest :data:`WINDOW` (thread-safe)."""

    def __init__(self, size: int = WINDOW) -> None:
        self._size = size
        self._top = 0
        self._seen = 0  # bit i: number top - i was accepted
        self._lock = threading.Lock()

    def accept(self, seq: int) -> bool:
        """True the first time ``seq`` is offered (and it is not too old)."""
        with self._lock:
            if seq > self._top:
                shift = seq - self._top
                self._seen = (((self._seen << shift) | 1) & ((1 << self._size) - 1)
                              if shift < self._size else 1)
                self._top = seq
                return True
            back = self._top - seq
            if back >= self._size or self._seen >> back & 1:
                return False
            self._seen |= 1 << back
            return True


def _nonce(purpose: Purpose, seq: int) -> bytes:
    return struct.pack(">BxxxQ", purpose, seq)


class Channel:
    """One end of an established channel: seals what it sends, opens what it receives.

    Args:
        cid: the channel id (16 bytes).
        key: the channel key ``K``.
        side: ``client`` (the token's holder) or ``server``.
    """

    def __init__(self, cid: bytes, key: bytes, side: str) -> None:
        self.id = cid
        c2s, s2c = Aead(_mac(key, b"c2s")), Aead(_mac(key, b"s2c"))
        self._out, self._in = (c2s, s2c) if side == "client" else (s2c, c2s)
        self._sends = {p for p in Purpose if (p in _FROM_CLIENT) == (side == "client")}
        self._count = 0
        self._lock = threading.Lock()
        self._windows = {p: ReplayWindow() for p in (Purpose.REQ, Purpose.PUSH, Purpose.SQ)
                         if p not in self._sends}
        self.used = time.monotonic()

    def next_seq(self) -> int:
        """A fresh sequence number for a message this side starts."""
        with self._lock:
            self._count += 1
            return self._count

    def seal(self, purpose: Purpose, key: str, data: bytes, seq: int | None = None
             ) -> tuple[bytes, bytes]:
        """``(attachment, payload)`` of ``data`` sealed for zenoh key ``key``.

        ``seq``: the number of the message answered (``REP``, ``SR``); a fresh one otherwise.
        """
        if purpose not in self._sends:
            raise ValueError(f"this side does not send {purpose.name}")
        if seq is None:
            seq = self.next_seq()
        header = HEADER.pack(VERSION, purpose, self.id, seq)
        return header, self._out.seal(_nonce(purpose, seq), data, header + key.encode())

    def open(self, purpose: Purpose, key: str, attachment: bytes | None, data: bytes, *,
             seq: int | None = None) -> tuple[int, bytes] | None:
        """``(seq, plaintext)`` of a message sealed by the other end, or None.

        None: not sealed on this channel for ``purpose`` and ``key``, tampered, replayed, or
        (a reply) not the answer to message ``seq``.
        """
        head = parse_header(attachment)
        if head is None or head[0] != purpose or head[1] != self.id:
            return None
        got = head[2]
        if seq is not None and got != seq:
            return None
        plain = self._in.open(_nonce(purpose, got), data, bytes(attachment or b"") + key.encode())
        if plain is None:
            return None
        window = self._windows.get(purpose)
        if window is not None and not window.accept(got):
            return None
        self.used = time.monotonic()
        return got, plain


def parse_header(attachment: bytes | None) -> tuple[Purpose, bytes, int] | None:
    """``(purpose, channel id, seq)`` of a sealed message's attachment, or None."""
    if attachment is None or len(attachment) != HEADER.size:
        return None
    version, purpose, cid, seq = HEADER.unpack(attachment)
    if version != VERSION or purpose not in Purpose._value2member_map_:
        return None
    return Purpose(purpose), cid, seq


# ---------------------------------------------------------------------- handshake


@dataclass(frozen=True)
class Handshake:
    """A client's half-done handshake: what it sent, to check the server's answer."""

    keys: TokenKeys
    nonce: bytes

    def request(self) -> bytes:
        """The ``api/hello`` query's payload."""
        return json.dumps({"v": VERSION, "id": self.keys.id.hex(),
                           "nonce": self.nonce.hex()}).encode()


def hello(token: str | bytes) -> Handshake:
    """Start a handshake for ``token``."""
    return Handshake(TokenKeys.from_token(token), secrets.token_bytes(16))


def _proof(keys: TokenKeys, nc: bytes, ns: bytes, cid: bytes, sign_key: bytes) -> bytes:
    return _mac(keys.key, b"osmo hello v1", keys.id, nc, ns, cid, sign_key)


def _channel_key(keys: TokenKeys, nc: bytes, ns: bytes, cid: bytes) -> bytes:
    return _mac(keys.key, b"osmo channel v1", nc, ns, cid)


def finish(shake: Handshake, reply: bytes) -> tuple[Channel, Verifier] | None:
    """The channel and the server's notice verifier, if ``reply`` is the real server's answer.

    None: anything else (an impostor's answer, garbage, an error).
    """
    try:
        body = json.loads(reply)
        cid, ns = bytes.fromhex(body["channel"]), bytes.fromhex(body["nonce"])
        proof, sign_key = bytes.fromhex(body["proof"]), bytes.fromhex(body["sign_key"])
    except (ValueError, KeyError, TypeError):
        return None
    if len(cid) != _ID or not hmac.compare_digest(
            proof, _proof(shake.keys, shake.nonce, ns, cid, sign_key)):
        return None
    try:
        verifier = Verifier(sign_key)
    except ValueError:
        return None
    return Channel(cid, _channel_key(shake.keys, shake.nonce, ns, cid), "client"), verifier


class HelloError(Exception):
    """A hello the server cannot answer (malformed, or for a token it does not know)."""


@dataclass
class _Entry:
    channel: Channel
    digest: str


class ChannelTable:
    """The server's open channels, by id (thread-safe, bounded: least recently used go).

    Args:
        lookup: token id → the digest of the live token with that id (None: none).
        signer: the server's notice signer (its public key goes into every handshake).
        limit: most channels kept; per_token: most channels one token holds.
    """

    def __init__(self, lookup: Callable[[bytes], str | None], signer: Signer, *,
                 limit: int = 1 << 15, per_token: int = 1024) -> None:
        self._lookup, self.signer = lookup, signer
        self._limit, self._per_token = limit, per_token
        self._lock = threading.Lock()
        self._entries: OrderedDict[bytes, _Entry] = OrderedDict()
        self._count: dict[str, int] = {}

    def accept(self, payload: bytes) -> bytes:
        """Answer a client's hello (the reply's payload) and open its channel.

        Raises:
            HelloError: a malformed hello, or a token this server does not know.
        """
        try:
            body = json.loads(payload)
            tid, nc = bytes.fromhex(body["id"]), bytes.fromhex(body["nonce"])
        except (ValueError, KeyError, TypeError):
            raise HelloError("malformed hello") from None
        if body.get("v") != VERSION or len(tid) != _ID or len(nc) != 16:
            raise HelloError("malformed hello (or another version of osmo)")
        digest = self._lookup(tid)
        if digest is None:
            raise HelloError("unknown token")
        keys = TokenKeys.from_digest(digest)
        cid, ns = secrets.token_bytes(_ID), secrets.token_bytes(16)
        channel = Channel(cid, _channel_key(keys, nc, ns, cid), "server")
        self._add(cid, _Entry(channel, digest))
        sign_key = self.signer.public
        return json.dumps({"v": VERSION, "channel": cid.hex(), "nonce": ns.hex(),
                           "sign_key": sign_key.hex(),
                           "proof": _proof(keys, nc, ns, cid, sign_key).hex()}).encode()

    def _add(self, cid: bytes, entry: _Entry) -> None:
        with self._lock:
            if self._count.get(entry.digest, 0) >= self._per_token:
                old = next(c for c, e in self._entries.items() if e.digest == entry.digest)
                self._drop(old)
            while len(self._entries) >= self._limit:
                self._drop(next(iter(self._entries)))
            self._entries[cid] = entry
            self._count[entry.digest] = self._count.get(entry.digest, 0) + 1

    def _drop(self, cid: bytes) -> None:
        entry = self._entries.pop(cid)
        left = self._count[entry.digest] - 1
        if left:
            self._count[entry.digest] = left
        else:
            del self._count[entry.digest]

    def get(self, cid: bytes) -> tuple[Channel, str] | None:
        """The channel with id ``cid`` and its token's digest (None: unknown or dropped)."""
        with self._lock:
            entry = self._entries.get(cid)
            if entry is None:
                return None
            self._entries.move_to_end(cid)
            return entry.channel, entry.digest

    def open(self, purpose: Purpose, key: str, attachment: bytes | None, data: bytes, *,
             seq: int | None = None) -> tuple[Channel, str, int, bytes] | None:
        """Open a message sealed on one of the table's channels.

        Returns ``(channel, token digest, seq, plaintext)``, or None.
        """
        head = parse_header(attachment)
        found = self.get(head[1]) if head is not None else None
        if found is None:
            return None
        opened = found[0].open(purpose, key, attachment, data, seq=seq)
        if opened is None:
            return None
        return found[0], found[1], opened[0], opened[1]

    def revoke(self, digest: str) -> None:
        """Close every channel of the token with ``digest``."""
        with self._lock:
            for cid in [c for c, e in self._entries.items() if e.digest == digest]:
                self._drop(cid)


# ---------------------------------------------------------------------- notices


class Signer:
    """The server's Ed25519 key for broadcast notices, kept in a 0600 file across restarts."""

    def __init__(self, path: Path | None = None) -> None:
        self._key = _load_or_make(path) if path is not None else Ed25519PrivateKey.generate()
        self.public = self._key.public_key().public_bytes(serialization.Encoding.Raw,
                                                          serialization.PublicFormat.Raw)

    def sign_notice(self, key: str, payload: bytes) -> bytes:
        """The 64-byte signature of a notice put on zenoh key ``key`` (its attachment)."""
        return self._key.sign(_notice(key, payload))


class Verifier:
    """Checks the server's notice signatures (its public key from the handshake)."""

    def __init__(self, public: bytes) -> None:
        self.public = public
        self._key = Ed25519PublicKey.from_public_bytes(public)

    def notice(self, key: str, payload: bytes, signature: bytes | None) -> bool:
        """True if ``signature`` is the server's over the notice ``payload`` on ``key``."""
        if signature is None:
            return False
        try:
            self._key.verify(signature, _notice(key, payload))
        except (InvalidSignature, ValueError):
            return False
        return True


def _notice(key: str, payload: bytes) -> bytes:
    return key.encode() + b"\0" + payload


def _load_or_make(path: Path) -> Ed25519PrivateKey:
    try:
        return Ed25519PrivateKey.from_private_bytes(path.read_bytes())
    except (FileNotFoundError, ValueError):
        pass
    key = Ed25519PrivateKey.generate()
    raw = key.private_bytes(serialization.Encoding.Raw, serialization.PrivateFormat.Raw,
                            serialization.NoEncryption())
    tmp = path.with_name(f".{path.name}.{os.getpid()}")
    fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_TRUNC | os.O_CLOEXEC, 0o600)
    with os.fdopen(fd, "wb") as f:
        f.write(raw)
    os.replace(tmp, path)
    return key


def seal_json(channel: Channel, purpose: Purpose, key: str, value: Any,
              seq: int | None = None) -> tuple[bytes, bytes]:
    """:meth:`Channel.seal` of ``value`` as JSON."""
    return channel.seal(purpose, key, json.dumps(value).encode(), seq)
