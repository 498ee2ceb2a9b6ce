"""A pool's record of the commands it runs, so that its next life can kill their leftovers.

A task dies with its worker (``osmo.runtime.process.groups``: bwrap's ``--die-with-parent``, or a
parent-death signal) — except a sandbox still being set up when the worker is SIGKILLed:
bubblewrap then runs on under init, and starts the command. What may be left after a crash
— such a sandbox, an unsandboxed command's children — is found through this record: one line
per started command in ``<folder>/running``, ``<pid> <start time>`` (so a pid reused by an
unrelated process is never killed; ``osmo.runtime.process.proctable.kill_stale``), appended on the
spawning thread right after the spawn, before the start is reported. Appending a line costs a
``write`` (no file per command, no fsync: it must outlive the process, not the machine). The
file is emptied whenever no recorded command runs any more.

Both the server's local pool and a remote worker's keep one (``OSMO_HOME/procs``).
"""

from __future__ import annotations

import logging
import os
import threading
from pathlib import Path

from osmo.runtime.process.proctable import kill_stale, process_start_time

__all__ = ["ProcessRecords", "kill_recorded"]

_log = logging.getLogger("osmo.worker")

_FILE = "running"


class ProcessRecords:
    """The record of running commands in ``folder`` (made 0700 if missing)."""

    def __init__(self, folder: Path) -> None:
        self.folder = Path(folder)
        self.folder.mkdir(mode=0o700, parents=True, exist_ok=True)
        self._fd = os.open(self.folder / _FILE, os.O_WRONLY | os.O_APPEND | os.O_CREAT
                           | os.O_CLOEXEC, 0o600)
        self._live: set[int] = set()
        self._lock = threading.Lock()

    def add(self, pid: int, started: float | None = None) -> None:
        """Record a command just started (its pid leads its process group).

        ``started``: its start time on ``process_start_time``'s clock (read when omitted).
        """
        if started is None:
            started = process_start_time(pid)
            if started is None:
                return  # already gone: nothing can be left of it but its group, reaped by us
        with self._lock:
            if self._fd < 0:
                return  # closed: the pool is shutting down and kills what it starts
            os.write(self._fd, f"{pid} {started!r}\n".encode("ascii"))
            self._live.add(pid)

    def remove(self, pid: int) -> None:
        """Forget a command that has been reaped (the file is emptied when none is left)."""
        with self._lock:
            self._live.discard(pid)
            if not self._live and self._fd >= 0:
                os.ftruncate(self._fd, 0)

    def close(self) -> None:
        """Close the file (what it records stays for the next life)."""
        with self._lock:
            if self._fd >= 0:
                os.close(self._fd)
                self._fd = -1


def kill_recorded(folder: Path) -> int:
    """Kill the process groups a previous life left running; clear the record.

    Also reads the one-file-per-pid records of earlier versions (``<folder>/<pid>``).

    Returns:
        how many groups were signalled.
    """
    if not folder.is_dir():
        return 0
    records: list[tuple[str, str]] = []
    for entry in folder.iterdir():
        try:
            if entry.name == _FILE:
                records += [tuple(line.split(" ", 1)) for line in  # type: ignore[misc]
                            entry.read_text(encoding="ascii").splitlines() if " " in line]
            elif entry.name.isdigit():
                records.append((entry.name, entry.read_text(encoding="ascii")))
            else:
                continue
        except (OSError, ValueError):
            pass
        entry.unlink(missing_ok=True)
    killed = 0
    for pid, started in records:
        try:
            if kill_stale(int(pid), float(started)):
                killed += 1
                _log.warning("killed process group %s left by a previous run", pid)
        except ValueError:
            continue
    return killed
