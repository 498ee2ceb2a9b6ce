"""How an attempt of the local pool starts: its preparation, its spawn, its watch.

A mixin of :class:`osmo.worker.pool.LocalPool` (over :class:`AttemptEndings`, how it ends);
see the pool's module docstring for the threads. ``prepare`` makes the attempt's folder on an
I/O thread (``osmo.worker.transfer.make_ready``) and, with no barrier, spawns it there too, so
the slots' spawns overlap and the reactor thread never waits on fork/exec; a container peer
starts once its group's lead runs.

A start whose sandbox could not be set up (bubblewrap failed before the command ran, e.g. a
mount vanished under it while containers started or stopped) is started again, up to
:data:`SETUP_TRIES` times in all with a growing pause; then the attempt fails to start (an
infrastructure error, exit code 3004), never with bwrap's exit code 1 as the command's.
"""

from __future__ import annotations

import functools
import logging
from collections.abc import Callable, Mapping
from dataclasses import replace
from pathlib import Path

from osmo.errors import OsmoError
from osmo.layout import AttemptDirs, Home
from osmo.runtime.process.groups import ProcessHandle, StartError
from osmo.runtime.process.proctable import process_start_time
from osmo.runtime.process.sandbox import Sandbox
from osmo.scheduler.types import (
    AttemptPrepared,
    AttemptStarted,
    AttemptStartFailed,
    Node,
    PrepareAttempt,
)
from osmo.spec.model import ResourceSpec, TaskSpec
from osmo.worker.checkpoints import start_checkpoints
from osmo.worker.container_images import registry_auth
from osmo.worker.containers import ContainerTasks
from osmo.worker.endings import AttemptEndings
from osmo.worker.live import AttemptState, LiveAttempt
from osmo.worker.logs import LogWriter, image_note
from osmo.worker.procs import ProcessRecords
from osmo.worker.secrets import SecretLookup, Secrets, gather
from osmo.worker.transfer import ManifestLookup, make_ready
from osmo.worker.workdir import Launch, remove_secret_files

__all__ = ["SETUP_TRIES", "AttemptStarts"]

_log = logging.getLogger("osmo.worker.pool")

SETUP_TRIES = 8
"""Starts of one attempt whose sandbox could not be set up, before it fails to start."""
_SETUP_PAUSE = 0.005  # seconds before the second try, doubled for each next one (0.6 s in all)


