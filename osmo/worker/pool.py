"""The local pool: runs attempts as host processes on this machine, within its capacity.

``LocalPool`` is the executor (``osmo.executor.Executor``) of one node: it turns the
scheduler's commands into processes and reports what happened as events
(``AttemptPrepared``, ``AttemptStarted``, ``AttemptExited``, ``AttemptStartFailed``) through
``emit``. Every ``prepare`` gets exactly one final report — ``AttemptStartFailed`` or
``AttemptExited`` — whatever happens (kill before start, spawn failure, promotion failure).

Threading: public methods may be called from any thread; they only queue work for the pool's
reactor thread (``osmo.worker.reactor``), which reads pipes, watches exits through pidfds,
runs kill grace timers and owns attempt state. Filesystem work that waits on the disk —
making an attempt's folders and promoting its outputs — runs on a few I/O threads, so a slow
disk never stalls pipes, and the waits of several attempts overlap. An attempt with no
barrier is also spawned on its I/O thread right after its folders are made, and a
successful exit is reported from the I/O thread that promoted its outputs: each saves a
thread hand-off per task, and the slots' spawns overlap. ``emit`` is therefore called from
the reactor and the I/O threads; it must be thread-safe and cheap (put the event on a
queue).

Kill: ``SIGTERM`` to the attempt's process group, ``SIGKILL`` after ``kill_grace`` seconds.
A killed attempt's outputs are never promoted; a prepared attempt killed before it started
reports ``AttemptExited(exit_code=137)``. ``close()`` kills what still runs and reports
nothing more (the server is shutting down; on restart those attempts are recovered from the
store, see ``kill_stale``).

Credentials (``osmo.worker.secrets``) are given to ``prepare`` or looked up via
``task_secrets``; their values are masked in the log, their mounted files deleted at the end.
How an attempt ends (exit, promotion, its one final report in every path) is
``osmo.worker.endings``.

Containers: with ``containers`` (``osmo.worker.containers.ContainerTasks``), a task with an
``image:`` (and no ``type:``) runs in its image through the container runtime; everything
else, and every task without ``containers``, runs as a host process, its ``image`` only noted
in the log.

Sandbox (``sandbox``: ``auto``, ``on``, ``off``; ``osmo.runtime.sandbox``): chosen once, when
the pool is made; commands then run in bubblewrap with a view of their own attempt's folders
only (``workdir.attempt_view``), and the node's ``sandbox`` label says ``bwrap``. Without one,
the label says ``none`` and every attempt's log starts with an osmo line saying so.
A remote worker's pool also records each running command's pid and start time in
``procs_dir`` (one file per process, removed when it is reaped), so that a worker restarted
after a crash can kill what its previous life left (``osmo.worker.procs``).
Creating a pool lifts the process's soft open-files limit (each running attempt holds four
descriptors).
"""

from __future__ import annotations

import collections
import functools
import logging
import os
import signal
from collections.abc import Callable, Mapping
from concurrent.futures import ThreadPoolExecutor
from dataclasses import replace
from pathlib import Path

from osmo.artifacts import ArtifactStore
from osmo.artifacts.store import DEFAULT_MAX_FILES
from osmo.errors import OsmoError
from osmo.layout import AttemptDirs, Home
from osmo.runtime.container_runtime import ContainerRuntime
from osmo.runtime.process import (
    ProcessHandle,
    ProcessRuntime,
    Runtime,
    StartError,
    kill_stale,
    process_start_time,
)
from osmo.runtime.sandbox import SandboxMode, choose, unavailable_reason
from osmo.scheduler.types import (
    LOCAL_NODE,
    AttemptExited,
    AttemptPrepared,
    AttemptStarted,
    AttemptStartFailed,
    Event,
    KillAttempt,
    Node,
    PrepareAttempt,
    RunAttempt,
)
from osmo.spec.model import ResourceSpec, TaskSpec
from osmo.worker.checkpoints import start_checkpoints
from osmo.worker.container_images import registry_auth
from osmo.worker.containers import ContainerTasks
from osmo.worker.endings import AttemptEndings
from osmo.worker.live import AttemptState, LiveAttempt
from osmo.worker.logs import LogWriter, image_note
from osmo.worker.machine import detect_capacity, raise_fd_limit
from osmo.worker.options import DEFAULT_KILL_GRACE
from osmo.worker.procs import ProcessRecords
from osmo.worker.reactor import Reactor
from osmo.worker.secrets import SecretLookup, Secrets, gather
from osmo.worker.taskenv import base_env
from osmo.worker.transfer import CredentialLookup, ManifestLookup, make_ready
from osmo.worker.workdir import Launch, remove_secret_files

