"""Handing blobs out as private, verified copies: what a task can write is never a blob itself.

A task may write to any file it is given (tasks run as root here, so a 0o444 mode protects
nothing); a blob shared by hard link would then change for every later reader. So whatever
leaves the store for a task or a user is a copy (:func:`copy_out`; :class:`HandOut` builds
folders of them, and of links for the few folders no task is handed), unless the task
cannot write to it: a sandboxed task's inputs are bound read-only, so they are hard links of
the checked blobs (:func:`link_out`, :meth:`HandOut.link_checked`), and no data is copied.
The copy, for everyone else:

- a **reflink** (``ioctl(FICLONE)``: btrfs, XFS, ...) when the filesystem can share the data
  copy-on-write, which costs no data writes and keeps the copy private;
- otherwise a plain copy (``copy_file_range``, or read/write).

A blob whose content no longer hashes to its name is never handed out. Hashing every byte of
every copy would double the cost of each hand-out, so :class:`Verifier` remembers the blobs
found intact by their inode, size and ``ctime``: the kernel updates ``ctime`` on every write
and no caller can set it back (short of changing the system clock), so an unchanged ``ctime``
means unchanged content (a blob changed less than a second ago is not remembered: file
times tick coarsely). A blob not known intact is hashed on the way (the copy is hashed,
so exactly what is handed out is checked); a mismatch raises :class:`ArtifactCorrupted` and
the caller removes the partial copy. Must not decide where blobs live or write into the
store (``osmo.artifacts.store``).
"""

from __future__ import annotations

import errno
import fcntl
import hashlib
import os
import stat
import tempfile
import threading
import time
from collections.abc import Callable
from io import FileIO
from pathlib import Path

from osmo.artifacts.errors import ArtifactCorrupted
from osmo.artifacts.fsops import CHUNK, hash_fd, make_dirs, remove_tree
from osmo.artifacts.manifest import Entry, Manifest
from osmo.errors import NotFoundError, UsageError

__all__ = ["HandOut", "Verifier", "copy_out", "link_out"]

_FICLONE = 0x40049409  # _IOW(0x94, 9, int), linux/fs.h
_SETTLED_NS = 1_000_000_000


class Verifier:
    """The blobs known intact: digest → (inode, size, ctime) when last hashed whole."""

    def __init__(self) -> None:
        self._intact: dict[str, tuple[int, int, int]] = {}
        self._lock = threading.Lock()

    def intact(self, digest: str, st: os.stat_result) -> bool:
        """True when the blob ``st`` describes was hashed whole since its last change."""
        with self._lock:
            return self._intact.get(digest) == _key(st)

    def note(self, digest: str, st: os.stat_result) -> None:
        """Remember that the blob ``st`` describes hashed to ``digest``.

        Unless it changed less than a second ago: file times tick coarsely (a few ms), and a write
        within the same tick as the last change would leave ``ctime`` as it was.
        """
        if time.time_ns() - st.st_ctime_ns < _SETTLED_NS:
            return
        with self._lock:
            self._intact[digest] = _key(st)

    def forget(self, digest: str) -> None:
        """The blob is gone or replaced."""
        with self._lock:
            self._intact.pop(digest, None)


