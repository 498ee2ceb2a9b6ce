"""Reading the files a spec is or names (the spec file, ``localpath`` files).

Regular files only, bounded in size, and never blocking. Light on purpose: the SDK reads a spec file
with it without loading the parsers.

A FIFO with no writer blocks ``open()`` forever and ``/dev/zero`` never ends, so anything but
a regular file is refused by what it is, before a byte is read. The file is opened
non-blocking and checked again on the open descriptor, so swapping in a FIFO after the check
does not hang the reader either.
"""

from __future__ import annotations

import os
import stat
from collections.abc import Callable

from osmo.errors import Diagnostic, SpecError

__all__ = ["MAX_SPEC_FILE", "FileRefused", "read_regular_file", "read_spec_file"]

MAX_SPEC_FILE = 16 * 1024 * 1024  # bytes of a spec file

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


def read_regular_file(path: str | os.PathLike[str], *, limit: int,
                      check: Callable[[str], None] | None = None) -> bytes:
    """The bytes of the regular file at ``path`` (symlinks followed), at most ``limit``.

    ``check`` is called with the real path of the file actually opened, before a byte is
    read; it raises (a ``FileRefused``) to refuse it.

    Raises:
        FileRefused: it is a folder, FIFO, device or socket, or larger than ``limit``, or
            ``check`` refused it.
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
        if check is not None:
            check(os.readlink(f"/proc/self/fd/{fd}"))
        data = f.read(limit + 1)
    if len(data) > limit:
        raise FileRefused(f"is larger than {limit // 2**20} MiB, the limit")
    return data


def read_spec_file(path: str | os.PathLike[str], name: str | None = None) -> str:
    """The text of a spec file.

    A regular file of UTF-8 text, at most :data:`MAX_SPEC_FILE` bytes; ``name`` is the file's name
    in messages (default: ``path``).

    Raises:
        SpecError: it cannot be read, or is a folder, FIFO or device, or too large.
    """
    try:
        return read_regular_file(path, limit=MAX_SPEC_FILE).decode("utf-8")
    except FileNotFoundError:
        message = "spec file not found; check the path"
    except FileRefused as exc:
        message = f"{exc}; pass a spec file"
    except UnicodeDecodeError as exc:
        message = f"is not UTF-8 text ({exc.reason} at byte {exc.start})"
    except OSError as exc:
        message = f"cannot read the spec file: {exc.strerror or exc}"
    raise SpecError([Diagnostic(name or os.fspath(path), 0, 0, message)])
