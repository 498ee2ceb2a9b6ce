"""The runtime contract: how one attempt runs, from its launch to its clean-up.

A runtime turns a prepared attempt into its launch and owns that launch to the end. The
worker pool (``osmo.worker.pool``) makes the attempt's folder, writes its files and copies its
inputs (``osmo.worker.workdir``, ``osmo.worker.transfer``); everything that depends on *how*
the attempt runs is the runtime's, one method per concern, called in this order:

=========================================  ====================================================
``paths(cmd)``                             how the task will see its attempt (:class:`Paths`):
                                           what ``{{output}}``, ``{{input:N}}``,
                                           ``{{host:NAME}}`` and ``OSMO_*`` name. Pure.
``prepare(launch, attempt, progress=)``    complete the launch the pool made: a sandbox's view,
                                           a container's image, mounts and network. I/O
                                           thread; it may pull, its lines go to ``progress``.
``start(launch)``                          spawn it: a :class:`ProcessHandle`. Any thread; it
                                           blocks only when ``launch.waits`` (a container
                                           group's peer waits for its lead), and the pool then
                                           calls it off its reactor.
*wait*                                     the handle's ``exit_fd`` becomes readable when the
                                           launch ended; its output is on ``stdout_fd`` and
                                           ``stderr_fd`` (non-blocking), the runtime's own
                                           lines on ``notes_fd`` if it has one. The pool's
                                           reactor selects on them all: nothing polls.
``kill(handle, force=)``                   SIGTERM (the pool sends ``force`` after its grace).
``reap(handle)``                           the exit code, once ``exit_fd`` was readable (128+N:
                                           killed by signal N; ``handle.setup_failed``: the
                                           command never ran, the pool may start it again).
``release(handle)``                        close the handle's descriptors.
``exec(launch, command, tty=, term=)``     what ``osmo workflow exec`` runs, and where.
``connector(launch, handle)``              how port-forward reaches the task's ports.
``cleanup(launch)``                        what the runtime holds for the attempt goes (after
                                           its end; at once: slow work in the runtime's own
                                           background, which ``close`` waits for).
``close()``                                the node stops: wait for what is still under way.
=========================================  ====================================================

Which runtime runs an attempt is decided in one place, ``osmo.runtime.choose``. The
runtimes: ``osmo.runtime.process`` (host processes, plain or in a bubblewrap sandbox) and
``osmo.runtime.container`` (the task's image, through podman or docker). A new runtime (a
Kubernetes pod, a Slurm job) implements :class:`Runtime` and passes
``osmo.testing.check_runtime`` (``tests/runtime/test_contract.py``); its start is watched
through a local process (the command itself, the engine's CLI attached to its container, a
job's watcher), which is what the pool's reactor and a restarted server's clean-up know.

A runtime whose launches are not the node's children and outlive it (a Slurm job, a pod)
also implements :class:`Adopting`: the pool journals its attempts (``osmo.worker.journal``),
the node tells the server so when it registers (the server then holds its attempts for a
grace when it goes), and a restarted node re-attaches to each journaled launch
(``adopt``) instead of running it again; a launch of its owner it finds and does not adopt
is cancelled (``cancel_orphans``).

This module holds the contract's types only; it runs nothing.
"""

from __future__ import annotations

import contextlib
import socket
import subprocess
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Protocol, runtime_checkable

from osmo.errors import OsmoError
from osmo.layout import AttemptDirs
from osmo.scheduler.types import PrepareAttempt
from osmo.spec.model import ResourceSpec, TaskSpec

__all__ = ["HOST_PATHS", "Adopting", "Attempt", "ConnectError", "Connector", "ExecCommand",
           "Launch", "Paths", "PrepareError", "ProcessHandle", "RunnerPaths", "Runtime",
           "SocketMaker", "StartError", "Terms", "dial"]

class StartError(OsmoError):
    """A command could not be started (not found, not executable, bad working folder)."""


class PrepareError(OsmoError):
    """An attempt's folder, files or tokens could not be prepared (message says which)."""


class ConnectError(OsmoError):
    """Port-forward cannot reach the task's port (the message says why, for the client)."""


