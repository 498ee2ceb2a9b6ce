"""A worker's record of the commands it runs, so that its next life can kill their leftovers.

A task dies with its worker (``osmo.runtime.process``: bwrap's ``--die-with-parent``, or a
parent-death signal). What may still be left after a crash — an unsandboxed command's
children, a process that escaped its parent's death — is found through this record: one
file per running command, ``<folder>/<pid>``, holding the process's start time (so a pid
reused by an unrelated process is never killed; ``osmo.runtime.proctable.kill_stale``). The
file is written when the command starts and removed once it has been reaped.

The server's local pool does not need it: the server records each attempt's pid and start
time in its store and kills leftovers on restart (``osmo.server.recovery``).
"""

from __future__ import annotations

import logging
import os
from pathlib import Path

from osmo.runtime.proctable import kill_stale, process_start_time

__all__ = ["ProcessRecords", "kill_recorded"]

_log = logging.getLogger("osmo.worker")


class ProcessRecords:
    """The folder of running commands' records (made 0700 if missing)."""

    def __init__(self, folder: Path) -> None:
        self.folder = Path(folder)
        self.folder.mkdir(mode=0o700, parents=True, exist_ok=True)

    def add(self, pid: int) -> None:
        """Record a command just started (its pid leads its process group)."""
        started = process_start_time(pid)
        if started is None:
            return  # already gone: nothing can be left of it but its group, reaped by us
        temp = self.folder / f".{pid}.tmp"
        temp.write_text(repr(started), encoding="ascii")
        os.replace(temp, self.folder / str(pid))

    def remove(self, pid: int) -> None:
        """Forget a command that has been reaped."""
        (self.folder / str(pid)).unlink(missing_ok=True)


def kill_recorded(folder: Path) -> int:
    """Kill the process groups a previous life of this worker left running; clear the record.

    Returns:
        how many groups were signalled.
    """
    if not folder.is_dir():
        return 0
    killed = 0
    for entry in folder.iterdir():
        if entry.name.isdigit():
            try:
                started = float(entry.read_text(encoding="ascii"))
            except (OSError, ValueError):
                started = None
            if started is not None and kill_stale(int(entry.name), started):
                killed += 1
                _log.warning("killed process group %s left by a previous run", entry.name)
        entry.unlink(missing_ok=True)
    return killed