class AttemptStarts(AttemptEndings):
    """Preparing, starting and watching attempts (the pool's state is declared here)."""

    _layout: Home
    _env: Mapping[str, str]
    _task_secrets: SecretLookup | None
    _input_manifests: ManifestLookup | None
    _log_sink: Callable[[str, bytes], None] | None
    _log_limit: int
    _containers: ContainerTasks | None
    _procs: ProcessRecords | None
    _hidden: list[Path]
    _masked: list[Path]
    sandbox: Sandbox | None
    _sandbox_note: str | None  # for each process task's log: no sandbox, no outbound network
    _preparing: dict[str, str | None]
    _run_pending: set[str]
    _kill: Callable[[str, str], None]
    node: Callable[[], Node]

    def _spawn(self, launch: Launch, *, wait: bool = False) -> ProcessHandle:
        """Start a launch (any thread): in its container, or as a (sandboxed) process.

        ``wait``: on an I/O thread (a container peer may wait for its lead). The pid is
        recorded (``osmo.worker.procs``) before the start is reported.
        """
        if launch.container is None or self._containers is None:
            handle = self._runtime.start(launch.argv, cwd=launch.cwd, env=launch.env,
                                         view=launch.view)
        else:
            handle = self._containers.start(launch, wait_for_lead=wait)
        if self._procs is not None:
            self._procs.add(handle.pid, handle.started_at)
        return handle

    def _prepare(self, cmd: PrepareAttempt, task: TaskSpec, secrets: Secrets | None,
                 resources: ResourceSpec) -> None:
        if cmd.attempt_id in self._attempts or cmd.attempt_id in self._preparing:
            _log.warning("attempt %s is already active; prepare ignored", cmd.attempt_id)
            return
        self._finished.pop(cmd.attempt_id, None)
        self._preparing[cmd.attempt_id] = None
        self._io.submit(self._prepare_io, cmd, task, secrets, resources)

    def _prepare_io(self, cmd: PrepareAttempt, task: TaskSpec, secrets: Secrets | None,
                    resources: ResourceSpec) -> None:
        """I/O thread: make the folders and files; hand the outcome back to the reactor.

        A container task's log is opened here, before its image is resolved, so that a
        pull's progress reaches it line by line (the writer is the reactor's afterwards).
        """
        log: LogWriter | None = None
        try:
            dirs = self._layout.attempt(cmd.workflow_id, cmd.task, cmd.retry)
            if secrets is None:
                secrets = gather(task, self._task_secrets)
            boxed = self._containers is not None and self._containers.applies(task)
            placed = self._containers.placement(cmd) if self._containers and boxed else cmd
            launch = make_ready(dirs, placed, task, env=self._env, secrets=secrets,
                                credential_for=self._credential_for, artifacts=self._artifacts,
                                input_manifests=self._input_manifests,
                                hide=tuple(self._hidden) if self.sandbox and not boxed else None,
                                masked=tuple(self._masked),
                                owner=self.sandbox.owner if self.sandbox else None, boxed=boxed)
            launch = replace(launch, max_output_bytes=resources.storage)
            if self._containers is not None and boxed:
                log = self._open_log(cmd, dirs, launch)
                pulled = functools.partial(_pull_line, log)
                launch = self._containers.finish(
                    launch, cmd, task, dirs, request=resources, gpus=self.node().capacity.gpu,
                    auth=registry_auth(task, self._task_secrets if self._task_secrets
                                       is not None else secrets.get), progress=pulled)
        except Exception as exc:  # every prepare must get its one final report
            message = str(exc) if isinstance(exc, OsmoError) else f"cannot prepare: {exc!r}"
            if log is not None:
                log.line("osmo", f"start failed: {message}")
                log.close()
            self._reactor.call_soon(self._prepared, cmd, task, None, None, message)
            return
        started: ProcessHandle | str | None = None
        if cmd.run and self._preparing.get(cmd.attempt_id) is None:
            # No barrier: spawn here, so the slots' spawns overlap and the reactor thread
            # (pipes, exits) never waits on fork/exec. A kill that came meanwhile is applied
            # by _prepared.
            try:
                started = self._spawn(launch, wait=True)
            except (StartError, OSError) as exc:
                started = str(exc)
            except Exception as exc:  # noqa: BLE001 - a bug: fail the start, report it
                _log.exception("starting %s failed", cmd.attempt_id)
                started = f"cannot start: {exc!r}"
        self._reactor.call_soon(self._prepared, cmd, task, dirs, launch, None, started, log)

    def _open_log(self, cmd: PrepareAttempt, dirs: AttemptDirs, launch: Launch) -> LogWriter:
        """The attempt's log writer (opened on its first record; raises OSError if it can't)."""
        sink = functools.partial(self._log_sink, cmd.attempt_id) if self._log_sink else None
        return LogWriter(dirs.log, launch.secrets, sink, limit=self._log_limit)

    def _prepared(self, cmd: PrepareAttempt, task: TaskSpec, dirs: AttemptDirs | None,
                  launch: Launch | None, error: str | None,
                  started: ProcessHandle | str | None = None,
                  log: LogWriter | None = None) -> None:
        kill_reason = self._preparing.pop(cmd.attempt_id, None)
        run_now = cmd.run or cmd.attempt_id in self._run_pending
        self._run_pending.discard(cmd.attempt_id)
        if error is not None or dirs is None or launch is None:
            self._remember(cmd.attempt_id)
            self._emit(AttemptStartFailed(cmd.attempt_id, error or "cannot prepare"))
            return
        try:
            log = log or self._open_log(cmd, dirs, launch)
        except OSError as exc:  # no log, no attempt: undo what preparing made, report once
            if isinstance(started, ProcessHandle):
                self._runtime.kill(started, force=True)
                self._reap(started)
                self._runtime.release(started)
            remove_secret_files(launch)
            self._ended(launch)
            self._remember(cmd.attempt_id)
            self._emit(AttemptStartFailed(cmd.attempt_id, f"cannot write its log: {exc}"))
            return
        attempt = LiveAttempt(cmd.attempt_id, task, dirs, launch, log)
        for note in launch.notes:
            attempt.log.line("osmo", note)
        if self._sandbox_note is not None and launch.container is None:
            attempt.log.line("osmo", self._sandbox_note)
        if task.image and launch.container is None:
            attempt.log.line("osmo", image_note(task.image))
        self._attempts[attempt.id] = attempt
        if isinstance(started, ProcessHandle):
            self._watch(attempt, started)
        if kill_reason is not None:  # killed while its folders were being made
            self._kill(attempt.id, kill_reason)
            return
        self._emit(AttemptPrepared(attempt.id))
        if isinstance(started, ProcessHandle):
            self._emit(_started(attempt.id, started))
        elif isinstance(started, str):
            attempt.log.line("osmo", f"start failed: {started}")
            self._finish(attempt, AttemptStartFailed(attempt.id, started))
        elif run_now:  # no barrier holds it (or run() already came): start now
            self._run(attempt.id)

    def _run(self, attempt_id: str) -> None:
        if attempt_id in self._preparing:
            self._run_pending.add(attempt_id)
            return
        attempt = self._attempts.get(attempt_id)
        if attempt is None:
            if attempt_id not in self._finished:
                self._remember(attempt_id)
                self._emit(AttemptStartFailed(attempt_id, "attempt was not prepared here"))
            return
        if attempt.state is not AttemptState.PREPARED:
            return
        launch = attempt.launch
        if launch.container is not None and launch.container.labels.get("osmo.lead") == "0":
            # a peer starts once its lead runs: wait off the reactor, then start (below)
            attempt.state = AttemptState.STARTING
            self._io.submit(self._after_lead, attempt)
            return
        self._start(attempt)

    def _after_lead(self, attempt: LiveAttempt) -> None:
        """I/O thread: wait for the group's lead to run, then start ``attempt``."""
        if self._containers is not None and attempt.launch.container is not None:
            self._containers.wait_for_lead(attempt.launch.container)
        self._reactor.call_soon(self._start, attempt)

    def _setup_failed(self, attempt: LiveAttempt) -> None:
        """Its sandbox could not be set up and the command never ran: start it again, or fail.

        Until it starts again it waits as STARTING (a kill meanwhile ends it at once).
        """
        attempt.setup_failures += 1
        tail = attempt.stderr_tail.decode("utf-8", "replace").strip().splitlines()
        why = tail[-1] if tail else "bwrap exited 1 before the command ran"
        attempt.stderr_tail = b""
        if attempt.setup_failures >= SETUP_TRIES:
            message = f"the sandbox could not be set up ({SETUP_TRIES} tries): {why}"
            attempt.log.line("osmo", f"start failed: {message}")
            self._finish(attempt, AttemptStartFailed(attempt.id, message))
            return
        attempt.log.line("osmo", f"the sandbox could not be set up ({why}); trying again "
                                 f"({attempt.setup_failures + 1} of {SETUP_TRIES})")
        attempt.state, attempt.handle = AttemptState.STARTING, None
        self._reactor.call_later(_SETUP_PAUSE * 2 ** (attempt.setup_failures - 1),
                                 self._start, attempt)

    def _start(self, attempt: LiveAttempt) -> None:
        if attempt.state not in (AttemptState.PREPARED, AttemptState.STARTING):
            return  # killed meanwhile
        attempt_id, launch = attempt.id, attempt.launch
        try:
            handle = self._spawn(launch)
        except (StartError, OSError) as exc:
            attempt.log.line("osmo", f"start failed: {exc}")
            self._finish(attempt, AttemptStartFailed(attempt_id, str(exc)))
            return
        self._watch(attempt, handle)
        self._emit(_started(attempt_id, handle))

    def _watch(self, attempt: LiveAttempt, handle: ProcessHandle) -> None:
        attempt.handle, attempt.state = handle, AttemptState.RUNNING
        reactor = self._reactor
        for fd, stream in ((handle.stdout_fd, "stdout"), (handle.stderr_fd, "stderr")):
            attempt.open_fds.add(fd)
            reactor.add_reader(fd, lambda a=attempt, f=fd, s=stream: a.read(reactor, f, s))
        self._reactor.add_reader(handle.exit_fd, lambda a=attempt: self._exited(a))
        attempt.checkpoints = start_checkpoints(
            attempt.task, attempt.dirs, attempt.id, reactor=self._reactor, io=self._io,
            credential_for=self._credential_for, log=functools.partial(attempt.log.line, "osmo"))


def _pull_line(log: LogWriter, line: str) -> None:
    log.line("osmo", f"pull: {line}")


def _started(attempt_id: str, handle: ProcessHandle) -> AttemptStarted:
    """The start report, with the process (group) id and its start time.

    The server records them, so that a restarted server can kill what is left of it.
    """
    started = handle.started_at
    return AttemptStarted(attempt_id, handle.pid,
                          process_start_time(handle.pid) if started is None else started)
