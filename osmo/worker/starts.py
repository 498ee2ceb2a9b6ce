"""How an attempt of the local pool starts and stops: its spawn, its watch, its kill, its exit.

:class:`Starting` is one of the parts :class:`osmo.worker.pool.LocalPool` is made of (see its
module docstring for the threads). It spawns a prepared launch through the attempt's runtime
(``Runtime.start``; on an I/O thread when ``launch.waits``: a container group's peer waits
for its lead), records the pid before the start is reported (``osmo.worker.procs``), watches
the launch's pipes and its exit on the reactor, kills it (SIGTERM, SIGKILL after the grace)
and, once it ended, reaps it and hands the exit code to :class:`~osmo.worker.endings.Ending`.

A start whose sandbox could not be set up (bubblewrap failed before the command ran, e.g. a
mount vanished under it while containers started or stopped) is started again, up to
:data:`SETUP_TRIES` times in all with a growing pause; then the attempt fails to start (an
infrastructure error, exit code 3004), never with bwrap's exit code 1 as the command's.

A runtime may say, when it reaps a launch, that it never ran for good (``start_failed``: a
pod whose image cannot be pulled; the attempt fails to start) or that it was lost to its
infrastructure (``lost``: an evicted pod; ``AttemptLost``, rescheduled and not a retry).
"""

from __future__ import annotations

import functools
import logging
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor

from osmo.runtime.api import Launch, ProcessHandle, Runtime, StartError
from osmo.runtime.process.proctable import process_start_time
from osmo.scheduler.types import (
    AttemptExited,
    AttemptLost,
    AttemptStarted,
    AttemptStartFailed,
    Event,
)
from osmo.worker.checkpoints import start_checkpoints
from osmo.worker.endings import KILLED_BEFORE_START, Ending
from osmo.worker.live import AttemptState, LiveAttempt, streams
from osmo.worker.logs import exit_note
from osmo.worker.procs import ProcessRecords
from osmo.worker.reactor import Reactor
from osmo.worker.transfer import CredentialLookup

__all__ = ["SETUP_TRIES", "Starting", "started_event"]

_log = logging.getLogger("osmo.worker.pool")

SETUP_TRIES = 8
"""Starts of one attempt whose sandbox could not be set up, before it fails to start."""
_SETUP_PAUSE = 0.005  # seconds before the second try, doubled for each next one (0.6 s in all)


