"""Artifact blobs between machines: served by digest in chunks, fetched verified and resumable.

Each side that holds blobs (the server, every remote worker) serves its
:class:`~osmo.artifacts.ArtifactStore` on ``osmo/<cluster>/blob/<owner>/<hex digest>``. A
request's payload is ``b"<offset>:<length>"``; the reply is those bytes (or an empty reply
with attachment ``b"missing"`` when the blob is not there).

:func:`fetch_blob` asks for a blob chunk by chunk with several requests in flight, hashing
the bytes as they arrive in order; the whole file must hash to its digest before it is
published into the receiving store (``adopt``): a blob is never visible half-written or
unverified. (Hashing every chunk a second time on both sides, measured, cost about 40% of
the throughput for no extra safety: a damaged chunk already fails the blob's digest.)
The bytes received so far stay in the store's ``tmp`` folder, so a fetch cut off by a
lost peer resumes where it stopped next time. A blob the receiver already has is not
fetched at all; one that lies in the sender's store on the same host and
filesystem is hard-linked instead of sent (:class:`SameHost`) — after the linked file was
hashed: a same-host peer's file is trusted no more than its bytes would be.

Every request and every reply is sealed (``osmo.transport.seal``): a client or worker asks
the server's blobs on its API channel (``REQ``/``REP``, through an :class:`Asker` such as
``osmo.transport.rpc.ApiClient``), the server asks a worker's (or an upload's) on the
channel that worker opened (``SQ``/``SR``, ``osmo.transport.rpc.ServerAsker``). A
:class:`BlobServer` answers only requests its :data:`Opener` can open and its ``allow``
accepts for the caller, and answers the others as if the blob were missing; an asker takes
only replies sealed for its request, so a peer that answers in the owner's place is not
believed (and cannot make a transfer fail: the real answer still counts).
"""

from __future__ import annotations

import hashlib
import os
import uuid
from collections import deque
from collections.abc import Callable, Iterator
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Protocol

from osmo.artifacts import ArtifactStore, Manifest
from osmo.artifacts.errors import ArtifactCorrupted
from osmo.artifacts.manifest import check_digest
from osmo.config import host_id
from osmo.errors import InfrastructureError
from osmo.layout import BlobDirs
from osmo.transport.auth import Identity
from osmo.transport.zenoh_link import Link, Request, Subscription

__all__ = ["SERVER", "Allow", "Asker", "BlobServer", "Opener", "SameHost", "Sealer",
           "TransferError", "fetch_blob", "fetch_manifest", "host_id"]

CHUNK = 512 << 10
WINDOW = 16  # chunks in flight per blob
_TIMEOUT = 30.0

SERVER = "server"
"""The owner name the server serves its blobs as (no worker or client may take it)."""


class TransferError(InfrastructureError):
    """A blob could not be fetched (the peer is gone, or sent something else)."""


@dataclass(frozen=True)
class SameHost:
    """The sender's store when it lies on this host: blobs are linked from ``root``."""

    root: Path

    def blob(self, digest: str) -> Path:
        """Where the sender keeps ``digest``."""
        return BlobDirs(self.root).blob(check_digest(digest))


Sealer = Callable[[bytes], tuple[bytes, bytes]]
"""Seals a reply to one opened request: ``data -> (attachment, payload)``."""
Opener = Callable[[str, bytes | None, bytes], tuple[Identity | None, bytes, Sealer] | None]
"""``(key, attachment, payload) -> (caller, request, sealer)`` of a sealed request; None: not
one this side can open (``osmo.transport.rpc``)."""
Allow = Callable[[Identity | None, str], bool]
"""``(caller, "sha256:<hex>") -> may it read that blob``."""


class Asker(Protocol):
    """Sends sealed queries and takes only their sealed answers (``osmo.transport.rpc``)."""

    def ask(self, rel: str, payload: bytes, *, timeout: float | None = None) -> Any:
        """Send ``payload`` sealed to ``rel`` (under the cluster prefix); a pending answer."""

    def answer(self, pending: Any) -> tuple[bool, bytes] | None:
        """``(sealed, payload)`` of the answer, None if nobody answered in time."""


_OK, _MISSING = b"\x00", b"\x01"


class BlobServer:
    """Serves ``store``'s blobs on ``<prefix>/blob/<owner>/*`` (reads on a small pool).

    ``opener`` opens each sealed request; ``allow(caller, "sha256:<hex>")`` decides who may
    read which blob (default: whoever ``opener`` accepts).
    """

    def __init__(self, link: Link, owner: str, store: ArtifactStore, opener: Opener,
                 allow: Allow | None = None, *, threads: int = 4) -> None:
        self._store = store
        self._opener, self._allow = opener, allow
        self._cut = len(link.prefix) + 1
        self._pool = ThreadPoolExecutor(threads, thread_name_prefix="osmo-blobs")
        self._sub: Subscription = link.serve(link.key("blob", owner, "*"),
                                             lambda req: self._pool.submit(self._serve, req))

    def _serve(self, request: Request) -> None:
        rel = request.key[self._cut:]
        opened = self._opener(rel, request.attachment, request.payload)
        if opened is None:
            request.reply(b"", b"missing")  # not sealed for this side: as if not here
            return
        who, body, seal = opened
        digest = "sha256:" + rel.rsplit("/", 1)[1]
        try:
            if self._allow is not None and not self._allow(who, digest):
                raise InfrastructureError("not allowed")
            offset, length = (int(x) for x in body.split(b":"))
            with open(self._store.path(digest), "rb") as f:
                f.seek(offset)
                data = _OK + f.read(min(length, 16 * CHUNK))
        except (OSError, ValueError, InfrastructureError):
            data = _MISSING
        attachment, payload = seal(data)
        request.reply(payload, attachment)

    def close(self) -> None:
        """Stop serving."""
        self._sub.close()
        self._pool.shutdown(wait=False, cancel_futures=True)


