"""The node's side of its pods' data: inputs to a pod's init container, outputs from its collector.

A pod does not see the node's folders (no shared volume): its init container fetches what the
task must find (inputs, ``files:``, the working folder) into the pod's own ``emptyDir``, and
its collector sends the task's output back once the task's container has ended. Both speak to
the node over zenoh (``osmo.runtime.kubernetes.podside`` is their side), on a small API of the
node's own, ``<prefix>/podio/<node>/<verb>`` (``osmo.transport.rpc.ApiServer``), sealed end
to end (``osmo.transport.seal``).

Tickets. Each attempt gets two one-time tickets (random tokens), one for its init container
(``fetch``) and one for its collector (``collect``), handed over in the attempt's own Secret,
which only those two containers mount (never the task's container, never its spec or env).
A ticket opens exactly one channel: its first hello spends it, so a ticket read later
(replayed) opens nothing. A channel acts for its own attempt and role only: every request
names the attempt, and one that names another attempt is refused, whatever its ticket.
A restarted node that adopts a pod (``KubernetesRuntime.adopt``) serves its collector again
from the ticket's digest it journaled (:meth:`PodData.reopen`): the ticket then opens one
channel once more, in the node's new life (the previous life's channels died with it).

What each side may do:

- ``fetch``: ``manifest`` (the attempt's files: relative path in the pod's data volume,
  size, sha256, mode; and its folders), ``read`` (a chunk of the N-th file), ``fetched``,
  ``failed`` (the init container says why it gave up: a file that did not match its digest).
  Nothing else on the node can be named: files are asked for by their index in the
  attempt's own list.
- ``collect``: ``wait`` (answers once the node saw the task's container end, from the API:
  the exit code is the kubelet's, never the pod's word), ``offer`` (the output's file list:
  relative paths and sizes; refused whole when a path is absolute, holds ``..``, ``.`` or an
  empty part, a file is also a folder, there are more than the files allowed, or the sizes
  add up to more than the task's ``storage``), ``put`` (the next bytes of the N-th file, in
  order, never beyond its offered size), ``done`` (every file's sha256: each must match what
  arrived), ``failed``. Files are written only by the node, under the attempt's
  ``output.partial`` (no name the pod sends can make it write elsewhere: folders are made by
  the node, files created exclusively without following symlinks). The node promotes that
  folder only after a complete collection and a successful exit, as on every node.

Must not: serve anything outside an attempt's list, write outside its output folder, or
believe an unsealed request. The runtime (``osmo.runtime.kubernetes.runtime``) opens an
attempt here before its pod is made and closes it when the attempt ends.
"""

from __future__ import annotations

import base64
import hashlib
import os
import stat
import threading
from collections.abc import Iterable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from osmo.artifacts.fsops import hash_fd
from osmo.artifacts.store import DEFAULT_MAX_FILES
from osmo.errors import NotAllowed, NotAuthenticated, UsageError
from osmo.transport.auth import Identity, Role, new_token, token_digest
from osmo.transport.rpc import ApiServer
from osmo.transport.rpc import field as req_field
from osmo.transport.seal import ChannelTable, Signer, TokenKeys
from osmo.transport.zenoh_link import Link

__all__ = ["CHUNK", "COLLECT", "FETCH", "SEALED", "PodData", "PodFile", "root_of", "scan_mounts",
           "ticket_seal"]

FETCH = "fetch"
COLLECT = "collect"
CHUNK = 256 << 10
"""Bytes per ``read``/``put`` (base64 in JSON: a third more on the wire)."""
WAIT = 5.0
"""Seconds one ``wait`` is held before it answers that the task still runs."""
SEALED = "osmo.dev/collect-ticket"
"""The annotation of a data pod that binds its collector's ticket (:func:`ticket_seal`)."""
_MAX_PATH = 4096


