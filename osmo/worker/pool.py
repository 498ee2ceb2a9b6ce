"""The local pool: runs attempts on this machine, within its capacity, through its runtimes.

``LocalPool`` is the executor (``osmo.executor.Executor``) of one node: it turns the
scheduler's commands into launches and reports what happened as events
(``AttemptPrepared``, ``AttemptStarted``, ``AttemptExited``, ``AttemptStartFailed``) through
``emit``. Every ``prepare`` gets exactly one final report — ``AttemptStartFailed`` or
``AttemptExited`` — whatever happens (kill before start, spawn failure, promotion failure).

It is composed of parts it holds, each given what it needs when the pool is made:

- the node's runtimes (``osmo.runtime.choose.Runtimes``): how each attempt runs — a host
  process, sandboxed or not, or its image in a container — chosen once per attempt; every
  runtime-specific step is that runtime's (``osmo.runtime.api``);
- :class:`~osmo.worker.preparing.Preparing`: an attempt's folder, files, inputs and launch;
- :class:`~osmo.worker.starts.Starting`: its spawn, its watch, its kill, its exit;
- :class:`~osmo.worker.endings.Ending`: its outputs, its one final report, its clean-up;
- the table of live attempts (``osmo.worker.live.Attempts``) they share.

The pool's own methods route the executor's commands to them.

Threading: public methods may be called from any thread; they only queue work for the pool's
reactor thread (``osmo.worker.reactor``), which reads pipes, watches exits through pidfds,
runs kill grace timers and owns attempt state. Work that waits — making an attempt's folders
and completing its launch (a pull), promoting its outputs, a container peer's wait for its
lead — runs on a few I/O threads, so a slow disk or engine never stalls pipes, and the waits
of several attempts overlap. Work crosses threads twice per attempt: reactor → I/O (prepare)
→ reactor (prepared), and reactor → I/O (promotion) → reactor (bookkeeping). An attempt with
no barrier is spawned on its I/O thread right after its launch is complete, and a successful
exit is reported from the I/O thread that promoted its outputs: each saves a thread hand-off
per task, and the slots' spawns overlap. ``emit`` is therefore called from the reactor and
the I/O threads; it must be thread-safe and cheap (put the event on a queue). A runtime's
own background work (a container's removal, its group network's) is the runtime's.

Kill: ``SIGTERM`` to the attempt's launch, ``SIGKILL`` after ``kill_grace`` seconds. A killed
attempt's outputs are never promoted; a prepared attempt killed before it started reports
``AttemptExited(exit_code=137)``. ``close()`` kills what still runs and reports nothing more
(the server is shutting down; on restart those attempts are recovered from the store, see
``kill_stale``).

Credentials (``osmo.worker.secrets``) are given to ``prepare`` or looked up via
``task_secrets``; their values are masked in the log, their mounted files deleted at the end.

Containers: with ``containers`` (``osmo.runtime.choose.containers_for_node``), a task with an
``image:`` (and no ``type:``) runs in its image; everything else, and every task without
``containers``, runs as a host process, its ``image`` only noted in the log.

Sandbox (``sandbox``: ``auto``, ``on``, ``off``; ``osmo.runtime.choose.processes_for_node``):
chosen once, when the pool is made, with the node's network namespace its tasks share
(``osmo.runtime.process.netns``, closed with the pool); commands then run in bubblewrap with a
view of their own attempt's folders only (``osmo.runtime.process.sandboxed``), and the node's
``sandbox`` label says ``bwrap``. Without one, the label says ``none``, ``no_sandbox_why``
says why in a few words (``osmo resource list``), and every attempt's log starts with an osmo
line saying so; without outbound network for its tasks, likewise. ``auto`` that finds no
working sandbox also logs :attr:`LocalPool.sandbox_warning` (level WARNING) when the pool is
made: nobody chose to run tasks unsandboxed, so it is said at start, not only in each task's
log.

Adoption: with a ``journal`` (``osmo.worker.journal``), an attempt whose runtime's launches
outlive the node (a Slurm job, a pod: ``osmo.runtime.api.Adopting``) is journaled before it
starts and until its end; a pool made by the node's next life re-attaches to each journaled
attempt (:meth:`LocalPool.adopt`: watched as if it had started it, its log resumed where it
was shipped, its outputs promoted and reported as usual) and then cancels what of its
owner's launches it did not adopt (:meth:`LocalPool.cancel_orphans`).

A pool records each command's pid and start time in ``procs_dir`` right after the spawn
(one appended line; ``osmo.worker.procs``), so that a server or worker restarted after a
crash can kill what its previous life left, even a command whose start it never reported.
Creating a pool lifts the process's soft open-files limit (each running attempt holds four
descriptors).
"""

