"""One attempt's live state in the local pool, and reading its output pipes.

Owned by the pool's reactor thread: nothing here is thread-safe, and nothing here decides
what happens to an attempt (that is ``osmo.worker.pool``).
"""

from __future__ import annotations

import enum
import os
from dataclasses import dataclass, field

from osmo.layout import AttemptDirs
from osmo.runtime.process.groups import ProcessHandle
from osmo.spec.model import TaskSpec
from osmo.worker.checkpoints import Checkpointer
from osmo.worker.logs import LogWriter
from osmo.worker.reactor import Reactor, Timer
from osmo.worker.workdir import Launch

__all__ = ["AttemptState", "LiveAttempt"]

_READ_SIZE = 65536
_DRAIN_READS = 64  # at exit, read at most this many chunks more per pipe
_TAIL = 512  # bytes of stderr kept: a sandbox's setup failure quotes bwrap's message


class AttemptState(enum.Enum):
    """Where an attempt is in the pool."""

    PREPARED = "prepared"
    STARTING = "starting"  # a container group's peer, waiting for its lead to run
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
    state: AttemptState = AttemptState.PREPARED
    handle: ProcessHandle | None = None
    open_fds: set[int] = field(default_factory=set)
    kill_reason: str | None = None
    escalation: Timer | None = None
    checkpoints: Checkpointer | None = None
    setup_failures: int = 0  # starts whose sandbox could not be set up
    stderr_tail: bytes = b""  # the end of what was read from stderr (at most 2 x _TAIL)

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
        for fd, stream in ((handle.stdout_fd, "stdout"), (handle.stderr_fd, "stderr")):
            for _ in range(_DRAIN_READS):
                if not self.read(reactor, fd, stream):
                    break
            self.unwatch(reactor, fd)