def ticket_seal(attempt_id: str, digest: str) -> str:
    """What binds a collector's ticket to its attempt: the pod's annotation :data:`SEALED`.

    The hash of the attempt id and the ticket's digest (itself no key: the digest cannot be
    found from it). A restarted node adopts a data pod only when its journaled digest gives
    the pod's annotation, which the API holds and the pod cannot change. 160 bits: podman
    refuses annotation values past 63 characters.
    """
    seal = hashlib.sha256(f"osmo podio ticket v1\0{attempt_id}\0{digest}".encode())
    return seal.hexdigest()[:40]


def root_of(node: str) -> str:
    """The key (under the cluster's prefix) of ``node``'s pod-data API."""
    return f"podio/{node}"


@dataclass(frozen=True)
class PodFile:
    """One file an init container fetches: its path in the pod's data volume, its source."""

    path: str
    source: Path
    size: int
    digest: str
    mode: int


@dataclass
class _Attempt:
    """What the node holds for one attempt's pod."""

    attempt_id: str
    files: tuple[PodFile, ...]
    dirs: tuple[str, ...]
    output: Path
    max_bytes: int | None
    max_files: int
    ended: threading.Event = field(default_factory=threading.Event)
    collect: bool = False
    finished: threading.Event = field(default_factory=threading.Event)
    outcome: str | None = None  # None: collected; else why not
    fetch_failure: str | None = None
    offered: list[tuple[str, int]] = field(default_factory=list)
    received: list[int] = field(default_factory=list)
    hashes: list[Any] = field(default_factory=list)
    lock: threading.RLock = field(default_factory=threading.RLock)


@dataclass(frozen=True)
class _Holder:
    attempt_id: str
    role: str


