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
How an attempt starts (preparation, spawn, watch) is ``osmo.worker.starts``; how it ends
(exit, promotion, its one final report in every path) is ``osmo.worker.endings``.

Containers: with ``containers`` (``osmo.worker.containers.ContainerTasks``), a task with an
``image:`` (and no ``type:``) runs in its image through the container runtime; everything
else, and every task without ``containers``, runs as a host process, its ``image`` only noted
in the log.

Sandbox (``sandbox``: ``auto``, ``on``, ``off``; ``osmo.runtime.process.sandbox``): chosen
once, when the pool is made, with the node's network namespace its tasks share
(``osmo.runtime.process.netns``, closed with the pool); commands then run in bubblewrap with a
view of their own attempt's folders only (``workdir.attempt_view``), and the node's ``sandbox``
label says ``bwrap``. Without one, the label says ``none``, ``no_sandbox_why`` says why in a
few words (``osmo resource list``), and every attempt's log starts with an osmo line saying so;
without outbound network for its tasks, likewise. ``auto`` that finds no working sandbox also
logs :attr:`LocalPool.sandbox_warning` (level WARNING) when the pool is made: nobody chose to
run tasks unsandboxed, so it is said at start, not only in each task's log.
A pool records each command's pid and start time in ``procs_dir`` right after the spawn
(one appended line; ``osmo.worker.procs``), so that a server or worker restarted after a
crash can kill what its previous life left, even a command whose start it never reported.
Creating a pool lifts the process's soft open-files limit (each running attempt holds four
descriptors).
"""

from __future__ import annotations

import collections
import logging
import os
import socket
from collections.abc import Callable, Mapping, Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import replace
from pathlib import Path

from osmo.artifacts import ArtifactStore
from osmo.artifacts.store import DEFAULT_MAX_FILES
from osmo.errors import InfrastructureError, UsageError
from osmo.layout import Home
from osmo.options import DEFAULT_LOG_LIMIT
from osmo.runtime.container.engine import ContainerEngine
from osmo.runtime.container.runs import ContainerRuntime
from osmo.runtime.process.groups import ProcessHandle, ProcessRuntime, Runtime
from osmo.runtime.process.netns import NodeNetwork
from osmo.runtime.process.proctable import kill_stale, process_start_time
from osmo.runtime.process.sandbox import (
    Sandbox,
    SandboxMode,
    choose,
    node_network,
    parse_share,
    unavailable_reason,
    unavailable_summary,
)
from osmo.scheduler.types import (
    LOCAL_NODE,
    AttemptExited,
    Event,
    KillAttempt,
    Node,
    PrepareAttempt,
    RunAttempt,
)
from osmo.spec.model import ResourceSpec, TaskSpec
from osmo.worker.containers import ContainerTasks
from osmo.worker.endings import KILLED_BEFORE_START
from osmo.worker.live import AttemptState, LiveAttempt
from osmo.worker.machine import detect_capacity, raise_fd_limit
from osmo.worker.options import DEFAULT_KILL_GRACE
from osmo.worker.procs import ProcessRecords
from osmo.worker.reactor import Reactor
from osmo.worker.secrets import SecretLookup, Secrets
from osmo.worker.starts import AttemptStarts
from osmo.worker.taskenv import base_env
from osmo.worker.transfer import CredentialLookup, ManifestLookup
from osmo.worker.workdir import Launch, remove_secret_files

__all__ = ["LocalPool", "kill_stale", "process_start_time"]

_log = logging.getLogger(__name__)

_IO_THREADS = 4


class LocalPool(AttemptStarts):
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
        log_limit: bytes each attempt's log keeps at most (``osmo.worker.logs``).
        sandbox: ``auto`` (when bubblewrap works here), ``on`` (required) or ``off``.
        sandbox_share: host folders every sandboxed task may write (never inside ``home``).
        address: how peers reach this node's tasks (``{{host:NAME}}``): given to the
            sandboxed tasks' network too (``osmo.runtime.process.netns``).
        procs_dir: record running commands' pids here (see the module docstring).
        containers: runs image tasks in containers (its runtime replaces ``runtime``); its
            orphans are removed here, before anything starts.

    Attributes:
        sandbox: the sandbox its process tasks run in (None: they run unsandboxed).
        no_sandbox_why: why they run unsandboxed, in a few words (``--sandbox off``, ``bwrap
            not found``, ...; None: they run in the sandbox).
        sandbox_warning: what was logged at start because ``auto`` found no sandbox (None
            when it found one, or with ``off``).

    Raises:
        InfrastructureError: ``sandbox="on"`` and no sandbox works here.
        UsageError: a ``sandbox_share`` folder is relative or inside ``home``.
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
        log_limit: int = DEFAULT_LOG_LIMIT,
        sandbox: SandboxMode = "auto",
        sandbox_share: Sequence[str] = (),
        address: str | None = None,
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
        inside = [d for d in sandbox_share
                  if Path(parse_share(d)[0]).absolute().is_relative_to(self.home)]
        if inside:
            raise UsageError(f"--sandbox-share {inside[0]}: it is inside osmo's home "
                             f"{self.home}, which tasks must never see")
        (self.sandbox, self._network, self._sandbox_note, self.no_sandbox_why,
         self.sandbox_warning) = _sandbox(sandbox, sandbox_share, address, pool)
        if self.sandbox_warning:
            _log.warning("%s", self.sandbox_warning)
        self._runtime: Runtime = runtime or ProcessRuntime(self.sandbox)
        self._procs = ProcessRecords(procs_dir) if procs_dir is not None else None
        self._hidden = [self.home]  # folders a sandboxed task never sees (see hide())
        self._masked: list[Path] = []  # files it never sees
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
        self._log_limit = log_limit
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

    def hide(self, path: Path) -> None:
        """Also hide ``path`` from sandboxed tasks.

        A folder (another osmo home on this host) or a file (a token file the server or
        worker was given).
        """
        path = Path(path).absolute()
        found = self._hidden
        if path.is_file():
            if self.sandbox is None or not self.sandbox.shows(str(path)):
                return  # a file no shown folder holds is not there anyway
            found = self._masked
        if path not in found:
            found.append(path)

    def task_socket(self, udp: bool) -> socket.socket | None:
        """A new socket in the network of this pool's sandboxed tasks (None: the host's).

        Raises:
            OSError: it cannot be made.
        """
        if self._network is None:
            return None
        return self._network.socket(socket.AF_INET, socket.SOCK_DGRAM if udp
                                    else socket.SOCK_STREAM)

    def owns(self, node_id: str) -> bool:
        """Whether ``node_id`` is this pool's node."""
        return node_id == self._node_id

    def running_launch(self, attempt_id: str) -> Launch | None:
        """What ``attempt_id`` runs with while it runs here (None otherwise).

        For interactive sessions (``osmo.worker.sessions``), from any thread: one read of the
        reactor's table (atomic under the GIL) of a frozen ``Launch``.
        """
        attempt = self._attempts.get(attempt_id)
        running = attempt is not None and attempt.state is AttemptState.RUNNING
        return attempt.launch if running and attempt is not None else None

    def running_pid(self, attempt_id: str) -> int | None:
        """The main process id of ``attempt_id`` while it runs here (None otherwise).

        A sandboxed attempt's is its sandbox's; its processes all run below it.
        """
        attempt = self._attempts.get(attempt_id)
        handle = attempt.handle if attempt is not None else None
        running = attempt is not None and attempt.state is AttemptState.RUNNING
        return handle.pid if running and handle is not None else None

    @property
    def container_engine(self) -> ContainerEngine | None:
        """The engine that runs this pool's image tasks (None: they run as processes)."""
        return self._containers.engine if self._containers is not None else None

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
        if self._network is not None:
            self._network.close()

    # -------------------------------------------------------------- containers

    def _ended(self, launch: Launch) -> None:
        """An attempt is over: its container's GPUs and group network are let go."""
        if launch.container is not None and self._containers is not None:
            try:
                self._io.submit(self._containers.ended, launch.container)
            except RuntimeError:  # closing: ContainerTasks.close removes the networks
                pass

    # -------------------------------------------------------------- reactor thread

    def _reap(self, handle: ProcessHandle) -> int:
        code = self._runtime.reap(handle)
        if self._procs is not None:
            self._procs.remove(handle.pid)
        return code

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
        if self._procs is not None:
            self._procs.close()