@dataclass(frozen=True)
class Paths:
    """How a runtime shows a task its attempt: what its tokens and ``OSMO_*`` variables name.

    The default (:data:`HOST_PATHS`) is the host's own paths: ``{{output}}`` is the attempt's
    ``output.partial`` folder, ``{{input:N}}`` the input's folder on this node, declared
    absolute ``files:`` are written under the attempt's ``files/`` and rewritten wherever the
    task's text names them (``osmo.worker.workdir``).

    Attributes:
        output: what ``{{output}}`` and ``OSMO_OUTPUT`` name (None: the host's folder).
        input_dir: what ``{{input:N}}`` names, ``{}`` standing for N (None: the input's own
            folder on this node).
        files_root: ``OSMO_FILES_ROOT`` (None: the attempt's ``files/``).
        bound_files: declared absolute ``files:`` appear at their own paths (bound there),
            so nothing is rewritten.
        own_env: the task's environment is its spec's and osmo's only (its image supplies
            ``PATH`` and the rest), not the worker's base environment.
        hidden_secrets: credential variables reach the task apart from its argv and
            environment (``Launch.secret_env``; an engine shows both), so ``$(NAME)`` of a
            credential stays as written in ``args``.
        linked_inputs: its artifact inputs are hard links of the checked blobs rather than
            copies: the runtime shows them read-only.
        hosts: ``{{host:NAME}}`` for each group member (None: the placement's addresses).
        runner: where a typed task's runner, its context file and osmo's code appear to the
            task (None: the host's own; a container runtime shows them in the task's image).
    """

    output: str | None = None
    input_dir: str | None = None
    files_root: str | None = None
    bound_files: bool = False
    own_env: bool = False
    hidden_secrets: bool = False
    linked_inputs: bool = False
    hosts: Mapping[str, str] | None = None
    runner: RunnerPaths | None = None


@dataclass(frozen=True)
class RunnerPaths:
    """How a runtime that shows a task other paths than the host's runs a typed task there.

    The runner (``python -m osmo.tasktypes.runner CONTEXT``) then runs on the view's own
    interpreter (an image's ``python3``), with osmo's code shown read-only under ``code``.

    Attributes:
        python: the interpreter, as the task's view names it.
        context: where the attempt's context file is shown (read-only).
        workdir: where the attempt's working folder is shown (its working folder).
        code: the folder holding osmo's own packages (``osmo``, ``osmo_plugins``).
        types: where a custom type's folders are shown, ``{}`` standing for their index.
    """

    python: str
    context: str
    workdir: str
    code: str
    types: str


HOST_PATHS = Paths()
"""The host's own paths (see :class:`Paths`)."""


@dataclass(frozen=True)
class Launch:
    """What runs for a prepared attempt, and what it holds until its end.

    The pool makes it (``osmo.worker.workdir.prepare``) and the attempt's runtime completes it
    (``Runtime.prepare``). Secret values are never shown by ``repr``.

    Attributes:
        argv: the command, tokens resolved.
        cwd: its working folder on this node (the attempt's ``work/``).
        env: its complete environment.
        secrets: every value of its credentials (its logs mask them).
        secret_env: credential variables kept out of ``argv`` and ``env``
            (``Paths.hidden_secrets``): the runtime hands them over privately.
        secret_files: the files its credential mounts wrote (deleted at its end).
        scratch: large input copies, deleted when it ends.
        files: each declared ``files:`` or credential-mount path → where it was written.
        inputs: each ``inputs:`` entry's folder on this node (None: it has none).
        max_output_bytes: the task's ``storage``: its output may hold no more.
        notes: osmo lines for its log from before the log existed (an image's id).
        image_id: the image it runs in (lineage), when it runs in one.
        waits: its start waits for another attempt (a container group's peer for its
            lead): the pool calls ``start`` off its reactor.
        run: the runtime's own description (a sandbox's ``View``, a container's
            ``ContainerRun``); only that runtime reads it.
    """

    argv: tuple[str, ...]
    cwd: Path
    env: dict[str, str] = field(repr=False)
    secrets: tuple[str, ...] = field(default=(), repr=False)
    secret_env: dict[str, str] = field(default_factory=dict, repr=False)
    secret_files: tuple[Path, ...] = ()
    scratch: tuple[Path, ...] = ()
    files: Mapping[str, Path] = field(default_factory=dict)
    inputs: tuple[str | None, ...] = ()
    max_output_bytes: int | None = None
    notes: tuple[str, ...] = ()
    image_id: str | None = None
    waits: bool = False
    run: object = None