class Starting:
    """Starting, watching and stopping the pool's attempts (reactor thread, but ``spawn``).

    Args:
        reactor: the pool's reactor.
        io: the pool's I/O threads.
        emit: where reports go.
        ending: how an attempt ends.
        procs: where each spawned pid is recorded (None: nowhere).
        grace: seconds between SIGTERM and SIGKILL when an attempt is killed.
        credential_for: ``url -> credential`` for checkpoints to URLs.
    """

    def __init__(self, *, reactor: Reactor, io: ThreadPoolExecutor,
                 emit: Callable[[Event], None], ending: Ending, procs: ProcessRecords | None,
                 grace: float, credential_for: CredentialLookup | None) -> None:
        self._reactor, self._io, self._emit, self._ending = reactor, io, emit, ending
        self._procs, self._grace, self._credential_for = procs, grace, credential_for

    def spawn(self, runtime: Runtime, launch: Launch) -> ProcessHandle:
        """Start ``launch`` (any thread; an I/O thread when ``launch.waits``).

        The pid is recorded (``osmo.worker.procs``) before the start is reported.

        Raises:
            StartError: it cannot be started.
            OSError: nor its descriptors be made.
        """
        handle = runtime.start(launch)
        if self._procs is not None:
            self._procs.add(handle.pid, handle.started_at)
        return handle

    def start(self, attempt: LiveAttempt) -> None:
        """Start a prepared attempt (or one waiting to start again); report the start."""
        if attempt.state not in (AttemptState.PREPARED, AttemptState.STARTING):
            return  # killed meanwhile
        if attempt.launch.waits:  # it waits for another attempt: off the reactor
            attempt.state = AttemptState.STARTING
            self._io.submit(self._start_io, attempt)
            return
        try:
            handle = self.spawn(attempt.runtime, attempt.launch)
        except (StartError, OSError) as exc:
            self.failed(attempt, str(exc))
            return
        self.watch(attempt, handle)
        self._emit(started_event(attempt.id, handle))

    def _start_io(self, attempt: LiveAttempt) -> None:
        """I/O thread: spawn a launch that waits first; hand the outcome to the reactor."""
        if attempt.state is not AttemptState.STARTING:
            return  # killed meanwhile (a stale read is caught by _began)
        try:
            started: ProcessHandle | str = self.spawn(attempt.runtime, attempt.launch)
        except (StartError, OSError) as exc:
            started = str(exc)
        except Exception as exc:  # noqa: BLE001 - a bug: fail the start, report it
            _log.exception("starting %s failed", attempt.id)
            started = f"cannot start: {exc!r}"
        self._reactor.call_soon(self._began, attempt, started)

    def _began(self, attempt: LiveAttempt, started: ProcessHandle | str) -> None:
        if isinstance(started, str):
            if attempt.state is AttemptState.STARTING:
                self.failed(attempt, started)
            return
        if attempt.state is not AttemptState.STARTING:  # killed while it was spawned
            self.discard(attempt.runtime, started)
            return
        self.watch(attempt, started)
        self._emit(started_event(attempt.id, started))

    def failed(self, attempt: LiveAttempt, message: str) -> None:
        """Its launch could not be started: the attempt fails to start."""
        attempt.log.line("osmo", f"start failed: {message}")
        self._ending.finish(attempt, AttemptStartFailed(attempt.id, message))

    def discard(self, runtime: Runtime, handle: ProcessHandle) -> None:
        """Kill, reap and release a launch nobody watches any more."""
        runtime.kill(handle, force=True)
        self._reap(runtime, handle)
        runtime.release(handle)

    def watch(self, attempt: LiveAttempt, handle: ProcessHandle) -> None:
        """Watch a started launch's pipes and exit; start the attempt's checkpoints."""
        attempt.handle, attempt.state = handle, AttemptState.RUNNING
        reactor = self._reactor
        for fd, stream in streams(handle):
            attempt.open_fds.add(fd)
            reactor.add_reader(fd, lambda a=attempt, f=fd, s=stream: a.read(reactor, f, s))
        reactor.add_reader(handle.exit_fd, lambda a=attempt: self._exited(a))
        attempt.checkpoints = start_checkpoints(
            attempt.task, attempt.dirs, attempt.id, reactor=reactor, io=self._io,
            credential_for=self._credential_for, log=functools.partial(attempt.log.line, "osmo"))

    def kill(self, attempt: LiveAttempt, reason: str) -> None:
        """Kill ``attempt``: SIGTERM, SIGKILL after the grace; one not started ends at once."""
        if attempt.state is AttemptState.FINISHING or attempt.kill_reason is not None:
            return  # it already exited (its report is on the way), or it is being killed
        attempt.kill_reason = reason
        attempt.log.line("osmo", f"killed: {reason}")
        if attempt.state in (AttemptState.PREPARED, AttemptState.STARTING):
            event = AttemptExited(attempt.id, KILLED_BEFORE_START, None, f"killed: {reason}")
            self._ending.finish(attempt, event)
        elif attempt.handle is not None:
            attempt.runtime.kill(attempt.handle)
            attempt.escalation = self._reactor.call_later(self._grace, self._escalate, attempt)

    def stop(self, attempt: LiveAttempt) -> None:
        """The pool closes: kill a running attempt at once, reap and release it."""
        handle = attempt.handle
        if attempt.state is AttemptState.RUNNING and handle is not None:
            attempt.log.line("osmo", "killed: pool closed")
            self.discard(attempt.runtime, handle)

    def _escalate(self, attempt: LiveAttempt) -> None:
        if attempt.state is AttemptState.RUNNING and attempt.handle is not None:
            attempt.log.line("osmo", f"still running {self._grace:g}s after SIGTERM: SIGKILL")
            attempt.runtime.kill(attempt.handle, force=True)

    def _reap(self, runtime: Runtime, handle: ProcessHandle) -> int:
        code = runtime.reap(handle)
        if self._procs is not None:
            self._procs.remove(handle.pid)
        return code

    def _exited(self, attempt: LiveAttempt) -> None:
        handle = attempt.handle
        assert handle is not None
        self._reactor.remove_reader(handle.exit_fd)
        code = self._reap(attempt.runtime, handle)
        try:
            attempt.drain(self._reactor, handle)
            attempt.runtime.release(handle)
            if attempt.escalation is not None:
                attempt.escalation.cancel()
            if attempt.checkpoints is not None:
                attempt.checkpoints.stop()
            attempt.log.flush_partial()
            if attempt.kill_reason is None and (handle.start_failed or handle.lost):
                self._not_run(attempt, handle)
                return
            if handle.setup_failed:  # the command never ran
                if attempt.kill_reason is None:
                    self._setup_failed(attempt)  # try again, or fail its start
                    return
                code = KILLED_BEFORE_START
            attempt.log.line("osmo", exit_note(code))
        except Exception as exc:  # noqa: BLE001 - e.g. a full disk: still one final report
            _log.exception("finishing %s failed", attempt.id)
            self._ending.finish(attempt, AttemptExited(
                attempt.id, code, None, f"its end could not be recorded: {exc!r}"))
            return
        self._ending.exited(attempt, code)

    def _not_run(self, attempt: LiveAttempt, handle: ProcessHandle) -> None:
        """Its runtime says it never ran (it fails to start) or was lost (rescheduled)."""
        if handle.start_failed:
            self.failed(attempt, handle.start_failed)
            return
        message = handle.lost or "lost"
        attempt.log.line("osmo", f"lost: {message}")
        self._ending.finish(attempt, AttemptLost(attempt.id, message))

    def _setup_failed(self, attempt: LiveAttempt) -> None:
        """Its sandbox could not be set up and the command never ran: start it again, or fail.

        Until it starts again it waits as STARTING (a kill meanwhile ends it at once).
        """
        attempt.setup_failures += 1
        tail = attempt.stderr_tail.decode("utf-8", "replace").strip().splitlines()
        why = tail[-1] if tail else "bwrap exited 1 before the command ran"
        attempt.stderr_tail = b""
        if attempt.setup_failures >= SETUP_TRIES:
            self.failed(attempt, f"the sandbox could not be set up ({SETUP_TRIES} tries): {why}")
            return
        attempt.log.line("osmo", f"the sandbox could not be set up ({why}); trying again "
                                 f"({attempt.setup_failures + 1} of {SETUP_TRIES})")
        attempt.state, attempt.handle = AttemptState.STARTING, None
        self._reactor.call_later(_SETUP_PAUSE * 2 ** (attempt.setup_failures - 1),
                                 self.start, attempt)


def started_event(attempt_id: str, handle: ProcessHandle) -> AttemptStarted:
    """The start report, with the process (group) id and its start time.

    The server records them, so that a restarted server can kill what is left of it.
    """
    started = handle.started_at
    return AttemptStarted(attempt_id, handle.pid,
                          process_start_time(handle.pid) if started is None else started)
