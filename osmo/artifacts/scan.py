"""Listing an output folder for ingest.

Owns the symlink policy of ingest (:func:`scan`). Must not open or write files: hashing and
storing are :mod:`osmo.artifacts.fsops`' and :mod:`osmo.artifacts.store`'s jobs.

Symlink policy (``cp -rL`` confined to the folder): a symlink whose target resolves inside the
folder is followed, and its content is recorded under the link's own path (a link to a folder
lists that folder's files again; blobs are deduplicated, so this costs no store space). A
symlink that leaves the folder, dangles, or loops back into a folder being walked rejects the
whole output with :class:`OutputRejected`: following it could copy host files (``~/.ssh``)
into the store, and dropping it would lose an output silently. Sockets, FIFOs and devices are
rejected the same way.
"""

from __future__ import annotations

import errno
import os
import stat

from osmo.artifacts.errors import OutputRejected

__all__ = ["scan"]

def scan(folder: str, *, max_files: int | None = None) -> list[tuple[str, str, int]]:
    """List every file an ingest of ``folder`` stores, following the module's symlink policy.

    The walk is iterative (an explicit stack), so any depth is walked; a folder whose path
    the system cannot open any more (longer than ``PATH_MAX``) rejects the output.

    Args:
        folder: the output folder.
        max_files: stop (and reject the output) once more files than this are listed.

    Returns:
        ``(relative posix path, real path to read, size)`` per file, in no particular order.

    Raises:
        OutputRejected: a symlink leaves the folder, dangles or loops, an entry is not a
            regular file, folder or symlink, the tree is nested too deep to open, or it
            lists more than ``max_files`` files.
    """
    root = os.path.realpath(folder)
    out: list[tuple[str, str, int]] = []
    walking: set[str] = set()  # real folders on the way from ``root`` to the current one
    stack: list[tuple[str, str, bool]] = [(root, "", True)]  # (real, rel, entering?)
    while stack:
        real, rel, entering = stack.pop()
        if not entering:
            walking.discard(real)
            continue
        walking.add(real)
        stack.append((real, rel, False))  # leave it after everything below it
        for name, target, st in _entries(root, real, rel):
            if stat.S_ISREG(st.st_mode):
                out.append((name, target, st.st_size))
                if max_files is not None and len(out) > max_files:
                    raise OutputRejected("", f"lists more than {max_files} files (symlinks "
                                         "to folders count their files again); write fewer "
                                         "or pack them into an archive")
            elif stat.S_ISDIR(st.st_mode):
                if target in walking:
                    raise OutputRejected(name, "is a symlink that loops back into a folder "
                                         "that contains it; remove it")
                stack.append((target, name + "/", True))
            else:
                raise OutputRejected(name, "is not a regular file or folder (socket, FIFO or "
                                     "device); remove it from the output folder")
    return out


def _entries(root: str, real: str, rel: str) -> list[tuple[str, str, os.stat_result]]:
    """``(listed name, real path, stat)`` of each entry of the real folder ``real``."""
    try:
        return _list(root, real, rel)
    except OSError as exc:
        if exc.errno == errno.ENAMETOOLONG:
            raise OutputRejected(rel[:120] + "...", "is nested too deep: its "
                                 "paths are longer than the system can open; flatten the "
                                 "output folder") from None
        raise


def _list(root: str, real: str, rel: str) -> list[tuple[str, str, os.stat_result]]:
    with os.scandir(real) as it:
        entries = list(it)
    found = []
    for e in entries:
        name = rel + e.name
        if not e.is_symlink():
            found.append((name, e.path, e.stat(follow_symlinks=False)))
            continue
        target = os.path.realpath(e.path)
        if target != root and not target.startswith(root + os.sep):
            raise OutputRejected(name, f"is a symlink to {target!r}, outside the "
                                 "output folder; copy the file into the folder instead")
        try:
            found.append((name, target, os.stat(target)))
        except FileNotFoundError:
            raise OutputRejected(name, "is a dangling symlink; remove it or point it at a "
                                 "file inside the output folder") from None
    return found
