"""A content-addressed blob store on the local filesystem (``OSMO_HOME/artifacts``).

Owns the on-disk layout below and every write into it: ingesting an output folder into blobs
plus a :class:`~osmo.artifacts.manifest.Manifest`, verified reads, materializing a manifest
into a folder, and garbage collection. Must not know about workflows, tasks or the state
store: callers persist manifests and say which digests are still referenced. Never pickles;
only the standard library.

Layout::

    root/blobs/sha256/ab/cdef...   one read-only (0o444) file per distinct content
    root/tmp/                      copies being written (cross-filesystem ingest)
    root/lock                      flock: ingest holds it shared, gc exclusive

How ingest stores a new file, fastest first:

- **Same filesystem, one link:** the file is hashed (one streaming read), made read-only
  (0o444), and hard-linked into place with ``os.link``, which either creates the final name
  atomically or fails because the blob exists: an existing blob wins, so concurrent ingests
  of the same content are safe. No data is copied. The output file and the blob then share
  one inode, which is why outputs are immutable once ingested: writing to the output would
  change the blob. The data is not fsynced on this path (that would cost a full disk write
  of every output); a blob torn by a power cut fails verification and is never used.
- **Otherwise** (another filesystem, hard links refused, or a file that already has more
  than one link): the file is copied to ``root/tmp``, fsynced, made read-only and linked
  into place the same way. A file with several links is never linked or chmod-ed: its
  other names may be outside the output folder (``ln /any/file {{output}}/x``), and ingest
  never changes a file it does not own.

A file whose blob already exists writes no data; ingest only refreshes the blob's ctime (a
``chmod`` to 0o444) so that :meth:`ArtifactStore.gc`'s grace period covers it until the caller
records the manifest — after checking that the existing blob still holds its digest (a blob
that does not is replaced). Reads and hand-outs (:mod:`osmo.artifacts.copies`) are checked
against the digest and raise :class:`ArtifactCorrupted` on a mismatch.
"""

from __future__ import annotations

import contextlib
import errno
import fcntl
import hashlib
import os
import shutil
import stat
import time
import uuid
from collections.abc import Iterable, Iterator
from concurrent.futures import ThreadPoolExecutor
from contextlib import contextmanager
from io import FileIO
from pathlib import Path

from osmo.artifacts.copies import HandOut, Verifier
from osmo.artifacts.errors import ArtifactCorrupted, OutputRejected
from osmo.artifacts.fsops import CHUNK, check_unchanged, files, hash_fd, link, refresh
from osmo.artifacts.manifest import Entry, Manifest, check_digest
from osmo.artifacts.scan import scan
from osmo.errors import UsageError
from osmo.layout import BlobDirs

__all__ = ["DEFAULT_GRACE", "DEFAULT_MAX_FILES", "ArtifactStore"]

DEFAULT_GRACE = 3600.0
"""Seconds a blob is safe from :meth:`ArtifactStore.gc` after it was stored or deduplicated."""

DEFAULT_MAX_FILES = 1_000_000
"""Files one output may list by default (bounds a tree of symlinks that lists itself over and
over: each name is a file ``artifacts get`` would write)."""

_PARALLEL_SIZE = 4 << 20  # files this large are hashed on a thread pool