from __future__ import annotations

import logging
import os
import threading
from collections.abc import Callable, Mapping, Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import replace
from pathlib import Path

from osmo.artifacts import ArtifactStore
from osmo.artifacts.store import DEFAULT_MAX_FILES
from osmo.errors import OsmoError, UsageError
from osmo.layout import Home
from osmo.options import DEFAULT_LOG_LIMIT, SandboxMode, WarmOptions
from osmo.runtime.api import Adopting, Runtime, Terms
from osmo.runtime.choose import Runtimes, processes_for_node
from osmo.runtime.container import ContainerRuntime
from osmo.runtime.process.sandbox import Sandbox
from osmo.runtime.process.warm import WarmRunners
from osmo.scheduler.types import (
    LOCAL_NODE,
    AttemptLost,
    AttemptStartFailed,
    Event,
    KillAttempt,
    Node,
    PrepareAttempt,
    RunAttempt,
)
from osmo.spec.model import ResourceSpec, TaskSpec
from osmo.worker.endings import KILLED_BEFORE_START, Ending
from osmo.worker.journal import Entry, Journal
from osmo.worker.live import Attempts, AttemptState, LiveAttempt, Running
from osmo.worker.machine import GpuSlots, detect_capacity, raise_fd_limit
from osmo.worker.options import DEFAULT_KILL_GRACE
from osmo.worker.preparing import Preparing
from osmo.worker.procs import ProcessRecords
from osmo.worker.reactor import Reactor
from osmo.worker.secrets import SecretLookup, Secrets
from osmo.worker.starts import Starting
from osmo.worker.taskenv import base_env
from osmo.worker.transfer import CredentialLookup, ManifestLookup

__all__ = ["KILLED_BEFORE_START", "LocalPool"]

_log = logging.getLogger(__name__)

_IO_THREADS = 4
_WARM_SWEEP = 5.0  # seconds between two reaps of the warm runners that exited


