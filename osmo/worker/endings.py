"""How an attempt of the local pool ends: its exit, its outputs, its final report.

A mixin of :class:`osmo.worker.pool.LocalPool`; see its module docstring for the threads.

Whatever happens after the process exits — a promotion or ingest that raises anything, a log
that cannot be written — the attempt gets exactly one ``AttemptExited`` (a failure carries
its reason; a successful exit whose outputs could not be stored fails with exit code 3005),
its credential files are deleted and its large input copies are removed, in every path.
"""

from __future__ import annotations

import collections
import logging
import signal
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor

from osmo.artifacts import ArtifactStore
from osmo.artifacts.fsops import remove_tree
from osmo.runtime.process.groups import ProcessHandle, Runtime
from osmo.scheduler.types import AttemptExited, AttemptStartFailed, Event
from osmo.spec.model import ExitAction
from osmo.worker.live import AttemptState, LiveAttempt
from osmo.worker.logs import exit_note
from osmo.worker.reactor import Reactor
from osmo.worker.transfer import CredentialLookup, DeliveryError, deliver
from osmo.worker.workdir import Launch, remove_secret_files

__all__ = ["KILLED_BEFORE_START", "AttemptEndings"]

_log = logging.getLogger("osmo.worker.pool")

_REMEMBER_FINISHED = 4096  # finished ids kept to ignore late run()/kill() for them
KILLED_BEFORE_START = 128 + signal.SIGKILL  # the exit code of an attempt killed before it ran


class AttemptEndings:
    """The ends of attempts (a mixin: the pool provides what is declared here)."""

    _emit: Callable[[Event], None]
    _reactor: Reactor
    _runtime: Runtime
    _io: ThreadPoolExecutor
    _attempts: dict[str, LiveAttempt]
    _finished: collections.OrderedDict[str, None]
    _artifacts: ArtifactStore | None
    _credential_for: CredentialLookup | None
    _max_output_files: int | None
    _reap: Callable[[ProcessHandle], int]
    _ended: Callable[[Launch], None]  # lets an ended container's GPUs and network go
    _setup_failed: Callable[[LiveAttempt], None]  # its sandbox could not be set up

    def _exited(self, attempt: LiveAttempt) -> None:
        handle = attempt.handle
        assert handle is not None
        self._reactor.remove_reader(handle.exit_fd)
        code = self._reap(handle)
        try:
            attempt.drain(self._reactor, handle)
            self._runtime.release(handle)
            if attempt.escalation is not None:
                attempt.escalation.cancel()
            if attempt.checkpoints is not None:
                attempt.checkpoints.stop()
            attempt.log.flush_partial()
            if handle.setup_failed:  # the command never ran
                if attempt.kill_reason is None:
                    self._setup_failed(attempt)  # try again, or fail its start
                    return
                code = KILLED_BEFORE_START
            attempt.log.line("osmo", exit_note(code))
        except Exception as exc:  # noqa: BLE001 - e.g. a full disk: still one final report
            _log.exception("finishing %s failed", attempt.id)
            self._finish(attempt, AttemptExited(attempt.id, code, None,
                                                f"its end could not be recorded: {exc!r}"))
            return
        if attempt.kill_reason is not None:
            self._finish(attempt, AttemptExited(attempt.id, code, None,
                                                f"killed: {attempt.kill_reason}"))
        elif attempt.task.exit_action(code) is not ExitAction.COMPLETE:
            self._finish(attempt, AttemptExited(attempt.id, code))
        else:
            attempt.state = AttemptState.FINISHING
            self._io.submit(self._promote_io, attempt, code)

    def _promote_io(self, attempt: LiveAttempt, code: int) -> None:
        """I/O thread: last checkpoint, promote the outputs; report the exit.

        Whatever is raised, the attempt gets its one final report (a failure, exit code
        3005, with the reason) and its credential files are deleted.
        """
        try:
            ref, manifest = deliver(attempt.dirs, attempt.task, checkpoints=attempt.checkpoints,
                                    artifacts=self._artifacts,
                                    credential_for=self._credential_for,
                                    max_bytes=attempt.launch.max_output_bytes,
                                    max_files=self._max_output_files)
            box = attempt.launch.container
            event = AttemptExited(attempt.id, code, ref, manifest=manifest,
                                  command=tuple(attempt.launch.argv),
                                  image_id=box.image if box is not None else None)
        except Exception as exc:  # noqa: BLE001 - DeliveryError, or a bug: still one report
            if not isinstance(exc, DeliveryError):
                _log.exception("promoting the outputs of %s failed", attempt.id)
            message = str(exc) if isinstance(exc, DeliveryError) else (
                f"outputs could not be promoted: {type(exc).__name__}: {exc}")
            self._reactor.call_soon(self._promoted, attempt,
                                    AttemptExited(attempt.id, code, None, message))
            return
        finally:
            remove_secret_files(attempt.launch)
        # Reported from here, one thread hop sooner; the reactor's bookkeeping follows (a
        # kill() that comes meanwhile finds it FINISHING and is ignored).
        self._emit(event)
        self._reactor.call_soon(self._finish, attempt, None)

    def _promoted(self, attempt: LiveAttempt, event: AttemptExited) -> None:
        try:
            if event.message:
                attempt.log.line("osmo", event.message)
        finally:
            self._finish(attempt, event)

    def _finish(self, attempt: LiveAttempt,
                event: AttemptExited | AttemptStartFailed | None) -> None:
        attempt.state = AttemptState.DONE
        try:
            attempt.log.close()
        finally:  # a log that cannot be written must not keep the report (or a secret) back
            remove_secret_files(attempt.launch)
            self._drop_scratch(attempt.launch)
            self._ended(attempt.launch)
            self._attempts.pop(attempt.id, None)
            self._remember(attempt.id)
            if event is not None:
                self._emit(event)

    def _drop_scratch(self, launch: Launch) -> None:
        """Delete an ended attempt's large input copies, off the reactor thread."""
        for folder in launch.scratch:
            try:
                self._io.submit(remove_tree, folder, ignore_errors=True)
            except RuntimeError:  # closing: they go when the attempt is prepared again
                return

    def _remember(self, attempt_id: str) -> None:
        self._finished[attempt_id] = None
        while len(self._finished) > _REMEMBER_FINISHED:
            self._finished.popitem(last=False)
