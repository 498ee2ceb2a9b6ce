"""The log files of attempts that run on remote workers, as their batches arrive.

A worker sends its attempts' log lines in batches (``worker_log``, checked by the hub);
each is appended to the attempt's ``log.txt`` under the server's home, where ``osmo logs``
reads local attempts' logs too. Files stay open while their attempt runs (at most 4,096 at
once: the oldest is closed first and reopened on its next batch).
"""

from __future__ import annotations

import os
import threading
from pathlib import Path

from osmo.layout import Home

__all__ = ["RemoteLogs"]

_MAX_OPEN = 4096


class RemoteLogs:
    """Appends remote attempts' log batches to their ``log.txt`` (thread-safe)."""

    def __init__(self, home: Path) -> None:
        self._home = Home(home)
        self._lock = threading.Lock()
        self._open: dict[str, int] = {}

    def append(self, attempt_id: str, records: bytes) -> None:
        """Append a batch of ``attempt_id``'s records (a malformed id is ignored)."""
        with self._lock:
            fd = self._open.get(attempt_id)
            if fd is None:
                dirs = self._home.attempt_of(attempt_id)
                if dirs is None:
                    return  # not an attempt id
                dirs.log.parent.mkdir(parents=True, exist_ok=True)
                fd = os.open(dirs.log, os.O_WRONLY | os.O_CREAT | os.O_APPEND | os.O_CLOEXEC,
                             0o644)
                self._open[attempt_id] = fd
                while len(self._open) > _MAX_OPEN:  # never more open than this
                    os.close(self._open.pop(next(iter(self._open))))
            os.write(fd, records)

    def end(self, attempt_id: str) -> None:
        """The attempt ended: close its file."""
        with self._lock:
            fd = self._open.pop(attempt_id, None)
        if fd is not None:
            os.close(fd)

    def close(self) -> None:
        """Close every file."""
        with self._lock:
            for fd in self._open.values():
                os.close(fd)
            self._open.clear()
