"""Checkpoints: periodic uploads of a folder a running task writes, and a last one at its end.

``checkpoint: - {path, url, frequency, regex?}``: while the task runs, every ``frequency``
the folder at ``path`` (tokens resolved; ``{{output}}`` is the attempt's output folder; a
relative path is under the working folder) is uploaded to ``url`` through ``osmo.urls`` —
each upload replaces the previous one and ends with the completion marker, so a reader
always sees the last complete checkpoint. A periodic upload that fails is logged and tried
again next time. When the task exits successfully a last upload runs before its outputs are
promoted; if that one fails the task fails (it is never COMPLETED with a partial upload).
A folder that does not exist yet is skipped.

Timers run on the pool's reactor thread; uploads on its I/O threads, one at a time per
checkpoint (a lock), never overlapping the last upload.
"""

from __future__ import annotations

import threading
from collections.abc import Callable
from concurrent.futures import Executor
from dataclasses import dataclass
from pathlib import Path

from osmo.errors import OsmoError
from osmo.layout import AttemptDirs
from osmo.spec.model import TaskSpec
from osmo.spec.tokens import substitute
from osmo.spec.units import parse_duration
from osmo.urls import for_url
from osmo.worker.reactor import Reactor, Timer
from osmo.worker.transfer import CredentialLookup

__all__ = ["Checkpoint", "Checkpointer", "plan", "start_checkpoints"]


@dataclass(frozen=True)
class Checkpoint:
    """One resolved ``checkpoint`` entry."""

    folder: Path
    url: str
    every: float
    regex: str | None


def plan(task: TaskSpec, dirs: AttemptDirs, workflow_id: str) -> list[Checkpoint]:
    """The task's checkpoints with their folders resolved for this attempt."""

    def resolve(token: str) -> str | None:
        if token == "output":
            return str(dirs.output_partial)
        return workflow_id if token == "workflow_id" else None

    out = []
    for entry in task.checkpoint:
        folder = Path(substitute(str(entry["path"]), resolve))
        url = substitute(str(entry["url"]), resolve)
        out.append(Checkpoint(folder if folder.is_absolute() else dirs.work / folder, url,
                              float(parse_duration(entry["frequency"])), entry.get("regex")))
    return out


class Checkpointer:
    """Drives an attempt's checkpoints (see the module docstring).

    Args:
        log: writes an osmo log line; called on the reactor thread only.
    """

    def __init__(self, checkpoints: list[Checkpoint], *, reactor: Reactor, io: Executor,
                 credential_for: CredentialLookup | None, log: Callable[[str], None]) -> None:
        self._checkpoints = checkpoints
        self._reactor = reactor
        self._io = io
        self._credential_for = credential_for
        self._log = log
        self._locks = [threading.Lock() for _ in checkpoints]
        self._timers: dict[int, Timer] = {}
        self._stopped = False

    def start(self) -> None:
        """Schedule the periodic uploads (reactor thread)."""
        for i, cp in enumerate(self._checkpoints):
            self._timers[i] = self._reactor.call_later(cp.every, self._due, i)

    def stop(self) -> None:
        """No more periodic uploads (reactor thread)."""
        self._stopped = True
        for timer in self._timers.values():
            timer.cancel()

    def final(self) -> str | None:
        """Upload every checkpoint once more (I/O thread); the first error, or None."""
        for i in range(len(self._checkpoints)):
            error = self._upload(i)
            if error is not None:
                return error
        return None

    def _due(self, i: int) -> None:
        if not self._stopped:
            self._io.submit(self._periodic, i)

    def _periodic(self, i: int) -> None:
        error = self._upload(i)
        self._reactor.call_soon(self._done, i, error)

    def _done(self, i: int, error: str | None) -> None:
        cp = self._checkpoints[i]
        self._log(f"checkpoint to {cp.url} failed (retried next time): {error}" if error
                  else f"checkpoint uploaded to {cp.url}")
        if not self._stopped:
            self._timers[i] = self._reactor.call_later(cp.every, self._due, i)

    def _upload(self, i: int) -> str | None:
        cp = self._checkpoints[i]
        with self._locks[i]:
            if not cp.folder.is_dir():
                return None
            try:
                remote = for_url(cp.url, self._credential_for(cp.url)
                                 if self._credential_for else None)
                remote.upload(cp.folder, regex=cp.regex)
            except (OSError, OsmoError) as exc:
                return str(exc)
        return None


def start_checkpoints(task: TaskSpec, dirs: AttemptDirs, attempt_id: str, *, reactor: Reactor,
                      io: Executor, credential_for: CredentialLookup | None,
                      log: Callable[[str], None]) -> Checkpointer | None:
    """Start the checkpoints of an attempt that just started running (None if it has none)."""
    if not task.checkpoint:
        return None
    checkpointer = Checkpointer(plan(task, dirs, attempt_id.rsplit(":", 2)[0]), reactor=reactor,
                                io=io, credential_for=credential_for, log=log)
    checkpointer.start()
    return checkpointer