class PodData:
    """The node's pod-data API (see the module docstring).

    Args:
        link: the node's zenoh link.
        node: the node's name (its key: ``podio/<node>``).
        threads: requests served at once (a collector's ``wait`` holds one up to
            :data:`WAIT` seconds).
    """

    def __init__(self, link: Link, node: str, *, threads: int = 32) -> None:
        self.root = root_of(node)
        self._lock = threading.Lock()
        self._tickets: dict[bytes, str] = {}  # unspent ticket id → its digest
        self._holders: dict[str, _Holder] = {}  # ticket digest → what it acts for
        self._attempts: dict[str, _Attempt] = {}
        self.channels = ChannelTable(self._spend, Signer())
        self._api = ApiServer(link, self._handle, self, threads=threads, root=self.root)

    # ------------------------------------------------------------ the runtime's side

    def open(self, attempt_id: str, files: Iterable[PodFile], dirs: Iterable[str],
             output: Path, *, max_bytes: int | None = None,
             max_files: int = DEFAULT_MAX_FILES) -> dict[str, str]:
        """Serve ``attempt_id``'s pod; its two tickets (role → token) for its Secret."""
        entry = _Attempt(attempt_id, tuple(files), tuple(dirs), output, max_bytes, max_files)
        tickets = {FETCH: new_token(), COLLECT: new_token()}
        self._serve(entry, {role: token_digest(token) for role, token in tickets.items()})
        return tickets

    def reopen(self, attempt_id: str, collect: str, output: Path, *,
               max_bytes: int | None = None, max_files: int = DEFAULT_MAX_FILES) -> None:
        """Serve again the collector of a pod a previous life of the node opened.

        ``collect`` is its ticket's digest (what the node journaled, never the ticket): the
        ticket opens one channel again, in this life. ``output`` must be empty: whatever the
        collector sent the previous life is sent again, whole. Its init container's ticket
        opens nothing: the node adopts only a pod whose fetch was done.
        """
        self._serve(_Attempt(attempt_id, (), (), output, max_bytes, max_files),
                    {COLLECT: collect})

    def _serve(self, entry: _Attempt, digests: dict[str, str]) -> None:
        """Serve ``entry``; each role's ticket (by its digest) opens one channel for it."""
        with self._lock:
            self._attempts[entry.attempt_id] = entry
            for role, digest in digests.items():
                self._tickets[TokenKeys.from_digest(digest).id] = digest
                self._holders[digest] = _Holder(entry.attempt_id, role)

    def ended(self, attempt_id: str, *, collect: bool) -> None:
        """The task's container ended (``collect``: take its output; else hand nothing)."""
        entry = self._get(attempt_id)
        if entry is not None:
            entry.collect = collect
            entry.ended.set()
            if not collect:
                self._finish(entry, "the task did not end in a way that hands outputs on")

    def collected(self, attempt_id: str, timeout: float) -> str | None:
        """Wait for the collection: None when every file arrived whole, else why not."""
        entry = self._get(attempt_id)
        if entry is None:
            return "the attempt is not served here"
        if not entry.finished.wait(timeout):
            self._finish(entry, f"the collector sent no complete output within {timeout:g} s")
        return entry.outcome

    def fetch_failure(self, attempt_id: str) -> str | None:
        """What the attempt's init container reported when it gave up (None: nothing)."""
        entry = self._get(attempt_id)
        return entry.fetch_failure if entry is not None else None

    def close(self, attempt_id: str) -> None:
        """Forget the attempt: its tickets and channels open nothing any more."""
        with self._lock:
            entry = self._attempts.pop(attempt_id, None)
            gone = [d for d, h in self._holders.items() if h.attempt_id == attempt_id]
            for digest in gone:
                del self._holders[digest]
                self._tickets.pop(TokenKeys.from_digest(digest).id, None)
        for digest in gone:
            self.channels.revoke(digest)
        if entry is not None:
            self._finish(entry, "the attempt ended before its output was collected")

    def stop(self) -> None:
        """Stop serving."""
        self._api.close()

    # ------------------------------------------------------------ the gate (rpc.Gate)

    def _spend(self, ticket_id: bytes) -> str | None:
        """A hello's ticket: its digest the first time, never again (one-time)."""
        with self._lock:
            return self._tickets.pop(ticket_id, None)

    def identity(self, digest: str, channel: bytes) -> Identity:
        """The holder of the ticket ``digest``, while its attempt is served.

        Raises:
            NotAuthenticated: the attempt is no longer served here.
        """
        with self._lock:
            holder = self._holders.get(digest)
        if holder is None:
            raise NotAuthenticated("this pod's ticket is no longer valid (its attempt ended)")
        return Identity(digest, Role.WORKER, channel)

    # ------------------------------------------------------------ requests

    def _get(self, attempt_id: str) -> _Attempt | None:
        with self._lock:
            return self._attempts.get(attempt_id)

    def _handle(self, verb: str, request: dict[str, Any], who: Identity) -> Any:
        with self._lock:
            holder = self._holders.get(who.name)
        if holder is None:
            raise NotAuthenticated("this pod's ticket is no longer valid (its attempt ended)")
        named = req_field(request, "attempt", str, max_len=512)
        if named != holder.attempt_id:
            raise NotAllowed(f"this ticket is for attempt {holder.attempt_id}, not {named}")
        entry = self._get(holder.attempt_id)
        if entry is None:
            raise NotAuthenticated("the attempt is no longer served here")
        handler = _VERBS.get((holder.role, verb))
        if handler is None:
            raise NotAllowed(f"a {holder.role} ticket may not ask {verb!r}")
        return handler(self, entry, request)

    def _manifest(self, entry: _Attempt, _request: dict[str, Any]) -> Any:
        return {"dirs": list(entry.dirs),
                "files": [{"path": f.path, "size": f.size, "digest": f.digest, "mode": f.mode}
                          for f in entry.files]}

    def _read(self, entry: _Attempt, request: dict[str, Any]) -> Any:
        index = req_field(request, "index", int)
        offset = req_field(request, "offset", int)
        if not 0 <= index < len(entry.files) or offset < 0:
            raise UsageError("no such file or offset")
        with open(entry.files[index].source, "rb") as f:
            f.seek(offset)
            data = f.read(CHUNK)
        return {"data": base64.b64encode(data).decode()}

    def _fetched(self, entry: _Attempt, _request: dict[str, Any]) -> Any:
        return {}

    def _failed(self, entry: _Attempt, request: dict[str, Any]) -> Any:
        message = req_field(request, "message", str, max_len=2000)
        if entry.ended.is_set():
            self._finish(entry, f"the collector failed: {message}")
        else:
            entry.fetch_failure = message
        return {}

    def _wait(self, entry: _Attempt, _request: dict[str, Any]) -> Any:
        ended = entry.ended.wait(WAIT)
        return {"ended": ended, "collect": ended and entry.collect}

    def _offer(self, entry: _Attempt, request: dict[str, Any]) -> Any:
        if not entry.ended.is_set() or not entry.collect:
            raise NotAllowed("outputs are taken only after the task's container ended")
        files = req_field(request, "files", list)
        try:
            offered = _checked_offer(files, entry.max_bytes, entry.max_files)
            with entry.lock:
                if entry.offered:
                    raise NotAllowed("the output was offered already")
                for name, _size in offered:
                    _make_parents(entry.output, name)
                entry.offered = offered
                entry.received = [0] * len(offered)
                entry.hashes = [hashlib.sha256() for _ in offered]
        except (UsageError, NotAllowed, OSError) as exc:
            why = exc.strerror if isinstance(exc, OSError) else str(exc)
            self._finish(entry, f"the output was refused: {why}")
            raise UsageError(f"the output was refused: {why}") from None
        return {}

    def _put(self, entry: _Attempt, request: dict[str, Any]) -> Any:
        index = req_field(request, "index", int)
        offset = req_field(request, "offset", int)
        data = base64.b64decode(req_field(request, "data", str, max_len=2 * CHUNK))
        with entry.lock:
            if entry.finished.is_set() or not 0 <= index < len(entry.offered):
                raise NotAllowed("no such offered file (or the collection is over)")
            name, size = entry.offered[index]
            if offset != entry.received[index] or offset + len(data) > size:
                self._finish(entry, f"the output was refused: {name!r} got bytes out of "
                             "order or beyond its offered size")
                raise UsageError("bytes out of order or beyond the offered size")
            flags = os.O_WRONLY | os.O_CREAT | os.O_NOFOLLOW | os.O_CLOEXEC | (
                os.O_EXCL if offset == 0 else os.O_APPEND)
            fd = os.open(entry.output / name, flags, 0o644)
            try:
                os.write(fd, data)
            finally:
                os.close(fd)
            entry.received[index] += len(data)
            entry.hashes[index].update(data)
        return {}

    def _done(self, entry: _Attempt, request: dict[str, Any]) -> Any:
        digests = req_field(request, "digests", list)
        with entry.lock:
            why = None
            if len(digests) != len(entry.offered):
                why = "the digests do not match the offer"
            for (name, size), got, h, digest in zip(entry.offered, entry.received,
                                                    entry.hashes, digests, strict=False):
                if why is None and got != size:
                    why = f"{name!r} arrived short ({got} of {size} bytes)"
                elif why is None and "sha256:" + h.hexdigest() != digest:
                    why = f"{name!r} does not match its digest"
                elif size == 0:  # nothing was put: the empty file is made here
                    os.close(os.open(entry.output / name, os.O_WRONLY | os.O_CREAT
                                     | os.O_NOFOLLOW | os.O_CLOEXEC, 0o644))
        if why is not None:
            self._finish(entry, f"the output was refused: {why}")
            raise UsageError(f"the output was refused: {why}")
        self._finish(entry, None)
        return {}

    def _finish(self, entry: _Attempt, outcome: str | None) -> None:
        with entry.lock:
            if not entry.finished.is_set():
                entry.outcome = outcome
                entry.finished.set()