def fetch_blob(asker: Asker, owner: str, digest: str, size: int, store: ArtifactStore, *,
               same_host: SameHost | None = None,
               on_bytes: Callable[[int], None] | None = None) -> int:
    """Make ``store`` hold blob ``digest`` (``size`` bytes) from ``owner``, through ``asker``.

    Returns the bytes sent over the network (0 when it was there already or linked on the same
    host).

    Raises:
        TransferError: the owner did not answer, lacks the blob, or sent bytes that do not
            match (what arrived intact is kept for the next attempt).
    """
    if store.has(digest):
        return 0
    if same_host is not None and _adopt_checked(store, same_host.blob(digest), digest):
        return 0
    hex_ = check_digest(digest)
    partial = store.tmp / f"{hex_}.partial"
    h = hashlib.sha256()
    have = _resume(partial, h)
    key = f"blob/{owner}/{hex_}"
    with open(partial, "ab") as out:
        for data in _chunks(asker, key, have, size):
            h.update(data)
            out.write(data)
            if on_bytes is not None:
                on_bytes(len(data))
    if "sha256:" + h.hexdigest() != digest:
        partial.unlink(missing_ok=True)
        raise TransferError(f"blob {digest} from {owner} does not match its digest; "
                            "it will be fetched again")
    store.adopt(partial, digest)
    return size - have


def _adopt_checked(store: ArtifactStore, src: Path, digest: str) -> bool:
    """Hard-link a same-host peer's blob into ``store`` if its bytes hash to ``digest``.

    The file is linked into ``store.tmp`` first and that inode is hashed, so what was checked
    is what is kept. False when it cannot be linked (the caller fetches it).

    Raises:
        ArtifactCorrupted: the peer's blob does not hash to ``digest`` (it serves the same
            bytes over the network: fetching them would not help).
    """
    hex_ = check_digest(digest)
    tmp = store.tmp / f"{hex_}.{uuid.uuid4().hex}.adopt"
    try:
        store.tmp.mkdir(parents=True, exist_ok=True)
        os.link(src, tmp)
    except OSError:
        return False
    try:
        h = hashlib.sha256()
        with open(tmp, "rb") as f:
            while data := f.read(CHUNK):
                h.update(data)
        if h.hexdigest() != hex_:
            raise ArtifactCorrupted(digest, str(src), "sha256:" + h.hexdigest())
        return store.adopt_link(tmp, digest)
    except OSError:
        return False
    finally:
        tmp.unlink(missing_ok=True)


def _resume(partial: Path, h: Any) -> int:
    """Hash what an earlier, cut-off fetch left in ``partial``; return its length."""
    try:
        with open(partial, "rb") as f:
            while data := f.read(CHUNK):
                h.update(data)
            return f.tell()
    except FileNotFoundError:
        return 0


def _chunks(asker: Asker, key: str, start: int, size: int) -> Iterator[bytes]:
    """Yield the bytes of ``[start, size)`` in order, ``WINDOW`` requests in flight."""
    pending: deque[tuple[int, int, Any]] = deque()
    offset = start
    while offset < size or pending:
        while offset < size and len(pending) < WINDOW:
            n = min(CHUNK, size - offset)
            pending.append((offset, n, asker.ask(key, f"{offset}:{n}".encode(),
                                                 timeout=_TIMEOUT)))
            offset += n
        at, n, ask = pending.popleft()
        answer = asker.answer(ask)
        if answer is None or not answer[0] or answer[1][:1] != _OK:
            raise TransferError(f"{key}: no answer for bytes {at}..{at + n} "
                                "(the peer is gone or lacks the blob)")
        data = answer[1][1:]
        if len(data) != n:
            raise TransferError(f"{key}: chunk at {at} arrived short ({len(data)} of {n} bytes)")
        yield data


def fetch_manifest(asker: Asker, owner: str, manifest: Manifest, store: ArtifactStore, *,
                   same_host: SameHost | None = None) -> int:
    """Fetch every blob of ``manifest`` that ``store`` lacks; return the bytes sent."""
    sent = 0
    seen: set[str] = set()
    for entry in manifest.entries:
        if entry.digest not in seen:
            seen.add(entry.digest)
            sent += fetch_blob(asker, owner, entry.digest, entry.size, store,
                               same_host=same_host)
    return sent

