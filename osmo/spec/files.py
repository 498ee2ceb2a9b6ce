"""Reading the files a spec is or names (the spec file, ``localpath`` files): regular files
only, bounded in size, and never blocking.

A FIFO with no writer blocks ``open()`` forever and ``/dev/zero`` never ends, so anything but
a regular file is refused by what it is, before a byte is read. The file is opened
non-blocking and checked again on the open descriptor, so swapping in a FIFO after the check
does not hang the reader either.
"""

from __future__ import annotations

import os
import stat

__all__ = ["FileRefused", "read_regular_file"]

_KINDS = ((stat.S_ISDIR, "a folder"), (stat.S_ISFIFO, "a FIFO (named pipe)"),
          (stat.S_ISCHR, "a character device"), (stat.S_ISBLK, "a block device"),
          (stat.S_ISSOCK, "a socket"))


class FileRefused(Exception):
    """The path is not a regular file, or is too large; the message says which."""


def _kind(mode: int) -> str | None:
    """What a non-regular file is ("a FIFO (named pipe)"...); None for a regular file."""
    if stat.S_ISREG(mode):
        return None
    return next((what for test, what in _KINDS if test(mode)), "not a regular file")


def read_regular_file(path: str | os.PathLike[str], *, limit: int) -> bytes:
    """The bytes of the regular file at ``path`` (symlinks followed), at most ``limit``.

    Raises:
        FileRefused: it is a folder, FIFO, device or socket, or larger than ``limit``.
        OSError: it cannot be read (missing, no permission...).
    """
    kind = _kind(os.stat(path).st_mode)
    if kind is not None:
        raise FileRefused(f"is {kind}, not a regular file")
    fd = os.open(path, os.O_RDONLY | os.O_NONBLOCK | os.O_NOCTTY | os.O_CLOEXEC)
    with os.fdopen(fd, "rb") as f:
        kind = _kind(os.fstat(fd).st_mode)  # it may have been swapped since the stat
        if kind is not None:
            raise FileRefused(f"is {kind}, not a regular file")
        data = f.read(limit + 1)
    if len(data) > limit:
        raise FileRefused(f"is larger than {limit // 2**20} MiB, the limit")
    return data