class HandOut:
    """How the artifact store hands blobs out: folders of checked copies or of links.

    Copies: :meth:`copy_tree`, :meth:`materialize`; links: :meth:`link_tree` (used by
    :class:`~osmo.artifacts.store.ArtifactStore`).

    A mixin: the store provides :meth:`path` and ``_verifier``.
    """

    _verifier: Verifier

    def path(self, digest: str) -> Path:
        """Where the blob for ``digest`` lives (the store's)."""
        raise NotImplementedError

    def link_tree(self, manifest: Manifest, dest: Path) -> None:
        """Create folder ``dest`` holding the manifest's files as hard links of their blobs.

        Read-only, nothing copied; a verified copy where links are refused. For folders no task is
        handed (a remote attempt's promoted output on the server); a task gets :meth:`copy_tree`.
        Built beside ``dest`` and renamed into place, so ``dest`` appears complete or not at all; an
        existing ``dest`` is left as it is.

        Raises:
            ArtifactCorrupted: a blob is missing.
        """
        if not dest.is_dir():
            self._build(manifest, dest, self._link_or_copy)

    def copy_tree(self, manifest: Manifest, dest: Path) -> None:
        """Fill the new folder ``dest`` with private, checked copies of the manifest's files.

        Reflinks where the filesystem shares data; each file is checked against its digest (see
        :mod:`osmo.artifacts.copies`). What a task is handed: changing it changes no blob. Written
        in place, not staged: ``dest`` must be the caller's alone until this returns.

        Raises:
            ArtifactCorrupted: a blob is missing or no longer matches its digest.
            OSError: ``dest`` exists or cannot be written.
        """
        self._fill(manifest, dest, self._copy)

    def link_checked(self, manifest: Manifest, dest: Path) -> None:
        """Fill the new folder ``dest`` with hard links of the manifest's blobs, each checked.

        For a task that cannot write to ``dest`` (a sandbox binds it read-only): no data is
        copied, and a blob that no longer matches its digest is never handed out (checked as
        :func:`copy_out` checks, so a blob known intact is not hashed again). A plain checked
        copy where a link is refused (another filesystem). Written in place, like
        :meth:`copy_tree`.

        Raises:
            ArtifactCorrupted: a blob is missing or no longer matches its digest.
            OSError: ``dest`` exists or cannot be written.
        """
        self._fill(manifest, dest, self._link_checked)

    def _link_checked(self, entry: Entry, final: Path) -> None:
        if not link_out(self.path(entry.digest), entry.digest, entry.size, final,
                        self._verifier):
            self._copy(entry, final)

    def _fill(self, manifest: Manifest, dest: Path,
              place: Callable[[Entry, Path], None]) -> None:
        """Make the new folder ``dest`` and ``place`` each entry in it, in place (not staged)."""
        os.mkdir(dest)
        made = {dest}
        for e in manifest.entries:
            final = dest / e.path
            if final.parent not in made:
                make_dirs(final.parent)
                made.add(final.parent)
            place(e, final)

    def _build(self, manifest: Manifest, dest: Path,
               place: Callable[[Entry, Path], None]) -> None:
        make_dirs(dest.parent)
        build = Path(tempfile.mkdtemp(prefix=f".{dest.name}.", dir=dest.parent))
        try:
            for e in manifest.entries:
                final = build / e.path
                make_dirs(final.parent)
                place(e, final)
            os.chmod(build, 0o755)
            try:
                os.rename(build, dest)
            except OSError:
                if not dest.is_dir():
                    raise
        finally:
            remove_tree(build, ignore_errors=True)

    def _link_or_copy(self, entry: Entry, final: Path) -> None:
        try:
            os.link(self.path(entry.digest), final)
        except FileNotFoundError:
            raise ArtifactCorrupted(entry.digest, str(self.path(entry.digest)), None) from None
        except OSError:
            self._copy(entry, final)

    def _copy(self, entry: Entry, final: Path) -> None:
        copy_out(self.path(entry.digest), entry.digest, entry.size, final, self._verifier)

    def materialize(self, manifest: Manifest, dest: Path, *, only: str | None = None
                    ) -> list[Path]:
        """Write the manifest's files (or just ``only``) under ``dest``, verified.

        Every file is first copied from its blob into a hidden staging folder inside ``dest``
        and checked; only when all match are they renamed into place (replacing existing
        files). So a corrupted blob leaves nothing new in ``dest``, and no file is ever
        visible under its final name half-written. Files are not fsynced: they can always be
        materialized again. Nothing is written through a symlink inside ``dest``: a file
        that is a symlink is replaced by the file, and a folder that is a symlink (or a file
        where a folder is needed) refuses the whole call before anything is written.

        Args:
            manifest: the files to write.
            dest: the folder to write them under (created if missing; may itself be a
                symlink to a folder).
            only: a single entry path to write instead of all of them.

        Returns:
            The paths written, in manifest order.

        Raises:
            UsageError: ``dest`` exists and is not a folder (a file, a dangling symlink), or
                a folder inside it is a symlink or a file.
            NotFoundError: ``only`` is not a path in the manifest.
            ArtifactCorrupted: a blob is missing or does not match its digest.
        """
        entries = list(manifest.entries)
        if only is not None:
            entry = manifest.get(only)
            if entry is None:
                raise NotFoundError(f"no artifact {only!r} in manifest {manifest.digest} "
                                    f"({len(entries)} files)")
            entries = [entry]
        dest = Path(dest)
        if os.path.lexists(dest) and not dest.is_dir():
            raise UsageError(f"{dest} exists and is not a folder (a file, or a symlink to "
                             "nothing); choose a folder, or remove it first")
        make_dirs(dest)
        checked: set[str] = set()
        for e in entries:
            _check_parents(dest, e.path, checked)
        staging = Path(tempfile.mkdtemp(prefix=".osmo-materialize-", dir=dest))
        try:
            staged = [staging / str(i) for i in range(len(entries))]
            for tmp, e in zip(staged, entries, strict=True):
                self._copy(e, tmp)
            for tmp, e in zip(staged, entries, strict=True):
                _place(tmp, dest, e.path)
            return [dest / e.path for e in entries]
        finally:
            remove_tree(staging, ignore_errors=True)


def _check_parents(dest: Path, path: str, checked: set[str]) -> None:
    """Refuse a folder of ``path`` (under ``dest``) that exists as a symlink or a file."""
    parts = path.split("/")[:-1]
    for i in range(1, len(parts) + 1):
        rel = "/".join(parts[:i])
        if rel in checked:
            continue
        try:
            mode = os.lstat(dest / rel).st_mode
        except FileNotFoundError:
            return  # made by _place; nothing below it can exist either
        if not stat.S_ISDIR(mode):
            what = "a symlink" if stat.S_ISLNK(mode) else "a file"
            raise UsageError(f"{dest / rel} is {what} where the artifact has a "
                             "folder; osmo never writes through a symlink inside the "
                             "destination: remove it, or choose another folder")
        checked.add(rel)