__all__ = ["LocalPool", "kill_stale", "process_start_time"]

_log = logging.getLogger(__name__)

KILLED_BEFORE_START = 128 + signal.SIGKILL
_IO_THREADS = 4


class LocalPool(AttemptEndings):
    """A resource-aware pool of host processes on this machine (see the module docstring).

    Args:
        home: osmo's home folder; attempts live under ``home/runs``.
        emit: receives every event, from the pool's threads; thread-safe and cheap.
        node_id: the node id this pool reports as.
        pool: the pool name.
        cpus, gpus, memory: capacity to advertise (default: what the machine has).
        kill_grace: seconds between SIGTERM and SIGKILL when killing an attempt.
        runtime: how commands run (default: ``ProcessRuntime``).
        env: the base environment of every command (default: ``taskenv.base_env`` of this
            process's environment).
        artifacts: where promoted outputs are ingested (content-addressed, verified); the
            exit report then carries the output's manifest. None: outputs are not ingested.
        credential_for: ``url -> credential`` for ``url`` inputs and outputs.
        input_manifests: input reference → its manifest, for inputs that are artifacts; each
            attempt then gets its own checked copy of them (``transfer.copy_inputs``).
        max_output_files: the most files one attempt's output may hold.
        task_secrets: credential name → payload, for tasks' ``credentials:`` when
            ``prepare`` is not given them.
        log_sink: also gets ``(attempt id, records)`` for every log record written.
        sandbox: ``auto`` (when bubblewrap works here), ``on`` (required) or ``off``.
        procs_dir: record running commands' pids here (see the module docstring).
        containers: runs image tasks in containers (its runtime replaces ``runtime``); its
            orphans are removed here, before anything starts.

    Raises:
        InfrastructureError: ``sandbox="on"`` and no sandbox works here.
    """

    def __init__(
        self,
        *,
        home: Path,
        emit: Callable[[Event], None],
        node_id: str = LOCAL_NODE,
        pool: str = LOCAL_NODE,
        cpus: float | None = None,
        gpus: int | None = None,
        memory: int | None = None,
        kill_grace: float = DEFAULT_KILL_GRACE,
        runtime: Runtime | None = None,
        env: Mapping[str, str] | None = None,
        artifacts: ArtifactStore | None = None,
        credential_for: CredentialLookup | None = None,
        input_manifests: ManifestLookup | None = None,
        max_output_files: int | None = DEFAULT_MAX_FILES,
        task_secrets: SecretLookup | None = None,
        log_sink: Callable[[str, bytes], None] | None = None,
        sandbox: SandboxMode = "auto",
        procs_dir: Path | None = None,
        containers: ContainerTasks | None = None,
    ) -> None:
        self.home = Path(home).absolute()
        self.home.mkdir(parents=True, exist_ok=True)
        self._layout = Home(self.home)
        raise_fd_limit()
        self._emit = emit
        self._node_id, self._pool = node_id, pool
        self._cpus, self._gpus, self._memory = cpus, gpus, memory
        self._grace = kill_grace
        self.sandbox = choose(sandbox)
        self._no_sandbox = None if self.sandbox else (
            "no sandbox: this task sees the host as the worker's user "
            f"({'--sandbox off' if sandbox == 'off' else unavailable_reason()})")
        self._runtime: Runtime = runtime or ProcessRuntime(self.sandbox)
        self._procs = ProcessRecords(procs_dir) if procs_dir is not None else None
        self._hidden = [self.home]  # folders a sandboxed task never sees (see hide())
        self._env = base_env(os.environ) if env is None else dict(env)
        self._containers = containers
        if containers is not None:
            containers.clean_orphans()  # a crashed predecessor's, before anything new runs
            # image tasks run in containers; every other one as a (sandboxed) process
            containers.runtime = ContainerRuntime(containers.engine,
                                                  processes=ProcessRuntime(self.sandbox))
            self._runtime = containers.runtime
        self._artifacts = artifacts
        self._credential_for = credential_for
        self._input_manifests = input_manifests
        self._max_output_files = max_output_files
        self._task_secrets = task_secrets
        self._log_sink = log_sink
        self._attempts: dict[str, LiveAttempt] = {}
        self._finished: collections.OrderedDict[str, None] = collections.OrderedDict()
        self._reactor = Reactor(f"osmo-pool-{pool}")
        self._io = ThreadPoolExecutor(_IO_THREADS, thread_name_prefix=f"osmo-io-{pool}")
        self._preparing: dict[str, str | None] = {}  # attempt id → kill reason, if killed
        self._run_pending: set[str] = set()  # run() came while its folders were being made

    # -------------------------------------------------------------- public (any thread)

    def node(self) -> Node:
        """This machine as a scheduler node, with its (or the configured) capacity."""
        capacity = detect_capacity(self.home, cpus=self._cpus, gpus=self._gpus,
                                   memory=self._memory)
        return Node(id=self._node_id, pool=self._pool, capacity=capacity,
                    labels={"sandbox": "bwrap" if self.sandbox else "none"})

    def prepare(self, cmd: PrepareAttempt, task: TaskSpec, secrets: Secrets | None = None,
                *, max_output_bytes: int | None = None,
                resources: ResourceSpec | None = None) -> None:
        """Prepare an attempt's folder; later emits AttemptPrepared or AttemptStartFailed.

        ``secrets``: payloads of the credentials ``task`` names (None: ask ``task_secrets``).
        ``max_output_bytes``: the task's ``storage`` request; a larger output fails it.
        ``resources``: its request (a container's cpu/memory limits and GPUs).
        """
        self._reactor.call_soon(self._prepare, cmd, task, secrets,
                                replace(resources or ResourceSpec(), storage=max_output_bytes))

    def runtime_name(self) -> str:
        """How this pool runs image tasks: ``container (podman 4.3.1)`` or ``process``."""
        return f"container ({self._containers.describe()})" if self._containers else "process"

    def hide(self, folder: Path) -> None:
        """Also hide ``folder`` from sandboxed tasks (another osmo home on this host)."""
        if folder not in self._hidden:
            self._hidden.append(folder)

    def owns(self, node_id: str) -> bool:
        """Whether ``node_id`` is this pool's node."""
        return node_id == self._node_id

    def run(self, cmd: RunAttempt) -> None:
        """Start a prepared attempt: AttemptStarted, then one AttemptExited.

        AttemptStartFailed instead if the command cannot be spawned.
        """
        self._reactor.call_soon(self._run, cmd.attempt_id)

    def kill(self, cmd: KillAttempt) -> None:
        """Kill an attempt's process group (SIGTERM, SIGKILL after the grace period)."""
        self._reactor.call_soon(self._kill, cmd.attempt_id, cmd.reason)

    def close(self) -> None:
        """Kill every running process group and stop the threads (no more events).

        The I/O threads are drained first: a process one of them just spawned is handed to
        the reactor before the reactor's final sweep kills everything.
        """
        self._io.shutdown(wait=True, cancel_futures=True)
        self._reactor.stop(self._shutdown)
        if self._containers is not None:
            self._containers.close()

    # -------------------------------------------------------------- containers

    def _spawn(self, launch: Launch, *, wait: bool = False) -> ProcessHandle:
        """Start a launch (any thread): in its container, or as a (sandboxed) process.

        ``wait``: on an I/O thread (a container peer may wait for its lead). A remote
        worker's pool records the pid.
        """
        if launch.container is None or self._containers is None:
            handle = self._runtime.start(launch.argv, cwd=launch.cwd, env=launch.env,
                                         view=launch.view)
        else:
            handle = self._containers.start(launch, wait_for_lead=wait)
        if self._procs is not None:
            self._procs.add(handle.pid)
        return handle

    def _ended(self, launch: Launch) -> None:
        """An attempt is over: its container's GPUs and group network are let go."""
        if launch.container is not None and self._containers is not None:
            try:
                self._io.submit(self._containers.ended, launch.container)
            except RuntimeError:  # closing: ContainerTasks.close removes the networks
                pass

    # -------------------------------------------------------------- reactor thread

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
        """I/O thread: make the folders and files; hand the outcome back to the reactor."""
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
                                boxed=boxed)
            launch = replace(launch, max_output_bytes=resources.storage)
            if self._containers is not None and boxed:
                launch = self._containers.finish(
                    launch, cmd, task, dirs, request=resources, gpus=self.node().capacity.gpu,
                    auth=registry_auth(task, self._task_secrets))
        except Exception as exc:  # every prepare must get its one final report
            message = str(exc) if isinstance(exc, OsmoError) else f"cannot prepare: {exc!r}"
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
        self._reactor.call_soon(self._prepared, cmd, task, dirs, launch, None, started)

    def _prepared(self, cmd: PrepareAttempt, task: TaskSpec, dirs: AttemptDirs | None,
                  launch: Launch | None, error: str | None,
                  started: ProcessHandle | str | None = None) -> None:
        kill_reason = self._preparing.pop(cmd.attempt_id, None)
        run_now = cmd.run or cmd.attempt_id in self._run_pending
        self._run_pending.discard(cmd.attempt_id)
        if error is not None or dirs is None or launch is None:
            self._remember(cmd.attempt_id)
            self._emit(AttemptStartFailed(cmd.attempt_id, error or "cannot prepare"))
            return
        sink = functools.partial(self._log_sink, cmd.attempt_id) if self._log_sink else None
        try:
            log = LogWriter(dirs.log, launch.secrets, sink)
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
        if self._no_sandbox is not None and launch.container is None:
            attempt.log.line("osmo", self._no_sandbox)
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

    def _reap(self, handle: ProcessHandle) -> int:
        code = self._runtime.reap(handle)
        if self._procs is not None:
            self._procs.remove(handle.pid)
        return code

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

    def _kill(self, attempt_id: str, reason: str) -> None:
        if attempt_id in self._preparing:  # acted on when its folders are ready
            self._preparing[attempt_id] = self._preparing[attempt_id] or reason
            return
        attempt = self._attempts.get(attempt_id)
        if attempt is None or attempt.kill_reason is not None:
            return
        if attempt.state is AttemptState.FINISHING:
            return  # it already exited; its report is on the way
        attempt.kill_reason = reason
        attempt.log.line("osmo", f"killed: {reason}")
        if attempt.state in (AttemptState.PREPARED, AttemptState.STARTING):
            event = AttemptExited(attempt_id, KILLED_BEFORE_START, None, f"killed: {reason}")
            self._finish(attempt, event)
        elif attempt.handle is not None:
            self._runtime.kill(attempt.handle)
            attempt.escalation = self._reactor.call_later(self._grace, self._escalate, attempt)

    def _escalate(self, attempt: LiveAttempt) -> None:
        if attempt.state is AttemptState.RUNNING and attempt.handle is not None:
            attempt.log.line("osmo", f"still running {self._grace:g}s after SIGTERM: SIGKILL")
            self._runtime.kill(attempt.handle, force=True)

    def _shutdown(self) -> None:
        for attempt in list(self._attempts.values()):
            handle = attempt.handle
            if attempt.state is AttemptState.RUNNING and handle is not None:
                attempt.log.line("osmo", "killed: pool closed")
                self._runtime.kill(handle, force=True)
                self._reap(handle)
                self._runtime.release(handle)
            attempt.log.close()
            remove_secret_files(attempt.launch)
            self._ended(attempt.launch)
        self._attempts.clear()


def _started(attempt_id: str, handle: ProcessHandle) -> AttemptStarted:
    """The start report, with the process (group) id and its start time.

    The server records them, so that a restarted server can kill what is left of it.
    """
    return AttemptStarted(attempt_id, handle.pid, process_start_time(handle.pid))
