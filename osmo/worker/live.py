"""The local pool's attempts: each one's live state, their table, and reading output pipes.

Owned by the pool's reactor thread: nothing here is thread-safe (but for the one read
:meth:`Attempts.running` documents), and nothing here decides what happens to an attempt
(that is ``osmo.worker.pool`` and its parts).
"""

from __future__ import annotations

import collections
import enum
import os
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field

from osmo.layout import AttemptDirs
from osmo.runtime.api import Launch, ProcessHandle, Runtime
from osmo.spec.model import TaskSpec
from osmo.worker.checkpoints import Checkpointer
from osmo.worker.logs import LogWriter
from osmo.worker.reactor import Reactor, Timer

__all__ = ["AttemptState", "Attempts", "LiveAttempt", "Running", "streams"]

_REMEMBER_FINISHED = 4096  # finished ids kept to ignore late run()/kill() for them

_READ_SIZE = 65536
_DRAIN_READS = 64  # at exit, read at most this many chunks more per pipe
_TAIL = 512  # bytes of stderr kept: a sandbox's setup failure quotes bwrap's message


class AttemptState(enum.Enum):
    """Where an attempt is in the pool."""

    PREPARED = "prepared"
    STARTING = "starting"  # waiting to start: for its lead (a container group's peer), or a retry
    RUNNING = "running"
    FINISHING = "finishing"  # exited; outputs being promoted on an I/O thread
    DONE = "done"


@dataclass(eq=False)
class LiveAttempt:
    """One attempt's live state (reactor thread only)."""

    id: str
    task: TaskSpec
    dirs: AttemptDirs
    launch: Launch
    log: LogWriter
    runtime: Runtime
    state: AttemptState = AttemptState.PREPARED
    handle: ProcessHandle | None = None
    open_fds: set[int] = field(default_factory=set)
    kill_reason: str | None = None
    escalation: Timer | None = None
    checkpoints: Checkpointer | None = None
    setup_failures: int = 0  # starts whose sandbox could not be set up
    stderr_tail: bytes = b""  # the end of what was read from stderr (at most 2 x _TAIL)
    # a journaled attempt (its launch outlives the node): bytes of stdout and stderr read,
    # and where the bytes logged whole so far are told (``osmo.worker.journal``)
    consumed: dict[str, int] | None = None
    on_shipped: Callable[[dict[str, int]], None] | None = None

    def read(self, reactor: Reactor, fd: int, stream: str) -> bool:
        """Log one chunk from a pipe; False when nothing was there (closed at EOF)."""
        if fd not in self.open_fds:
            return False
        try:
            data = os.read(fd, _READ_SIZE)
        except BlockingIOError:
            return False
        if data:
            self.log.write(stream, data)
            if stream == "stderr":
                self.stderr_tail = self.stderr_tail[-_TAIL:] + data[-_TAIL:]
            if self.consumed is not None and stream in self.consumed:
                self.consumed[stream] += len(data)
                if self.on_shipped is not None:
                    self.on_shipped({name: read - self.log.pending(name)
                                     for name, read in self.consumed.items()})
        else:
            self.unwatch(reactor, fd)
        return bool(data)

    def unwatch(self, reactor: Reactor, fd: int) -> None:
        """Stop reading ``fd``."""
        self.open_fds.discard(fd)
        reactor.remove_reader(fd)

    def drain(self, reactor: Reactor, handle: ProcessHandle) -> None:
        """Read what the pipes still hold, then stop watching them.

        Bounded: a process that escaped the group (``setsid``) and keeps writing to an
        inherited pipe is not waited for.
        """
        for fd, stream in streams(handle):
            for _ in range(_DRAIN_READS):
                if not self.read(reactor, fd, stream):
                    break
            self.unwatch(reactor, fd)


def streams(handle: ProcessHandle) -> list[tuple[int, str]]:
    """The handle's pipes and the log stream each goes to (its notes are osmo's lines)."""
    found = [(handle.stdout_fd, "stdout"), (handle.stderr_fd, "stderr")]
    return [*found, (handle.notes_fd, "osmo")] if handle.notes_fd >= 0 else found


@dataclass(frozen=True)
class Running:
    """A running attempt as another thread may see it (an exec or port-forward session)."""

    runtime: Runtime
    launch: Launch
    handle: ProcessHandle


class Attempts:
    """The pool's live attempts by id, and the ids of those that finished lately."""

    def __init__(self) -> None:
        self._live: dict[str, LiveAttempt] = {}
        self._finished: collections.OrderedDict[str, None] = collections.OrderedDict()

    def get(self, attempt_id: str) -> LiveAttempt | None:
        """The live attempt ``attempt_id`` (None: not live here)."""
        return self._live.get(attempt_id)

    def __contains__(self, attempt_id: object) -> bool:
        return attempt_id in self._live

    def __iter__(self) -> Iterator[LiveAttempt]:
        return iter(list(self._live.values()))

    def add(self, attempt: LiveAttempt) -> None:
        """``attempt`` is live (prepared)."""
        self._live[attempt.id] = attempt

    def drop(self, attempt_id: str) -> None:
        """``attempt_id`` ended: it is not live any more, and remembered as finished."""
        self._live.pop(attempt_id, None)
        self.remember(attempt_id)

    def remember(self, attempt_id: str) -> None:
        """Remember ``attempt_id`` as finished (late run or kill orders are ignored)."""
        self._finished[attempt_id] = None
        while len(self._finished) > _REMEMBER_FINISHED:
            self._finished.popitem(last=False)

    def finished(self, attempt_id: str) -> bool:
        """Whether ``attempt_id`` finished here lately."""
        return attempt_id in self._finished

    def again(self, attempt_id: str) -> None:
        """``attempt_id`` is prepared again (after a server restart): not finished now."""
        self._finished.pop(attempt_id, None)

    def clear(self) -> None:
        """Forget every live attempt (the pool closed)."""
        self._live.clear()

    def running(self, attempt_id: str) -> Running | None:
        """``attempt_id``'s runtime, launch and handle while it runs (None otherwise).

        From any thread: one read of the table (atomic under the GIL), then of one
        attempt's fields.
        """
        attempt = self._live.get(attempt_id)
        if attempt is None or attempt.state is not AttemptState.RUNNING:
            return None
        handle = attempt.handle
        return Running(attempt.runtime, attempt.launch, handle) if handle is not None else None
