"""The log files of attempts that run on remote workers, as their batches arrive.

A worker sends its attempts' log lines in batches (``worker_log``, checked by the hub);
each is appended to the attempt's ``log.txt`` under the server's home, where ``osmo logs``
reads local attempts' logs too. The server caps each file itself (``--log-limit``; the
oldest records are dropped behind a marker, ``osmo.worker.logs.CappedFile``), whatever the
worker's own cap: a worker cannot make the server keep more. Files stay open while their
attempt runs (at most 4,096 at once: the oldest is closed first and reopened on its next
batch). A batch that cannot be written (a full disk) is logged and lost.
"""

from __future__ import annotations

import logging
import threading

from osmo.layout import Home
from osmo.options import DEFAULT_LOG_LIMIT
from osmo.worker.logs import CappedFile

__all__ = ["RemoteLogs"]

_MAX_OPEN = 4096
log = logging.getLogger("osmo.server.workers")


class RemoteLogs:
    """Appends remote attempts' log batches to their ``log.txt`` (thread-safe).

    Args:
        home: the server's home.
        limit: bytes each attempt's log keeps at most.
    """

    def __init__(self, home: Home, limit: int = DEFAULT_LOG_LIMIT) -> None:
        self._home = home
        self._limit = limit
        self._lock = threading.Lock()
        self._open: dict[str, CappedFile] = {}

    def append(self, attempt_id: str, records: bytes) -> None:
        """Append a batch of ``attempt_id``'s records (a malformed id is ignored)."""
        with self._lock:
            file = self._open.get(attempt_id)
            if file is None:
                dirs = self._home.attempt_of(attempt_id)
                if dirs is None:
                    return  # not an attempt id
                dirs.log.parent.mkdir(parents=True, exist_ok=True)
                file = self._open[attempt_id] = CappedFile(dirs.log, self._limit)
                while len(self._open) > _MAX_OPEN:  # never more open than this
                    self._open.pop(next(iter(self._open))).close()
            try:
                file.append(records)
            except OSError as exc:
                log.warning("log of %s: batch lost: %s", attempt_id, exc)

    def end(self, attempt_id: str) -> None:
        """The attempt ended: close its file."""
        with self._lock:
            file = self._open.pop(attempt_id, None)
        if file is not None:
            file.close()

    def close(self) -> None:
        """Close every file."""
        with self._lock:
            for file in self._open.values():
                file.close()
            self._open.clear()