class ArtifactStore(HandOut):
    """Blobs named by their sha256, written once and never modified.

    Handed out as checked copies or links (:class:`~osmo.artifacts.copies.HandOut`).

    Args:
        root: the store's folder (``OSMO_HOME/artifacts``); created if missing.
    """

    def __init__(self, root: Path) -> None:
        self.root = Path(root)
        self._dirs = BlobDirs(self.root)
        self._blobs = self._dirs.blobs
        self._tmp = self._dirs.tmp
        self._blobs.mkdir(parents=True, exist_ok=True)
        self._tmp.mkdir(exist_ok=True)
        self._dev = os.stat(self._blobs).st_dev
        self._verifier = Verifier()

    # -- queries -----------------------------------------------------------------------------

    def path(self, digest: str) -> Path:
        """Return where the blob for ``digest`` lives; it may not exist, nothing is verified.

        Raises:
            UsageError: ``digest`` is malformed.
        """
        return self._dirs.blob(check_digest(digest))

    def has(self, digest: str) -> bool:
        """Return whether a blob for ``digest`` exists (its content is not verified)."""
        return self.path(digest).is_file()

    def verify(self, digest: str) -> bool:
        """Re-hash the blob for ``digest``: ``True`` when it exists and matches."""
        try:
            with open(self.path(digest), "rb", buffering=0) as f:
                before = os.fstat(f.fileno())
                ok = hash_fd(f, before.st_size)[0] == digest
                if ok and os.fstat(f.fileno()).st_ctime_ns == before.st_ctime_ns:
                    self._verifier.note(digest, before)
                return ok
        except FileNotFoundError:
            return False

    def read(self, digest: str) -> bytes:
        """Return the blob's content after checking it hashes to ``digest``.

        Meant for small artifacts; use :meth:`materialize` for large ones.

        Raises:
            ArtifactCorrupted: the blob is missing or its content does not match.
        """
        path = self.path(digest)
        try:
            data = path.read_bytes()
        except FileNotFoundError:
            raise ArtifactCorrupted(digest, str(path), None) from None
        actual = "sha256:" + hashlib.sha256(data).hexdigest()
        if actual != digest:
            raise ArtifactCorrupted(digest, str(path), actual)
        return data

    # -- ingest ------------------------------------------------------------------------------

    def ingest(self, folder: Path, *, max_bytes: int | None = None,
               max_files: int | None = DEFAULT_MAX_FILES) -> Manifest:
        """Store every file under ``folder`` and return its manifest.

        Files are hashed with streaming 1 MiB reads and stored deduplicated (see the module
        docstring). New blobs on the same filesystem are hard links to the output files,
        which become read-only. Symlinks follow :func:`osmo.artifacts.scan.scan`'s policy;
        a file listed under several names (through symlinks) is read once. The limits are
        checked on the listing, before anything is read or stored.

        Args:
            folder: the output folder; entry paths are relative to it.
            max_bytes: the most bytes the listed files may hold (None: no limit). Sizes are
                the files' lengths, so a sparse file counts its holes.
            max_files: the most files the output may list (None: no limit).

        Returns:
            The manifest of every regular file under ``folder``.

        Raises:
            UsageError: ``folder`` is not a folder.
            OutputRejected: a symlink leaves the folder, dangles or loops, an entry is not a
                regular file, a file changed while it was being stored, or the output holds
                more than ``max_bytes`` or ``max_files``.
        """
        if not Path(folder).is_dir():
            raise UsageError(f"cannot ingest {folder}: not a folder")
        files = scan(str(folder), max_files=max_files)
        total = sum(size for _rel, _src, size in files)
        if max_bytes is not None and total > max_bytes:
            raise OutputRejected("", f"holds {total} bytes in {len(files)} files, more than "
                                 f"the task's storage limit of {max_bytes} bytes (resources: "
                                 "storage); write less, or raise the limit")
        first: dict[str, tuple[str, int]] = {}  # real file → (first name listed, size)
        for rel, src, size in files:
            first.setdefault(src, (rel, size))
        stored = dict(zip(first, self._ingest_all(
            [(rel, src, size) for src, (rel, size) in first.items()]), strict=True))
        return Manifest(tuple(Entry(rel, stored[src].digest, stored[src].size)
                              for rel, src, _size in files))

    def _ingest_all(self, files: list[tuple[str, str, int]]) -> list[Entry]:
        """Ingest each ``(name, real path, size)``; entries in the same order."""
        if not files:  # an empty output: no blob to keep from gc, no lock to take
            return []
        with self._lock(exclusive=False):
            big = [i for i, (_rel, _src, size) in enumerate(files) if size >= _PARALLEL_SIZE]
            if len(big) < 2:
                return [self._ingest_file(rel, src) for rel, src, _size in files]
            # hashlib releases the GIL, so large files hash in parallel; small ones are
            # syscall-bound and run faster on this thread than through a pool
            workers = min(len(big), os.cpu_count() or 1, 8)
            out: list[Entry | None] = [None] * len(files)
            with ThreadPoolExecutor(workers, thread_name_prefix="osmo-ingest") as pool:
                futures = {i: pool.submit(self._ingest_file, *files[i][:2]) for i in big}
                for i, (rel, src, _size) in enumerate(files):
                    if i not in futures:
                        out[i] = self._ingest_file(rel, src)
                for i, future in futures.items():
                    out[i] = future.result()
            return [e for e in out if e is not None]

    def _ingest_file(self, rel: str, src: str) -> Entry:
        """Hash one file and make sure its blob exists."""
        try:  # O_NOFOLLOW: a symlink swapped in since the scan is never followed
            f = open(os.open(src, os.O_RDONLY | os.O_NOFOLLOW | os.O_CLOEXEC), "rb", buffering=0)
        except PermissionError as exc:
            raise OutputRejected(rel, f"cannot be read ({exc.strerror}); make it readable "
                                 "by the worker") from None
        with f:
            before = os.fstat(f.fileno())
            digest, n = hash_fd(f, before.st_size)
            check_unchanged(rel, f, before, n)
            blob = self.path(digest)
            try:
                existing: os.stat_result | None = os.stat(blob)
            except FileNotFoundError:
                existing = None
            if existing is None or existing.st_size != n or not self._reusable(
                    blob, digest, existing):
                if existing is not None:  # no longer holds its digest: replace it
                    blob.unlink(missing_ok=True)
                    self._verifier.forget(digest)
                self._store_new(rel, src, f, before, blob)
        return Entry(rel, digest, n)

    def _reusable(self, blob: Path, digest: str, existing: os.stat_result) -> bool:
        """Whether the existing blob still holds ``digest`` (hashed unless known intact).

        Its ctime is then refreshed for gc's grace period.
        """
        if not self._verifier.intact(digest, existing) and not self.verify(digest):
            return False
        refresh(blob)
        try:
            after = os.stat(blob)
        except FileNotFoundError:
            return False
        if (after.st_mtime_ns, after.st_size) == (existing.st_mtime_ns, existing.st_size):
            self._verifier.note(digest, after)  # only our chmod changed its ctime
        return True

    def _store_new(self, rel: str, src: str, f: FileIO, before: os.stat_result,
                   blob: Path) -> None:
        """Publish a blob for the open file ``f``: by hard link if possible, else by copy.

        A file with more than one link is always copied: its other names may lie outside the
        output folder (a task can hard-link any file it can reach, even the state store), and
        linking or chmod-ing its inode would change that file and serve it as a blob.
        """
        if before.st_dev == self._dev and before.st_nlink == 1:
            try:
                os.fchmod(f.fileno(), 0o444)  # before the link: a blob is never writable
                if link(src, blob) and os.stat(blob).st_ino != before.st_ino:
                    blob.unlink()  # ``src`` was replaced after we opened it: copy our file
                    raise OSError(errno.ESTALE, "output replaced during ingest")
                return
            except OSError:  # links refused (EXDEV across bind mounts, EPERM, EMLINK): copy
                with contextlib.suppress(OSError):
                    os.fchmod(f.fileno(), stat.S_IMODE(before.st_mode))  # not shared after all
        tmp = self._tmp / uuid.uuid4().hex
        try:
            with open(tmp, "xb") as out:
                f.seek(0)
                shutil.copyfileobj(f, out, CHUNK)
                out.flush()
                os.fsync(out.fileno())
            check_unchanged(rel, f, before, before.st_size)
            os.chmod(tmp, 0o444)
            link(str(tmp), blob)
        finally:
            tmp.unlink(missing_ok=True)

    # -- transfer ----------------------------------------------------------------------------

    @property
    def tmp(self) -> Path:
        """Scratch folder for blobs being received (same filesystem; gc clears old files)."""
        return self._tmp

    def adopt(self, tmp: Path, digest: str) -> None:
        """Publish ``tmp``, complete and hashed to ``digest`` by the caller, as that blob.

        Fsynced, read-only, linked into place; an existing blob wins.
        """
        with open(tmp, "rb") as f:
            os.fsync(f.fileno())
        os.chmod(tmp, 0o444)
        try:
            link(str(tmp), self.path(digest))
        finally:
            tmp.unlink(missing_ok=True)

    def adopt_link(self, src: Path, digest: str) -> bool:
        """Hard-link another store's blob ``src`` (same host and filesystem) as ``digest``.

        False when it cannot be linked (then the caller copies it).
        """
        try:
            link(str(src), self.path(digest))
        except OSError:
            return False
        return True

    # -- garbage collection ------------------------------------------------------------------

    def gc(self, referenced: Iterable[str], *, grace: float = DEFAULT_GRACE,
           now: float | None = None) -> tuple[int, int]:
        """Remove blobs whose digest is not in ``referenced``.

        A blob is kept while it is younger than ``grace`` seconds, measured by its ctime:
        storing a blob (``link``) and deduplicating onto it (``chmod``) both refresh it, so
        an ingest whose manifest the caller has not recorded yet is safe. gc also waits for
        running ingests (the store lock) and removes copies left in ``root/tmp`` older than
        ``grace`` by a crash.

        Args:
            referenced: digests still in use (``"sha256:<hex>"``).
            grace: seconds a newly stored or deduplicated blob is kept regardless.
            now: the current time (``time.time()`` when omitted; injectable for tests).

        Returns:
            ``(blobs removed, their total size in bytes)``. Space is only freed once no
            output file shares the blob's inode.

        Raises:
            UsageError: a referenced digest is malformed.
        """
        keep = {check_digest(d) for d in referenced}
        now = time.time() if now is None else now
        count = freed = 0
        with self._lock(exclusive=True):
            for blob in files(self._blobs, depth=2):
                st = blob.stat()
                if blob.parent.name + blob.name in keep or now - st.st_ctime < grace:
                    continue
                blob.unlink(missing_ok=True)
                count, freed = count + 1, freed + st.st_size
            for tmp in files(self._tmp, depth=1):
                if now - tmp.stat().st_ctime >= grace:
                    tmp.unlink(missing_ok=True)
        return count, freed

    def size(self) -> int:
        """Bytes the blobs take (a blob shared with an output file counts once)."""
        total = 0
        for blob in files(self._blobs, depth=2):
            with contextlib.suppress(FileNotFoundError):  # removed by a gc meanwhile
                total += blob.stat().st_size
        return total

    @contextmanager
    def _lock(self, *, exclusive: bool) -> Iterator[None]:
        """Hold the store lock: shared for ingest, exclusive for gc (one fd per call)."""
        fd = os.open(self.root / "lock", os.O_RDWR | os.O_CREAT, 0o644)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX if exclusive else fcntl.LOCK_SH)
            yield
        finally:
            os.close(fd)  # closing releases the flock