def _sandbox(mode: SandboxMode, shares: Sequence[str], address: str | None, pool: str
             ) -> tuple[Sandbox | None, NodeNetwork | None, str | None, str | None, str | None]:
    """The pool's sandbox in its node's namespaces, those namespaces, and what to say.

    What to say: in each process task's log (no sandbox at all, or no outbound network), in
    ``osmo resource list`` (why there is no sandbox, in a few words), and once at start (a
    warning when ``auto`` found none: nobody chose it).

    Raises:
        InfrastructureError: ``mode`` is ``on`` and no sandbox works here.
    """
    sandbox = choose(mode, shares)
    if mode == "off":
        return (None, None, "no sandbox: this task sees the host as the worker's user "
                "(--sandbox off)", "--sandbox off", None)
    if sandbox is None:
        reason, summary = unavailable_reason(), unavailable_summary()
    else:
        try:
            network = node_network(address=address)
        except InfrastructureError as exc:
            if mode == "on":
                raise
            reason, summary = str(exc), "no network namespace"
        else:
            if network.caveat:
                _log.warning("sandboxed tasks: %s", network.caveat)
            return sandbox.joined(network), network, network.caveat or None, None, None
    return (None, None, f"no sandbox: this task sees the host as the worker's user ({reason})",
            summary, f"UNSANDBOXED: pool {pool} runs its tasks without a sandbox (--sandbox "
            f"{mode}): {reason}. They see the host as uid {os.geteuid()}, osmo's home (state, "
            "credentials) included; --sandbox on refuses to start instead")
