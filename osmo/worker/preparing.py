"""How an attempt of the local pool is prepared: its runtime, its folder, its launch.

:class:`Preparing` is one of the parts :class:`osmo.worker.pool.LocalPool` is made of (see its
module docstring for the threads). ``prepare`` takes an attempt on the reactor and hands the
work to an I/O thread, in one straight line:

1. its runtime, chosen once (``osmo.runtime.choose.Runtimes``), and what that runtime shows
   the task (``Runtime.paths``);
2. its credentials (given, or looked up), its folder, files and inputs
   (``osmo.worker.transfer.make_ready``);
3. its log (opened on its first record) and its GPU indices (``osmo.worker.machine``);
4. its launch completed by its runtime (``Runtime.prepare``: a sandbox's view, a container's
   image, pulled if missing, its progress in the log);
5. with no barrier, its spawn right there (``Starting.spawn``), so the slots' spawns overlap
   and the reactor never waits on fork/exec;
6. its launch's notes written to its log (the log's file made) while it starts.

The outcome goes back to the reactor, which makes the attempt live and reports it prepared
(and started), applies a kill or a run that came meanwhile, or fails its start. Every
``prepare`` gets exactly one final report; a failed preparation leaves no credential file
and holds no GPU.
"""

from __future__ import annotations

import functools
import logging
from collections.abc import Callable, Mapping
from concurrent.futures import ThreadPoolExecutor
from dataclasses import replace

from osmo.artifacts import ArtifactStore
from osmo.errors import OsmoError
from osmo.layout import AttemptDirs, Home
from osmo.runtime.api import (
    Adopting,
    Attempt,
    Launch,
    ProcessHandle,
    Runtime,
    StartError,
    Terms,
)
from osmo.runtime.choose import Runtimes
from osmo.scheduler.types import (
    AttemptPrepared,
    AttemptStartFailed,
    AttemptWaiting,
    Event,
    PrepareAttempt,
)
from osmo.spec.model import ResourceSpec, TaskSpec
from osmo.worker.journal import Journal
from osmo.worker.live import Attempts, LiveAttempt
from osmo.worker.logs import LogWriter
from osmo.worker.machine import GpuSlots
from osmo.worker.reactor import Reactor
from osmo.worker.secrets import SecretLookup, Secrets, gather
from osmo.worker.starts import Starting, started_event
from osmo.worker.taskenv import with_threads
from osmo.worker.transfer import CredentialLookup, ManifestLookup, make_ready
from osmo.worker.workdir import remove_secret_files

__all__ = ["Preparing"]

_log = logging.getLogger("osmo.worker.pool")