class LocalPool:
    """A resource-aware pool of this machine's attempts (see the module docstring).

    Args:
        home: osmo's home (absolute, ``osmo.config.open_home``); attempts live under its
            ``runs/``.
        emit: receives every event, from the pool's threads; thread-safe and cheap.
        node_id: the node id this pool reports as.
        pool: the pool name.
        cpus, gpus, memory: capacity to advertise (default: what the machine has).
        kill_grace: seconds between SIGTERM and SIGKILL when killing an attempt.
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
        containers: runs image tasks in containers, or as a cluster's pods (closed with
            the pool).
        cluster: runs every task as a cluster scheduler's job (``--runtime slurm``:
            ``osmo.runtime.choose.slurm_for_node``; closed with the pool).
        cluster_images: the cluster's runtime for tasks that run in their image.
        warm: its warm runners for typed tasks (``osmo.runtime.process.warm``; default
            on: ``osmo.options.WarmOptions``); unsandboxed process tasks only.
        journal: where attempts whose launches outlive the node are journaled (see the
            module docstring; None: nowhere, nothing is adopted).

    Attributes:
        home: osmo's home.
        sandbox: the sandbox its process tasks run in (None: they run unsandboxed).
        no_sandbox_why: why they run unsandboxed, in a few words (``--sandbox off``, ``bwrap
            not found``, ...; None: they run in the sandbox).
        sandbox_warning: what was logged at start because ``auto`` found no sandbox (None
            when it found one, or with ``off``).
        warm: the warm runners its typed tasks start from (None: none, they start cold).

    Raises:
        InfrastructureError: ``sandbox="on"`` and no sandbox works here.
        UsageError: ``home`` is relative, or a ``sandbox_share`` folder is relative or inside
            ``home``.
    """

    def __init__(
        self,
        *,
        home: Home,
        emit: Callable[[Event], None],
        node_id: str = LOCAL_NODE,
        pool: str = LOCAL_NODE,
        cpus: float | None = None,
        gpus: int | None = None,
        memory: int | None = None,
        kill_grace: float = DEFAULT_KILL_GRACE,
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
        containers: Runtime | None = None,
        cluster: Runtime | None = None,
        cluster_images: Runtime | None = None,
        warm: WarmOptions | None = None,
        journal: Journal | None = None,
    ) -> None:
        if not home.root.is_absolute():
            raise UsageError(f"osmo's home must be an absolute path, not {home.root}")
        self.home = home
        home.root.mkdir(parents=True, exist_ok=True)
        raise_fd_limit()
        self._emit = emit
        self._node_id, self._pool = node_id, pool
        self._cpus, self._gpus, self._memory = cpus, gpus, memory
        base = base_env(os.environ) if env is None else dict(env)
        warm = WarmOptions() if warm is None else warm
        runners = (WarmRunners(base, idle=warm.idle, max_rss=warm.max_memory) if warm.on
                   else None)
        process = processes_for_node(sandbox, sandbox_share, home=home.root, address=address,
                                     pool=pool, warm=runners)
        self.warm = process.warm
        self.no_sandbox_why, self.sandbox_warning = process.why, process.warning
        if self.sandbox_warning:
            _log.warning("%s", self.sandbox_warning)
        if warm.on and isinstance(containers, ContainerRuntime):  # typed tasks in images
            containers.warm_up(idle=warm.idle, max_rss=warm.max_memory)
        self._boxes = containers if isinstance(containers, ContainerRuntime) else None
        self._runtimes = Runtimes(process, containers, cluster, cluster_images)
        self._procs = ProcessRecords(procs_dir) if procs_dir is not None else None
        self._attempts = Attempts()
        self._reactor = Reactor(f"osmo-pool-{pool}")
        self._io = ThreadPoolExecutor(_IO_THREADS, thread_name_prefix=f"osmo-io-{pool}")
        slots = GpuSlots(self.node().capacity.gpu)
        self._ending = Ending(attempts=self._attempts, reactor=self._reactor, io=self._io,
                              emit=emit, gpus=slots, artifacts=artifacts,
                              credential_for=credential_for, max_output_files=max_output_files,
                              journal=journal)
        self._starting = Starting(reactor=self._reactor, io=self._io, emit=emit,
                                  ending=self._ending, procs=self._procs, grace=kill_grace,
                                  credential_for=credential_for)
        self._preparing = Preparing(
            home=home, runtimes=self._runtimes, attempts=self._attempts, reactor=self._reactor,
            io=self._io, emit=emit, starting=self._starting, gpus=slots,
            env=base, task_secrets=task_secrets,
            credential_for=credential_for, artifacts=artifacts, input_manifests=input_manifests,
            log_sink=log_sink, log_limit=log_limit, journal=journal)
        if self.warm is not None or self._boxes is not None:
            self._reactor.call_soon(self._sweep_warm)

    # -------------------------------------------------------------- public (any thread)

    @property
    def sandbox(self) -> Sandbox | None:
        """The sandbox its process tasks run in (None: they run unsandboxed)."""
        return self._runtimes.sandbox

    def offer(self, cpus: float | None, gpus: int | None, memory: int | None) -> None:
        """Offer this capacity from now on (a cluster node's cluster grew or shrank)."""
        self._cpus, self._gpus, self._memory = cpus, gpus, memory

    def node(self) -> Node:
        """This machine as a scheduler node, with its (or the configured) capacity."""
        capacity = detect_capacity(self.home.root, cpus=self._cpus, gpus=self._gpus,
                                   memory=self._memory)
        return Node(id=self._node_id, pool=self._pool, capacity=capacity,
                    labels={"sandbox": "bwrap" if self.sandbox else "none"})

    def prepare(self, cmd: PrepareAttempt, task: TaskSpec, secrets: Secrets | None = None,
                *, max_output_bytes: int | None = None,
                resources: ResourceSpec | None = None, terms: Terms | None = None) -> None:
        """Prepare an attempt's folder; later emits AttemptPrepared or AttemptStartFailed.

        ``secrets``: payloads of the credentials ``task`` names (None: ask ``task_secrets``).
        ``max_output_bytes``: the task's ``storage`` request; a larger output fails it.
        ``resources``: its request (a container's cpu/memory limits and GPUs).
        ``terms``: its workflow's time limit and priority (a cluster runtime's job asks for
        them).
        """
        self._reactor.call_soon(self._preparing.prepare, cmd, task, secrets,
                                replace(resources or ResourceSpec(), storage=max_output_bytes),
                                terms or Terms())

    def warm_runners(self) -> list[dict[str, object]]:
        """Its live warm runners, as ``osmo resource list`` shows them (JSON).

        Its host processes' runners, then its runner containers'.
        """
        found = self.warm.runners() if self.warm is not None else []
        found += self._boxes.warm_runners() if self._boxes is not None else []
        return [r.to_dict() for r in found]

    def runtime_name(self) -> str:
        """How this pool runs image tasks: ``container (podman 4.3.1)`` or ``process``."""
        return self._runtimes.describe()

    def outlives(self) -> bool:
        """Whether attempts of this node outlive its process (a cluster's jobs or pods)."""
        return bool(self._runtimes.adopting())

    def adopt(self, entry: Entry) -> None:
        """Re-attach to a journaled attempt a previous life of the node started (blocks).

        It is then watched as if started here: one final report, as for any attempt
        (``AttemptLost`` if there is nothing to adopt).
        """
        done = threading.Event()

        def adopt() -> None:
            try:
                self._adopt(entry)
            finally:
                done.set()

        self._reactor.call_soon(adopt)
        done.wait()

    def cancel_orphans(self) -> list[str]:
        """Cancel the launches of this node's owner that were not adopted (after ``adopt``)."""
        adopting = self._runtimes.adopting()
        keep = sorted({launch for runtime in adopting for launch in runtime.adopted()})
        return adopting[0].cancel_orphans(keep) if adopting else []

    def hide(self, path: Path) -> None:
        """Also hide ``path`` from sandboxed tasks.

        A folder (another osmo home on this host) or a file (a token file the server or
        worker was given).
        """
        self._runtimes.hide(path)

    def owns(self, node_id: str) -> bool:
        """Whether ``node_id`` is this pool's node."""
        return node_id == self._node_id

    def running(self, attempt_id: str) -> Running | None:
        """``attempt_id``'s runtime, launch and handle while it runs here (None otherwise).

        For interactive sessions (``osmo.worker.sessions``), from any thread.
        """
        return self._attempts.running(attempt_id)

    def run(self, cmd: RunAttempt) -> None:
        """Start a prepared attempt: AttemptStarted, then one AttemptExited.

        AttemptStartFailed instead if the command cannot be spawned.
        """
        self._reactor.call_soon(self._run, cmd.attempt_id)

    def kill(self, cmd: KillAttempt) -> None:
        """Kill an attempt (SIGTERM, SIGKILL after the grace period)."""
        self._reactor.call_soon(self._kill, cmd.attempt_id, cmd.reason)

    def close(self) -> None:
        """Kill every running attempt and stop the threads (no more events).

        The I/O threads are drained first: a process one of them just spawned is handed to
        the reactor before the reactor's final sweep kills everything.
        """
        self._io.shutdown(wait=True, cancel_futures=True)
        self._reactor.stop(self._shutdown)
        self._runtimes.close()

    # -------------------------------------------------------------- reactor thread

    def _sweep_warm(self) -> None:
        """Reap the warm runners that exited (idle, or retired), and again in a while."""
        if self.warm is not None:
            self.warm.sweep()
        if self._boxes is not None:
            self._boxes.sweep()
        self._reactor.call_later(_WARM_SWEEP, self._sweep_warm)

    def _run(self, attempt_id: str) -> None:
        if self._preparing.run(attempt_id):
            return  # started once it is prepared
        attempt = self._attempts.get(attempt_id)
        if attempt is None:
            if not self._attempts.finished(attempt_id):
                self._attempts.remember(attempt_id)
                self._emit(AttemptStartFailed(attempt_id, "attempt was not prepared here"))
            return
        if attempt.state is AttemptState.PREPARED:
            self._starting.start(attempt)

    def _adopt(self, entry: Entry) -> None:
        runtime = self._runtimes.choose(entry.spec)
        log = self._preparing.open_log(entry.attempt_id, entry.dirs, entry.secrets)
        try:
            if not isinstance(runtime, Adopting):
                raise OsmoError("its runtime's launches do not outlive the node")
            launch, handle = runtime.adopt(entry.dirs, entry.shipped)
        except (OsmoError, OSError) as exc:
            message = f"the restarted node could not adopt it: {exc}"
            _log.warning("attempt %s: %s", entry.attempt_id, message)
            log.line("osmo", f"lost: {message}")
            log.close()
            self._attempts.remember(entry.attempt_id)
            self._ending.forget(entry.attempt_id)
            self._emit(AttemptLost(entry.attempt_id, message))
            return
        launch = replace(launch, argv=entry.argv, image_id=entry.image_id,
                         secrets=entry.secrets, max_output_bytes=entry.max_output_bytes)
        attempt = LiveAttempt(entry.attempt_id, entry.spec, entry.dirs, launch, log, runtime)
        self._preparing.journaled(attempt, dict(entry.shipped))
        self._attempts.add(attempt)
        attempt.log.line("osmo", f"adopted by node {self._node_id} after its restart")
        self._starting.watch(attempt, handle)

    def _kill(self, attempt_id: str, reason: str) -> None:
        if self._preparing.kill(attempt_id, reason):
            return  # acted on when its folders are ready
        attempt = self._attempts.get(attempt_id)
        if attempt is not None:
            self._starting.kill(attempt, reason)

    def _shutdown(self) -> None:
        for attempt in self._attempts:
            self._starting.stop(attempt)
            self._ending.abandon(attempt)
        self._attempts.clear()
        if self._procs is not None:
            self._procs.close()
