"""File-level primitives of the blob store: hash, publish by hard link, walk trees.

The tree walks are the ones every caller shares; verified copies are :mod:`osmo.artifacts.copies`.

Owns the few system calls whose order matters for atomicity (``link`` publishes a complete
file under its final name or fails because one is there) and the streaming hash loop. Every
walk over a tree here is iterative (:func:`files`, :func:`make_dirs`, :func:`remove_tree`):
a task may leave thousands of nested folders, and Python's recursion limit (or
``shutil.rmtree``'s and ``Path.mkdir(parents=True)``'s recursion) must not decide whether its
attempt finishes. Must not decide where blobs live or which files to store: that is
:mod:`osmo.artifacts.store`'s job.
"""

from __future__ import annotations

import hashlib
import os
import stat
import uuid
from collections.abc import Iterator
from io import FileIO
from pathlib import Path

from osmo.artifacts.errors import OutputRejected

__all__ = ["CHUNK", "check_unchanged", "files", "hash_fd", "link", "make_dirs",
           "refresh", "remove_tree"]

CHUNK = 1 << 20  # 1 MiB reads: large enough that sha256 (not syscalls) bounds the speed


def hash_fd(f: FileIO, size_hint: int) -> tuple[str, int]:
    """Hash an open file from its current position to the end.

    Args:
        f: an unbuffered binary file.
        size_hint: the expected size; the read buffer is no larger than needed for it.

    Returns:
        ``("sha256:<hex>", bytes read)``.
    """
    h = hashlib.sha256()
    buf = bytearray(min(CHUNK, max(size_hint, 0) + 1))  # +1: a small file takes one read
    view = memoryview(buf)
    total = 0
    while n := f.readinto(buf):
        h.update(view[:n])  # releases the GIL for large chunks, so threads hash in parallel
        total += n
    return "sha256:" + h.hexdigest(), total


def link(src: str, blob: Path) -> bool:
    """Create ``blob`` as a hard link to ``src``; ``False`` if it already existed (it wins)."""
    try:
        os.link(src, blob)
    except FileExistsError:
        refresh(blob)
        return False
    except FileNotFoundError:
        if not os.path.exists(src):
            raise
        blob.parent.mkdir(exist_ok=True)  # first blob of this shard
        return link(src, blob)
    return True


def refresh(blob: Path) -> None:
    """Bump the blob's ctime (and re-assert 0o444) so gc's grace period covers it."""
    try:
        os.chmod(blob, 0o444)
    except OSError:
        pass  # someone else's blob in a shared store: its age is then theirs to keep fresh


def check_unchanged(rel: str, f: FileIO, before: os.stat_result, n: int) -> None:
    """Raise if the file changed size or mtime since ``before`` (or ``n`` bytes were read)."""
    st = os.fstat(f.fileno())
    if n != before.st_size or (st.st_size, st.st_mtime_ns) != (before.st_size,
                                                              before.st_mtime_ns):
        raise OutputRejected(rel, "changed while it was being stored; make sure the task "
                             "and its child processes have finished writing its outputs")


def files(folder: Path, depth: int) -> Iterator[Path]:
    """Yield the files ``depth`` levels below ``folder`` (1: its own files)."""
    pending = [(Path(folder), depth)]
    while pending:
        current, left = pending.pop()
        with os.scandir(current) as it:
            entries = list(it)
        for entry in entries:
            if left > 1 and entry.is_dir(follow_symlinks=False):
                pending.append((Path(entry.path), left - 1))
            elif left == 1 and entry.is_file(follow_symlinks=False):
                yield Path(entry.path)


def make_dirs(folder: Path) -> None:
    """``mkdir -p folder``, without recursion (existing folders are fine).

    Raises:
        OSError: a level cannot be made (a file is in the way, the path is too long, ...).
    """
    missing: list[Path] = []
    current = Path(folder)
    while not current.is_dir():
        missing.append(current)
        if current.parent == current:
            break
        current = current.parent
    for level in reversed(missing):
        try:
            os.mkdir(level)
        except FileExistsError:
            if not level.is_dir():
                raise


def remove_tree(path: Path, *, ignore_errors: bool = False) -> None:
    """``rm -rf path`` without recursion and without following symlinks.

    Each folder met is emptied one level at a time: its sub-folders are first moved up into
    ``path`` (a rename within one filesystem), so no path grows longer than ``path`` plus one
    name, however deep the tree (``shutil.rmtree`` recurses, and a deep tree's paths exceed
    ``PATH_MAX``).

    Raises:
        OSError: something could not be removed (unless ``ignore_errors``).
    """
    root = Path(path)
    try:
        if not stat.S_ISDIR(os.lstat(root).st_mode):
            os.unlink(root)
            return
        while entries := _listing(root):
            for entry in entries:
                if not entry.is_dir(follow_symlinks=False):
                    os.unlink(entry.path)
                    continue
                for inner in _listing(Path(entry.path)):
                    if inner.is_dir(follow_symlinks=False):
                        os.rename(inner.path, root / f".rm-{uuid.uuid4().hex}")
                    else:
                        os.unlink(inner.path)
                os.rmdir(entry.path)
        os.rmdir(root)
    except FileNotFoundError:
        pass  # gone already (or removed by someone else meanwhile)
    except OSError:
        if not ignore_errors:
            raise


def _listing(folder: Path) -> list[os.DirEntry[str]]:
    with os.scandir(folder) as it:
        return list(it)