@dataclass(frozen=True)
class Attempt:
    """What a runtime is told of the attempt it prepares a launch for.

    Attributes:
        cmd: its placement, inputs resolved to their folders on this node.
        task: what runs.
        dirs: its folder.
        resources: its request (a container's cpu and memory limits).
        gpus: the GPU indices the pool assigned it.
        credential: stored credentials by name (a registry's, for a pull); None: none.
        terms: its workflow's time limit and priority, for a cluster's own scheduler.
        waiting: tells the server why a cluster's scheduler holds the started attempt (a pod
            Pending, a Slurm job PENDING), and ``""`` once it runs: any thread, cheap; say
            a reason once, not at every poll (the node's ``AttemptWaiting`` report).
    """

    cmd: PrepareAttempt
    task: TaskSpec
    dirs: AttemptDirs
    resources: ResourceSpec = field(default_factory=ResourceSpec)
    gpus: tuple[int, ...] = ()
    credential: Callable[[str], Mapping[str, str] | None] | None = None
    terms: Terms = field(default_factory=lambda: Terms())
    waiting: Callable[[str], None] = field(default=lambda _reason: None, repr=False)


@dataclass(frozen=True)
class Terms:
    """What a workflow asks of a cluster scheduler beside resources (``wire.Prepare``).

    Attributes:
        exec_timeout: the workflow's ``exec_timeout`` in seconds (None: none, or unknown).
            osmo's own timeout (the server's) still holds; a cluster job may ask for
            this much time (Slurm's ``--time``).
        priority: ``HIGH``, ``NORMAL`` or ``LOW`` (None: unknown).
    """

    exec_timeout: float | None = None
    priority: str | None = None


@dataclass(eq=False)
class ProcessHandle:
    """A started launch: the local process that stands for it.

    The command itself, in its own process group (its group id is ``pid``); or the engine's
    CLI attached to the launch's container; in a sandbox, bubblewrap.

    Attributes:
        pid: the main process id (also its process group id).
        exit_fd: a file descriptor that becomes readable when the main process has ended.
        stdout_fd: read end of the stdout pipe (non-blocking).
        stderr_fd: read end of the stderr pipe (non-blocking).
        sandboxed: the command runs in a sandbox (``pid`` is bwrap's).
        status_fd: read end of bwrap's status pipe (non-blocking; -1: none).
        notes_fd: read end of a pipe of the runtime's own lines about the launch (a cluster
            job's queue reason, its node), logged as osmo's (non-blocking; -1: none; the
            runtime closes it on ``release``).
        started_at: the clock of ``osmo.runtime.process.proctable.process_start_time`` read
            just before the spawn: at most a moment before the process's own start time,
            without reading ``/proc``.
        setup_failed: set by ``reap``: the sandbox could not be set up, the command never ran
            (its exit code is bwrap's 1; bwrap's message is on stderr).
        start_failed: set by ``reap``: the launch never ran its command, for a reason that
            starting it again would not change (a pod's image cannot be pulled): the
            attempt fails to start with this message, whatever the exit code.
        lost: set by ``reap``: the launch was lost to its infrastructure (a pod evicted,
            preempted, its node lost): the attempt is lost with this message (rescheduled,
            not counted as a retry), whatever the exit code.
        output_failed: set by ``reap``: the command ran, but its output could not be taken
            back from where it ran (a pod's collector failed, or sent what the node refused):
            an exit that would hand outputs on fails with this message instead, and nothing
            is promoted.
    """

    pid: int
    exit_fd: int
    stdout_fd: int
    stderr_fd: int
    popen: subprocess.Popen[bytes]
    sandboxed: bool = False
    status_fd: int = -1
    notes_fd: int = -1
    setup_failed: bool = False
    started_at: float | None = None
    start_failed: str | None = None
    lost: str | None = None
    output_failed: str | None = None


@dataclass(frozen=True)
class ExecCommand:
    """What an exec session runs (``Runtime.exec``), spawned by ``osmo.worker.exec_process``.

    Attributes:
        argv: the command to spawn.
        cwd: its working folder.
        env: its environment.
        ctty: its terminal (with a TTY) becomes the spawned process's controlling terminal.
        pass_fds: descriptors it must inherit (a sandbox's user namespace).
        enter: a context the spawn happens in (the node's network namespace).
    """

    argv: list[str]
    cwd: Path
    env: dict[str, str] = field(repr=False)
    ctty: bool = True
    pass_fds: tuple[int, ...] = ()
    enter: Callable[[], contextlib.AbstractContextManager[None]] = contextlib.nullcontext


Connector = Callable[[int, bool], socket.socket]
"""``(port, udp) → a socket connected to that port of the task``; raises ConnectError."""


