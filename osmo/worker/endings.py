"""How an attempt of the local pool ends: its exit, its outputs, its one final report.

:class:`Ending` is one of the parts :class:`osmo.worker.pool.LocalPool` is made of (see its
module docstring for the threads). Whatever happens after the launch ended — a promotion or
ingest that raises anything, a log that cannot be written — the attempt gets exactly one
``AttemptExited`` (a failure carries its reason; a successful exit whose outputs could not be
stored fails with exit code 3005). In every path, before that report, its credential files
are deleted, its GPUs are free again and its runtime lets go of what it held for it
(``Runtime.cleanup``, which returns at once: a container group's network is removed in the
runtime's background); its large input copies are removed on an I/O thread.
"""

from __future__ import annotations

import logging
import signal
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor

from osmo.artifacts import ArtifactStore
from osmo.artifacts.fsops import remove_tree
from osmo.scheduler.types import AttemptExited, AttemptLost, AttemptStartFailed, Event
from osmo.spec.model import ExitAction
from osmo.worker.journal import Journal
from osmo.worker.live import Attempts, AttemptState, LiveAttempt
from osmo.worker.machine import GpuSlots
from osmo.worker.reactor import Reactor
from osmo.worker.transfer import CredentialLookup, DeliveryError, deliver
from osmo.worker.workdir import remove_secret_files

__all__ = ["KILLED_BEFORE_START", "Ending"]

_log = logging.getLogger("osmo.worker.pool")

KILLED_BEFORE_START = 128 + signal.SIGKILL  # the exit code of an attempt killed before it ran


class Ending:
    """The ends of the pool's attempts (reactor thread, but for its own I/O-thread steps).

    Args:
        attempts: the pool's table.
        reactor: the pool's reactor.
        io: the pool's I/O threads.
        emit: where reports go.
        gpus: the pool's GPU assignment (an ended attempt's indices are free again).
        artifacts: where promoted outputs are ingested (None: not ingested).
        credential_for: ``url -> credential`` for ``url`` outputs.
        max_output_files: the most files one attempt's output may hold.
        journal: where attempts whose launches outlive the node are journaled (their
            entry goes when they end; None: none is).
    """

    def __init__(self, *, attempts: Attempts, reactor: Reactor, io: ThreadPoolExecutor,
                 emit: Callable[[Event], None], gpus: GpuSlots,
                 artifacts: ArtifactStore | None, credential_for: CredentialLookup | None,
                 max_output_files: int | None, journal: Journal | None = None) -> None:
        self._attempts, self._reactor, self._io, self._emit = attempts, reactor, io, emit
        self._gpus = gpus
        self._artifacts, self._credential_for = artifacts, credential_for
        self._max_output_files = max_output_files
        self._journal = journal

    def exited(self, attempt: LiveAttempt, code: int) -> None:
        """Its launch ended with ``code`` (reaped and logged): report it, or promote first."""
        if attempt.kill_reason is not None:
            self.finish(attempt, AttemptExited(attempt.id, code, None,
                                               f"killed: {attempt.kill_reason}"))
        elif attempt.task.exit_action(code) is not ExitAction.COMPLETE:
            self.finish(attempt, AttemptExited(attempt.id, code))
        elif attempt.handle is not None and attempt.handle.output_failed:
            message = f"outputs could not be taken back: {attempt.handle.output_failed}"
            attempt.log.line("osmo", message)
            self.finish(attempt, AttemptExited(attempt.id, code, None, message))
        else:
            attempt.state = AttemptState.FINISHING
            self._io.submit(self._promote_io, attempt, code)

    def finish(self, attempt: LiveAttempt,
               event: AttemptExited | AttemptStartFailed | AttemptLost | None) -> None:
        """The attempt is over: its log closes, what it holds goes, ``event`` is reported."""
        attempt.state = AttemptState.DONE
        try:
            attempt.log.close()
        finally:  # a log that cannot be written must not keep the report (or a secret) back
            remove_secret_files(attempt.launch)
            if self._journal is not None:
                self._journal.remove(attempt.id)
            self._gpus.give_back(attempt.id)
            self._let_go(attempt)
            self._attempts.drop(attempt.id)
            if event is not None:
                self._emit(event)

    def forget(self, attempt_id: str) -> None:
        """An attempt that will not end here (not adopted): its journal entry goes."""
        if self._journal is not None:
            self._journal.remove(attempt_id)

    def abandon(self, attempt: LiveAttempt) -> None:
        """The pool closes with ``attempt`` live: its log closes, its secret files go.

        Nothing is reported; the runtimes' ``close`` removes what they still hold.
        """
        try:
            attempt.log.close()
        finally:
            remove_secret_files(attempt.launch)

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
            event = AttemptExited(attempt.id, code, ref, manifest=manifest,
                                  command=tuple(attempt.launch.argv),
                                  image_id=attempt.launch.image_id)
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
        self._reactor.call_soon(self.finish, attempt, None)

    def _promoted(self, attempt: LiveAttempt, event: AttemptExited) -> None:
        try:
            if event.message:
                attempt.log.line("osmo", event.message)
        finally:
            self.finish(attempt, event)

    def _let_go(self, attempt: LiveAttempt) -> None:
        """Its runtime lets go of it; its large input copies go, off the reactor thread."""
        try:
            attempt.runtime.cleanup(attempt.launch)
        except Exception:  # noqa: BLE001 - a runtime's bug must not keep the report back
            _log.exception("the runtime could not clean up after %s", attempt.id)
        for folder in attempt.launch.scratch:
            try:
                self._io.submit(remove_tree, folder, ignore_errors=True)
            except RuntimeError:  # closing: they go when the attempt is prepared again
                return
