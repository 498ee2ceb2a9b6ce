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

import os
import stat

from osmo.artifacts.errors import OutputRejected

__all__ = ["scan"]

def scan(folder: str) -> list[tuple[str, str, int]]:
    """List every file an ingest of ``folder`` stores, following the module's symlink policy.

    Args:
        folder: the output folder.

    Returns:
        ``(relative posix path, real path to read, size)`` per file, in no particular order.

    Raises:
        OutputRejected: a symlink leaves the folder, dangles or loops, or an entry is not a
            regular file, folder or symlink.
    """
    root = os.path.realpath(folder)
    out: list[tuple[str, str, int]] = []
    _scan_dir(root, root, "", {root}, out)
    return out


def _scan_dir(root: str, real: str, rel: str, walking: set[str],
              out: list[tuple[str, str, int]]) -> None:
    """Append the files under the real folder ``real`` (listed as ``rel``) to ``out``."""
    with os.scandir(real) as it:
        entries = list(it)
    for e in entries:
        name = rel + e.name
        if e.is_symlink():
            target = os.path.realpath(e.path)
            if target != root and not target.startswith(root + os.sep):
                raise OutputRejected(name, f"is a symlink to {target}, outside the output "
                                     "folder; copy the file into the folder instead")
            try:
                st = os.stat(target)
            except FileNotFoundError:
                raise OutputRejected(name, "is a dangling symlink; remove it or point it at "
                                     "a file inside the output folder") from None
            _add(root, target, name, st, walking, out)
        else:
            _add(root, e.path, name, e.stat(follow_symlinks=False), walking, out)


def _add(root: str, real: str, name: str, st: os.stat_result, walking: set[str],
         out: list[tuple[str, str, int]]) -> None:
    """Record a regular file, descend into a folder, reject anything else."""
    if stat.S_ISREG(st.st_mode):
        out.append((name, real, st.st_size))
    elif stat.S_ISDIR(st.st_mode):
        if real in walking:
            raise OutputRejected(name, "is a symlink that loops back into a folder that "
                                 "contains it; remove it")
        walking.add(real)
        try:
            _scan_dir(root, real, name + "/", walking, out)
        finally:
            walking.discard(real)
    else:
        raise OutputRejected(name, "is not a regular file or folder (socket, FIFO or device); "
                             "remove it from the output folder")
