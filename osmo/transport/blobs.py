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

Every request carries an attachment (the asker's API token, or the key a worker's
registration handed the server); a :class:`BlobServer` answers only the requests its
``allow(attachment, digest)`` accepts, and answers the others as if the blob were missing.
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
from typing import Any

from osmo.artifacts import ArtifactStore, Manifest
from osmo.artifacts.errors import ArtifactCorrupted
from osmo.artifacts.manifest import check_digest
from osmo.config import host_id
from osmo.errors import InfrastructureError
from osmo.layout import BlobDirs
from osmo.transport.zenoh_link import Link, Request, Subscription

__all__ = ["SERVER", "BlobServer", "SameHost", "TransferError", "fetch_blob", "fetch_manifest",
           "host_id"]

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


Allow = Callable[[bytes | None, str], bool]


class BlobServer:
    """Serves ``store``'s blobs on ``<prefix>/blob/<owner>/*`` (reads on a small pool).

    ``allow(attachment, "sha256:<hex>")`` decides who may read which blob.
    """

    def __init__(self, link: Link, owner: str, store: ArtifactStore, allow: Allow, *,
                 threads: int = 4) -> None:
        self._store = store
        self._allow = allow
        self._pool = ThreadPoolExecutor(threads, thread_name_prefix="osmo-blobs")
        self._sub: Subscription = link.serve(link.key("blob", owner, "*"),
                                             lambda req: self._pool.submit(self._serve, req))

    def _serve(self, request: Request) -> None:
        hex_ = request.key.rsplit("/", 1)[1]
        try:
            if not self._allow(request.attachment, "sha256:" + hex_):
                raise InfrastructureError("not allowed")
            offset, length = (int(x) for x in request.payload.split(b":"))
            with open(self._store.path("sha256:" + hex_), "rb") as f:
                f.seek(offset)
                data = f.read(min(length, 16 * CHUNK))
        except (OSError, ValueError, InfrastructureError):
            request.reply(b"", b"missing")
            return
        request.reply(data)

    def close(self) -> None:
        """Stop serving."""
        self._sub.close()
        self._pool.shutdown(wait=False, cancel_futures=True)


def fetch_blob(link: Link, owner: str, digest: str, size: int, store: ArtifactStore, *,
               same_host: SameHost | None = None,
               on_bytes: Callable[[int], None] | None = None,
               attachment: bytes | None = None) -> int:
    """Make ``store`` hold blob ``digest`` (``size`` bytes) from ``owner``.

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
    key = link.key("blob", owner, hex_)
    with open(partial, "ab") as out:
        for data in _chunks(link, key, have, size, attachment):
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


def _chunks(link: Link, key: str, start: int, size: int,
            attachment: bytes | None) -> Iterator[bytes]:
    """Yield the bytes of ``[start, size)`` in order, ``WINDOW`` requests in flight."""
    pending: deque[tuple[int, int, Any]] = deque()
    offset = start
    while offset < size or pending:
        while offset < size and len(pending) < WINDOW:
            n = min(CHUNK, size - offset)
            pending.append((offset, n, link.ask(key, f"{offset}:{n}".encode(),
                                                attachment=attachment, timeout=_TIMEOUT)))
            offset += n
        at, n, ask = pending.popleft()
        answer = Link.answer(ask)
        if answer is None or answer[1] == b"missing":
            raise TransferError(f"{key}: no answer for bytes {at}..{at + n} "
                                "(the peer is gone or lacks the blob)")
        data = answer[0]
        if len(data) != n:
            raise TransferError(f"{key}: chunk at {at} arrived short ({len(data)} of {n} bytes)")
        yield data


def fetch_manifest(link: Link, owner: str, manifest: Manifest, store: ArtifactStore, *,
                   same_host: SameHost | None = None, attachment: bytes | None = None) -> int:
    """Fetch every blob of ``manifest`` that ``store`` lacks; return the bytes sent.

    ``attachment`` goes with every request (the owner's blob server checks it).
    """
    sent = 0
    seen: set[str] = set()
    for entry in manifest.entries:
        if entry.digest not in seen:
            seen.add(entry.digest)
            sent += fetch_blob(link, owner, entry.digest, entry.size, store,
                               same_host=same_host, attachment=attachment)
    return sent