def _place(tmp: Path, dest: Path, path: str) -> None:
    """Rename ``tmp`` to ``dest/path`` without following a symlink on the way.

    Each folder on the way is opened so: a folder swapped for a symlink meanwhile fails instead of
    being written through.
    """
    *folders, name = path.split("/")
    fd = os.open(dest, os.O_RDONLY | os.O_DIRECTORY | os.O_CLOEXEC)
    try:
        for folder in folders:
            try:
                os.mkdir(folder, dir_fd=fd)
            except FileExistsError:
                pass
            try:
                inner = os.open(folder, os.O_RDONLY | os.O_DIRECTORY | os.O_NOFOLLOW |
                                os.O_CLOEXEC, dir_fd=fd)
            except OSError as exc:
                raise UsageError(f"{dest / path}: a folder on its way is not a "
                                 f"folder any more ({exc.strerror}); nothing was written "
                                 "through it") from None
            os.close(fd)
            fd = inner
        try:
            os.replace(tmp, name, dst_dir_fd=fd)
        except (IsADirectoryError, NotADirectoryError):
            raise UsageError(f"{dest / path} is a folder where the artifact has a "
                             "file; remove it, or choose another folder") from None
    finally:
        os.close(fd)


def copy_out(blob: Path, digest: str, size: int, dest: Path, verifier: Verifier) -> None:
    """Write a private copy of ``blob`` at the new file ``dest``, checked against ``digest``.

    Raises:
        ArtifactCorrupted: the blob is missing or does not hash to ``digest`` (``dest`` may
            then hold a partial copy; the caller removes it).
        OSError: ``dest`` cannot be written.
    """
    try:
        src = open(blob, "rb", buffering=0)
    except FileNotFoundError:
        verifier.forget(digest)
        raise ArtifactCorrupted(digest, str(blob), None) from None
    with src, open(dest, "xb", buffering=0) as out:
        before = os.fstat(src.fileno())
        trusted = verifier.intact(digest, before)
        actual = None
        if not _clone(src, out):
            actual = _copy(src, out, size, hashing=not trusted)
        unchanged = _key(os.fstat(src.fileno())) == _key(before)
        if trusted and unchanged:
            return
        if actual is None or not unchanged:  # hash exactly what was handed out
            with open(dest, "rb", buffering=0) as copy:
                actual = hash_fd(copy, size)[0]
    if actual != digest:
        verifier.forget(digest)
        raise ArtifactCorrupted(digest, str(blob), actual)
    if unchanged:
        verifier.note(digest, before)


def link_out(blob: Path, digest: str, size: int, dest: Path, verifier: Verifier) -> bool:
    """Hard-link ``blob`` at the new name ``dest`` once it is known to hash to ``digest``.

    Returns:
        False when the link is refused (``dest`` on another filesystem): nothing was made.

    Raises:
        ArtifactCorrupted: the blob is missing or does not hash to ``digest``.
    """
    try:
        src = open(blob, "rb", buffering=0)
    except FileNotFoundError:
        verifier.forget(digest)
        raise ArtifactCorrupted(digest, str(blob), None) from None
    with src:
        before = os.fstat(src.fileno())
        if not verifier.intact(digest, before):
            actual = hash_fd(src, size)[0]
            if actual != digest:
                verifier.forget(digest)
                raise ArtifactCorrupted(digest, str(blob), actual)
            if _key(os.fstat(src.fileno())) == _key(before):
                verifier.note(digest, before)
    try:
        os.link(blob, dest)
    except OSError as exc:
        if exc.errno in (errno.EXDEV, errno.EMLINK, errno.EPERM):
            return False
        raise
    return True


def _key(st: os.stat_result) -> tuple[int, int, int]:
    return (st.st_ino, st.st_size, st.st_ctime_ns)


def _clone(src: FileIO, out: FileIO) -> bool:
    """Share ``src``'s data with ``out`` copy-on-write; False where unsupported."""
    try:
        fcntl.ioctl(out.fileno(), _FICLONE, src.fileno())
    except OSError:
        return False
    return True


def _copy(src: FileIO, out: FileIO, size: int, *, hashing: bool) -> str | None:
    """Copy all of ``src`` to ``out``; return the digest of the bytes when ``hashing``."""
    if not hashing:
        try:
            left = size
            while left > 0 and (n := os.copy_file_range(src.fileno(), out.fileno(),
                                                        min(left, 1 << 30))):
                left -= n
            if left == 0:
                return None
        except OSError:
            pass  # not on this filesystem (or kernel): copy through user space
        src.seek(0)
        out.seek(0)
        out.truncate()
    h = hashlib.sha256()
    buf = bytearray(min(CHUNK, size + 1))
    view = memoryview(buf)
    while n := src.readinto(buf):
        h.update(view[:n])
        out.write(view[:n])
    return "sha256:" + h.hexdigest() if hashing else None