_VERBS = {
    (FETCH, "manifest"): PodData._manifest,
    (FETCH, "read"): PodData._read,
    (FETCH, "fetched"): PodData._fetched,
    (FETCH, "failed"): PodData._failed,
    (COLLECT, "wait"): PodData._wait,
    (COLLECT, "offer"): PodData._offer,
    (COLLECT, "put"): PodData._put,
    (COLLECT, "done"): PodData._done,
    (COLLECT, "failed"): PodData._failed,
}


def _checked_offer(files: list[Any], max_bytes: int | None,
                   max_files: int) -> list[tuple[str, int]]:
    """The offered ``(path, size)`` list, or UsageError naming the first problem."""
    if len(files) > max_files:
        raise UsageError(f"{len(files)} files, more than the {max_files} allowed")
    out: list[tuple[str, int]] = []
    names: set[str] = set()
    parents: set[str] = set()
    total = 0
    for item in files:
        if not isinstance(item, dict):
            raise UsageError("each offered file is an object")
        name, size = item.get("path"), item.get("size")
        if not isinstance(size, int) or isinstance(size, bool) or size < 0:
            raise UsageError(f"{name!r}: the size must be a whole number of bytes")
        check_relative(name)
        assert isinstance(name, str)
        parts = name.split("/")
        prefixes = {"/".join(parts[:i]) for i in range(1, len(parts))}
        if name in names or name in parents or prefixes & names:
            raise UsageError(f"{name!r} is listed twice, or both as a file and a folder")
        names.add(name)
        parents |= prefixes
        total += size
        out.append((name, size))
    if max_bytes is not None and total > max_bytes:
        raise UsageError(f"{total} bytes, more than the task's storage limit of {max_bytes} "
                         "bytes (resources: storage)")
    return out