class Preparing:
    """The pool's attempts being prepared (reactor thread, but its I/O-thread step).

    Args:
        home: osmo's home (attempts live under its ``runs/``).
        runtimes: the node's runtimes.
        attempts, reactor, io, emit: the pool's table, reactor, I/O threads and reports.
        starting: how a prepared attempt starts (and how one is killed).
        gpus: the pool's GPU assignment.
        env: the base environment of every command.
        task_secrets: credential name → payload, when ``prepare`` is not given them.
        credential_for: ``url -> credential`` for ``url`` inputs.
        artifacts: the artifact store inputs are copied from (None: none).
        input_manifests: input reference → its manifest, for inputs that are artifacts.
        log_sink: also gets ``(attempt id, records)`` for every log record written.
        log_limit: bytes each attempt's log keeps at most.
        journal: where an attempt whose runtime's launches outlive the node
            (``osmo.runtime.api.Adopting``) is journaled before it starts (None: nowhere).
    """

    def __init__(self, *, home: Home, runtimes: Runtimes, attempts: Attempts, reactor: Reactor,
                 io: ThreadPoolExecutor, emit: Callable[[Event], None], starting: Starting,
                 gpus: GpuSlots, env: Mapping[str, str],
                 task_secrets: SecretLookup | None, credential_for: CredentialLookup | None,
                 artifacts: ArtifactStore | None, input_manifests: ManifestLookup | None,
                 log_sink: Callable[[str, bytes], None] | None, log_limit: int,
                 journal: Journal | None = None) -> None:
        self._home, self._runtimes = home, runtimes
        self._attempts, self._reactor, self._io, self._emit = attempts, reactor, io, emit
        self._starting, self._gpus = starting, gpus
        self._env, self._task_secrets = env, task_secrets
        self._credential_for, self._artifacts = credential_for, artifacts
        self._input_manifests = input_manifests
        self._log_sink, self._log_limit = log_sink, log_limit
        self._journal = journal
        self._pending: dict[str, str | None] = {}  # attempt id → kill reason, if killed
        self._run_pending: set[str] = set()  # run() came while its folders were being made

    def prepare(self, cmd: PrepareAttempt, task: TaskSpec, secrets: Secrets | None,
                resources: ResourceSpec, terms: Terms | None = None) -> None:
        """Prepare an attempt (reactor thread); emits AttemptPrepared or AttemptStartFailed."""
        if cmd.attempt_id in self._attempts or cmd.attempt_id in self._pending:
            _log.warning("attempt %s is already active; prepare ignored", cmd.attempt_id)
            return
        self._attempts.again(cmd.attempt_id)
        self._pending[cmd.attempt_id] = None
        self._io.submit(self._prepare_io, cmd, task, secrets, resources, terms or Terms())

    def kill(self, attempt_id: str, reason: str) -> bool:
        """Kill an attempt being prepared, once it is (False: it is not being prepared)."""
        if attempt_id not in self._pending:
            return False
        self._pending[attempt_id] = self._pending[attempt_id] or reason
        return True

    def run(self, attempt_id: str) -> bool:
        """Run an attempt being prepared, once it is (False: it is not being prepared)."""
        if attempt_id not in self._pending:
            return False
        self._run_pending.add(attempt_id)
        return True

    def _prepare_io(self, cmd: PrepareAttempt, task: TaskSpec, secrets: Secrets | None,
                    resources: ResourceSpec, terms: Terms) -> None:
        """I/O thread: the steps of the module docstring; the outcome goes to the reactor."""
        launch: Launch | None = None
        log: LogWriter | None = None
        try:
            runtime = self._runtimes.choose(task)
            dirs = self._home.attempt(cmd.workflow_id, cmd.task, cmd.retry)
            if secrets is None:
                secrets = gather(task, self._task_secrets)
            paths = runtime.paths(cmd)
            placed, launch = make_ready(dirs, cmd, task, env=self._env, secrets=secrets,
                                        credential_for=self._credential_for,
                                        artifacts=self._artifacts,
                                        input_manifests=self._input_manifests, paths=paths)
            env = launch.env if paths.own_env else with_threads(launch.env, resources.cpu)
            launch = replace(launch, env=env, max_output_bytes=resources.storage)
            log = self._open_log(cmd, dirs, launch)
            gpus = self._gpus.take(cmd.attempt_id, resources.gpu) if resources.gpu else ()
            lookup = self._task_secrets if self._task_secrets is not None else secrets.get
            attempt = Attempt(placed, task, dirs, resources, gpus, lookup, terms,
                              waiting=functools.partial(self._waiting, cmd.attempt_id))
            launch = runtime.prepare(launch, attempt,
                                     progress=functools.partial(_pull_line, log))
            if self._journal is not None and isinstance(runtime, Adopting):
                self._journal.add(cmd, argv=launch.argv, image_id=launch.image_id,
                                  secrets=launch.secrets, max_output_bytes=resources.storage)
        except Exception as exc:  # every prepare must get its one final report
            message = str(exc) if isinstance(exc, OsmoError) else f"cannot prepare: {exc!r}"
            if log is not None:  # its runtime could not take it: say so where it is looked for
                log.line("osmo", f"start failed: {message}")
                log.close()
            if launch is not None:
                remove_secret_files(launch)
            self._gpus.give_back(cmd.attempt_id)
            self._reactor.call_soon(self._not_prepared, cmd.attempt_id, message)
            return
        started: ProcessHandle | str | None = None
        if cmd.run and self._pending.get(cmd.attempt_id) is None:
            # No barrier: spawn here, so the slots' spawns overlap and the reactor thread
            # (pipes, exits) never waits on fork/exec. A kill that came meanwhile is applied
            # by _prepared.
            try:
                started = self._starting.spawn(runtime, launch)
            except (StartError, OSError) as exc:
                started = str(exc)
            except Exception as exc:  # noqa: BLE001 - a bug: fail the start, report it
                _log.exception("starting %s failed", cmd.attempt_id)
                started = f"cannot start: {exc!r}"
        # Its log's first records (and so the file, an inode) are made here, while its command
        # starts, not on the reactor; the reactor reads the command's output after them.
        try:
            for note in launch.notes:
                log.line("osmo", note)
        except Exception:  # noqa: BLE001 - e.g. its log's sink: the attempt still goes on
            _log.exception("the notes of %s could not be logged", cmd.attempt_id)
        self._reactor.call_soon(self._prepared, cmd, task, dirs, launch, runtime, log, started)

    def _open_log(self, cmd: PrepareAttempt, dirs: AttemptDirs, launch: Launch) -> LogWriter:
        return self.open_log(cmd.attempt_id, dirs, launch.secrets)

    def open_log(self, attempt_id: str, dirs: AttemptDirs, secrets: tuple[str, ...]
                 ) -> LogWriter:
        """The attempt's log writer (the file is opened, or appended to, on its first record)."""
        sink = functools.partial(self._log_sink, attempt_id) if self._log_sink else None
        return LogWriter(dirs.log, secrets, sink, limit=self._log_limit)

    def journaled(self, attempt: LiveAttempt, shipped: dict[str, int] | None = None) -> None:
        """Count what ``attempt``'s log shipped, in the journal, if its launch outlives the node.

        ``shipped``: what an adopted attempt's previous life shipped.
        """
        if self._journal is not None and isinstance(attempt.runtime, Adopting):
            attempt.consumed = dict(shipped or {"stdout": 0, "stderr": 0})
            attempt.on_shipped = functools.partial(self._journal.shipped, attempt.id)

    def _waiting(self, attempt_id: str, reason: str) -> None:
        """Any thread: the attempt's cluster holds it (``reason``), or no longer (``""``)."""
        self._emit(AttemptWaiting(attempt_id, reason))

    def _not_prepared(self, attempt_id: str, message: str) -> None:
        """Reactor thread: the attempt could not be prepared; it fails to start."""
        self._pending.pop(attempt_id, None)
        self._run_pending.discard(attempt_id)
        self._attempts.remember(attempt_id)
        if self._journal is not None:
            self._journal.remove(attempt_id)
        self._emit(AttemptStartFailed(attempt_id, message))

    def _prepared(self, cmd: PrepareAttempt, task: TaskSpec, dirs: AttemptDirs, launch: Launch,
                  runtime: Runtime, log: LogWriter, started: ProcessHandle | str | None
                  ) -> None:
        """Reactor thread: the attempt is live; what came meanwhile is applied."""
        kill_reason = self._pending.pop(cmd.attempt_id, None)
        run_now = cmd.run or cmd.attempt_id in self._run_pending
        self._run_pending.discard(cmd.attempt_id)
        attempt = LiveAttempt(cmd.attempt_id, task, dirs, launch, log, runtime)
        self.journaled(attempt)
        self._attempts.add(attempt)
        if isinstance(started, ProcessHandle):
            self._starting.watch(attempt, started)
        if kill_reason is not None:  # killed while its folders were being made
            self._starting.kill(attempt, kill_reason)
            return
        self._emit(AttemptPrepared(attempt.id))
        if isinstance(started, ProcessHandle):
            self._emit(started_event(attempt.id, started))
        elif isinstance(started, str):
            self._starting.failed(attempt, started)
        elif run_now:  # no barrier holds it (or run() already came): start now
            self._starting.start(attempt)


def _pull_line(log: LogWriter, line: str) -> None:
    log.line("osmo", f"pull: {line}")