class Runtime(Protocol):
    """How attempts run (see the module docstring for the order of the calls).

    Thread-safety: ``paths``, ``prepare``, ``start``, ``exec`` and ``connector`` may be
    called from any thread, for different attempts at once; ``kill``, ``reap``, ``release``
    and ``cleanup`` come from the pool's reactor thread and must not block it.
    """

    def describe(self) -> str:
        """How it runs tasks, in a few words: ``process``, ``container (podman 4.3.1)``."""
        ...

    def paths(self, cmd: PrepareAttempt) -> Paths:
        """How the task of the attempt ``cmd`` places sees its attempt and its peers."""
        ...

    def prepare(self, launch: Launch, attempt: Attempt, *,
                progress: Callable[[str], None]) -> Launch:
        """``launch`` complete for this runtime (made with :meth:`paths`' paths).

        ``progress`` gets lines worth showing in the attempt's log meanwhile (a pull's).

        Raises:
            OsmoError: it cannot be run here (an image that cannot be had, a network that
                cannot be made, a view a sandbox cannot take); nothing stays held then.
        """
        ...

    def start(self, launch: Launch) -> ProcessHandle:
        """Spawn ``launch`` (blocks first when ``launch.waits``).

        Raises:
            StartError: it cannot be started (the message is the user's).
        """
        ...

    def kill(self, handle: ProcessHandle, *, force: bool = False) -> None:
        """Signal the whole launch: SIGTERM, or SIGKILL when ``force``. Never raises."""
        ...

    def reap(self, handle: ProcessHandle) -> int:
        """After ``exit_fd`` became readable: the exit code; nothing of it keeps running."""
        ...

    def release(self, handle: ProcessHandle) -> None:
        """Close the handle's descriptors (idempotent)."""
        ...

    def exec(self, launch: Launch, command: Sequence[str], *, tty: bool,
             term: str | None) -> ExecCommand:
        """What runs ``command`` beside the running ``launch``, seeing what its task sees.

        ``term``: the client's ``TERM``, set with a TTY.
        """
        ...

    def connector(self, launch: Launch, handle: ProcessHandle) -> Connector:
        """How port-forward connects to the running ``launch``'s ports.

        Raises:
            ConnectError: the task can have no reachable port (the message says why).
            OsmoError: the runtime cannot tell (its engine failed).
        """
        ...

    def cleanup(self, launch: Launch) -> None:
        """What this runtime holds for ``launch`` goes, after its end; returns at once."""
        ...

    def close(self) -> None:
        """The node stops: wait for calls still under way, let go of shared resources."""
        ...


@runtime_checkable
class Adopting(Protocol):
    """A runtime whose launches outlive the node (see the module docstring)."""

    def adopt(self, dirs: AttemptDirs, shipped: Mapping[str, int]
              ) -> tuple[Launch, ProcessHandle]:
        """Re-attach to the launch a previous life of the node started in ``dirs``.

        ``shipped``: bytes of its ``stdout`` and ``stderr`` already logged (the handle's
        pipes resume after them). Returns its launch as far as the runtime knows it (its
        ``run`` is the runtime's own), and a handle watched like a started one's.

        Raises:
            OsmoError: there is nothing to adopt there, or not safely (the attempt is lost).
        """
        ...

    def adopted(self) -> set[str]:
        """The ids of the launches (jobs, pods) it adopted and still watches."""
        ...

    def cancel_orphans(self, keep: Sequence[str] = ()) -> list[str]:
        """Cancel every launch of this node's owner but those in ``keep``; the ids cancelled.

        ``keep``: what the node's runtimes adopted (:meth:`adopted`).
        """
        ...


_CONNECT_TIMEOUT = 5.0


SocketMaker = Callable[[socket.AddressFamily, socket.SocketKind], socket.socket]
"""``(family, kind) → a new socket`` (one inside a network namespace)."""


def dial(host: str, port: int, *, udp: bool, make: SocketMaker = socket.socket
         ) -> socket.socket:
    """A socket of ``host``'s family, made by ``make``, connected to ``host:port``.

    Raises:
        ConnectError: ``cannot connect to HOST:PORT: <why>``.
    """
    try:
        made = make(socket.AF_INET6 if ":" in host else socket.AF_INET,
                    socket.SOCK_DGRAM if udp else socket.SOCK_STREAM)
        try:
            made.settimeout(_CONNECT_TIMEOUT)
            made.connect((host, port))
            made.settimeout(None)
        except OSError:
            made.close()
            raise
    except OSError as exc:
        raise ConnectError(f"cannot connect to {host}:{port}: {exc.strerror or exc}") from exc
    return made