def check_relative(name: object) -> None:
    """Raise UsageError unless ``name`` is a plain relative path (no ``..``, ``.``, ``//``)."""
    if not isinstance(name, str) or not name or len(name) > _MAX_PATH or "\0" in name:
        raise UsageError(f"{str(name)[:200]!r} is not a file name")
    if name.startswith("/") or any(p in ("", ".", "..") or len(p.encode()) > 255
                                   for p in name.split("/")):
        raise UsageError(f"{name[:200]!r} leaves the output folder (absolute, '..', '.' "
                         "or an empty part)")


def _make_parents(root: Path, name: str) -> None:
    """Make the folders of ``name`` under ``root`` (the node's own folder: no symlinks)."""
    folder = root
    for part in name.split("/")[:-1]:
        folder = folder / part
        try:
            os.mkdir(folder, 0o755)
        except FileExistsError:
            if not stat.S_ISDIR(os.lstat(folder).st_mode):
                raise UsageError(f"{name!r}: {part!r} is a file, not a folder") from None


def scan_mounts(mounts: Iterable[tuple[Path, str]]) -> tuple[list[PodFile], list[str]]:
    """The files and folders an init container fetches: each ``(node path, volume path)``.

    A folder is walked (symlinks are not followed: the node's own copies hold none); each
    file is hashed here, and the pod checks what it receives against that.
    """
    files: list[PodFile] = []
    dirs: list[str] = []
    for source, target in mounts:
        st = os.lstat(source)
        if stat.S_ISREG(st.st_mode):
            files.append(_pod_file(source, target, st))
            continue
        dirs.append(target)
        for folder, subdirs, names in os.walk(source):
            rel = os.path.relpath(folder, source)
            base = target if rel == "." else f"{target}/{rel}"
            dirs += [f"{base}/{d}" for d in sorted(subdirs)]
            for name in sorted(names):
                path = Path(folder, name)
                st = os.lstat(path)
                if stat.S_ISREG(st.st_mode):
                    files.append(_pod_file(path, f"{base}/{name}", st))
    return files, dirs


def _pod_file(path: Path, target: str, st: os.stat_result) -> PodFile:
    with open(path, "rb", buffering=0) as f:
        digest, _ = hash_fd(f, st.st_size)
    return PodFile(target, path, st.st_size, digest, stat.S_IMODE(st.st_mode))
