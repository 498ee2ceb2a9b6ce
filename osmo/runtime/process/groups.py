"""Commands as process groups: the spawning, killing and reaping under both process runtimes.

:class:`ProcessGroups` runs one command per process group; ``osmo.runtime.process.runtime``
(plain) and ``osmo.runtime.process.sandboxed`` (in bubblewrap) launch attempts through it,
and the container runtime runs its engine's CLI through it. What it owns:

- spawning: the command starts in a new session (``start_new_session=True``, so its process
  group id is its pid), with the given working folder and environment, stdin from
  ``/dev/null``, stdout and stderr as non-blocking pipes.
- the sandbox: given a :class:`~osmo.runtime.process.sandbox.Sandbox` and a start's ``view``,
  the command runs inside bubblewrap (``osmo.runtime.process.sandbox``), spawned in the
  node's namespaces (``Sandbox.entered``, ``Sandbox.fds``); bwrap's two processes then lead
  the group. ``--die-with-parent`` ends the sandbox when the spawning thread's process dies
  (not while bwrap is still setting it up: the pool records every pid at once for that,
  ``osmo.worker.procs``).
  Unsandboxed, the command starts under util-linux's ``setpriv --pdeathsig KILL``, so it
  too dies with its worker (the command's own children are then left to ``kill_stale``
  after a restart). The signal is set by that wrapper, not by a ``preexec_fn``, so CPython
  keeps its ``vfork``: a ``fork`` copies the server's page tables, 4-5 ms of the server's
  CPU per spawn at its size (measured: 66 against 143 unsandboxed `true` tasks a second).
  The wrapper would report a command that cannot be executed as its own exit 126 or 127,
  so such a start is failed first, with the error a spawn would raise (``check_runnable``).
  Without ``setpriv`` on the ``PATH``, a ``preexec_fn`` sets the signal.
- waiting without polling: a ``pidfd`` (``os.pidfd_open``) becomes readable when the process
  ends, so a caller's selector watches exits and pipes together.
- killing: a signal always goes to the whole process group (grandchildren included). The
  caller sends ``SIGTERM`` first and ``SIGKILL`` after its grace period. In a sandbox,
  ``SIGTERM`` goes to every member of the group but bwrap's own two processes (bwrap does not
  forward signals, and its death would SIGKILL the sandbox at once: no grace); the command
  then ends, and bwrap exits with its exit code. ``SIGKILL`` goes to the whole group.
- exit codes: killed by signal N → ``128 + N`` (the shell's convention). A sandbox that
  could not be set up (bwrap exits 1 before the command runs: a mount that vanished under
  it, a folder it cannot make) is told from the command's own exit: bwrap reports the
  command's exit code on its status pipe (``--json-status-fd``) only when the command ran,
  and ``reap`` marks the handle ``setup_failed`` otherwise (the caller may start it again).
- crash clean-up: ``osmo.runtime.process.proctable.kill_stale`` kills a process group left
  over by a crashed server, only if the pid still belongs to the process that was started
  (its start time matches); a handle's ``started_at`` is read on that module's clock.

When the main process ends, whatever is left of its group is killed: like a container, an
attempt ends when its main process does, and background children do not outlive it.

It must not know about attempts, logs or the scheduler.
"""

from __future__ import annotations

import contextlib
import ctypes
import functools
import os
import shutil
import signal
import subprocess
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path

from osmo.runtime.api import ProcessHandle, StartError
from osmo.runtime.process.proctable import group_members, start_clock, stat_fields
from osmo.runtime.process.sandbox import Sandbox, View

__all__ = ["ProcessGroups", "check_command", "check_runnable", "die_with_parent", "exit_code_of",
           "pdeathsig_wrapper"]


def exit_code_of(returncode: int) -> int:
    """Normalise a ``Popen.returncode``: killed by signal N (``-N``) → ``128 + N``."""
    return 128 - returncode if returncode < 0 else returncode


class ProcessGroups:
    """Runs commands as host processes, one process group each (see the module docstring).

    Args:
        sandbox: run every start that has a ``view`` in this sandbox (None: never).
    """

    def __init__(self, sandbox: Sandbox | None = None) -> None:
        self.sandbox = sandbox

    def start(self, argv: Sequence[str], *, cwd: Path, env: Mapping[str, str],
              view: View | None = None) -> ProcessHandle:
        """Start ``argv`` in its own session. Raises StartError with a user-facing message.

        With a sandbox and a ``view``, in the sandbox (the command is looked up first, so a
        missing one fails the start as it does outside).
        """
        if not argv:
            raise StartError("empty command")
        command = list(argv)
        preexec: Callable[[], object] | None = None
        status_r = status_w = -1
        fds: tuple[int, ...] = ()
        entered: contextlib.AbstractContextManager[None] = contextlib.nullcontext()
        sandboxed = False
        if self.sandbox is not None and view is not None:
            sandboxed = True
            check_command(argv[0], cwd, env, self.sandbox)
            if self.sandbox.status:
                status_r, status_w = _status_pipe(argv[0])
            command = self.sandbox.argv(argv, view, status_w)  # --die-with-parent
            fds, entered = self.sandbox.fds, self.sandbox.entered()
        elif (wrapper := pdeathsig_wrapper()) is not None:
            check_runnable(argv[0], cwd, env)
            command = [*wrapper, *argv]
        else:
            preexec = die_with_parent()
        started_at = start_clock()
        try:
            with entered:  # in the node's network namespace (``osmo.runtime.process.netns``)
                popen = subprocess.Popen(
                    command,
                    cwd=cwd,
                    env=dict(env),
                    stdin=subprocess.DEVNULL,
                    stdout=subprocess.PIPE,
                    stderr=subprocess.PIPE,
                    start_new_session=True,
                    preexec_fn=preexec,
                    pass_fds=(*fds, status_w) if status_w >= 0 else fds,
                )
        except OSError as exc:
            _close_fds(status_r)
            raise StartError(_start_message(argv[0], cwd, exc)) from exc
        except subprocess.SubprocessError as exc:  # the preexec_fn failed in the child
            _close_fds(status_r)
            raise StartError(f"cannot start '{argv[0]}': {exc}") from exc
        finally:
            _close_fds(status_w)  # bwrap has its copy
        try:
            handle = _handle(popen, sandboxed=sandboxed, status_fd=status_r)
        except OSError as exc:  # e.g. out of file descriptors: do not leave it running
            os.killpg(popen.pid, signal.SIGKILL)
            popen.wait()
            _close_pipes(popen)
            _close_fds(status_r)
            raise StartError(f"cannot watch '{argv[0]}': {exc.strerror or exc}") from exc
        handle.started_at = started_at
        return handle

    def kill(self, handle: ProcessHandle, *, force: bool = False) -> None:
        """Send SIGTERM (SIGKILL when ``force``) to the handle's process group."""
        if handle.popen.returncode is not None:
            return  # reaped: the group id may name someone else's group now
        if handle.sandboxed and not force:
            _terminate_inside(handle.pid)
            return
        try:
            os.killpg(handle.pid, signal.SIGKILL if force else signal.SIGTERM)
        except (ProcessLookupError, PermissionError):
            pass

    def reap(self, handle: ProcessHandle) -> int:
        """Kill what is left of the group, then collect the main process's exit code.

        The main process is a zombie until collected, so its group id is still ours.
        """
        self.kill(handle, force=True)
        code = exit_code_of(handle.popen.wait())
        if handle.status_fd >= 0 and code == _BWRAP_FAILED:
            handle.setup_failed = not _command_ran(handle.status_fd)
        return code

    def release(self, handle: ProcessHandle) -> None:
        """Close the pidfd, both pipes and the status pipe (idempotent)."""
        _close_pipes(handle.popen)
        _close_fds(handle.exit_fd, handle.status_fd)
        handle.exit_fd = handle.status_fd = -1


_BWRAP_FAILED = 1  # bwrap's own exit code when it fails


def _status_pipe(program: str) -> tuple[int, int]:
    """The status pipe bwrap writes to: its read end non-blocking (read once bwrap exited)."""
    try:
        read, write = os.pipe2(os.O_CLOEXEC)
    except OSError as exc:
        raise StartError(f"cannot start '{program}': {exc.strerror or exc}") from exc
    os.set_blocking(read, False)
    return read, write


def _command_ran(status_fd: int) -> bool:
    """Whether bwrap's status says the command ran (its exit code is there).

    bwrap writes ``{ "child-pid": N ... }`` once it has forked and ``{ "exit-code": N }``
    when the command it started ends, but only if its setup finished and it ran the
    command; the sandboxed command itself never holds this pipe.
    """
    try:
        data = os.read(status_fd, 65536)
    except BlockingIOError:
        return False
    return b'"exit-code"' in data


def _close_fds(*fds: int) -> None:
    for fd in fds:
        if fd >= 0:
            os.close(fd)


def _close_pipes(popen: subprocess.Popen[bytes]) -> None:
    for pipe in (popen.stdout, popen.stderr):
        if pipe is not None:
            pipe.close()


def _handle(popen: subprocess.Popen[bytes], *, sandboxed: bool, status_fd: int) -> ProcessHandle:
    assert popen.stdout is not None and popen.stderr is not None
    out, err = popen.stdout.fileno(), popen.stderr.fileno()
    os.set_blocking(out, False)
    os.set_blocking(err, False)
    return ProcessHandle(popen.pid, os.pidfd_open(popen.pid), out, err, popen, sandboxed,
                         status_fd)


_PR_SET_PDEATHSIG = 1


@functools.cache  # loaded in the parent: the child between fork and exec only calls it
def die_with_parent() -> Callable[[], object]:
    """A ``preexec_fn``: SIGKILL the child when the thread that spawned it ends."""
    prctl = ctypes.CDLL(None, use_errno=True).prctl
    return functools.partial(prctl, _PR_SET_PDEATHSIG, signal.SIGKILL, 0, 0, 0)


@functools.cache
def pdeathsig_wrapper() -> tuple[str, ...] | None:
    """The argv prefix that starts a command with ``PR_SET_PDEATHSIG`` = SIGKILL, if any.

    util-linux's ``setpriv`` (2.33+) where it is found; None: a ``preexec_fn`` must.
    """
    found = shutil.which("setpriv")
    if found is None:
        return None
    try:
        usage = subprocess.run([found, "--help"], capture_output=True, text=True, timeout=10,
                               check=False).stdout
    except (OSError, subprocess.SubprocessError):
        return None
    return (found, "--pdeathsig", "KILL", "--") if "--pdeathsig" in usage else None


def check_runnable(program: str, cwd: Path, env: Mapping[str, str]) -> None:
    """:func:`check_command`, and the errors an ``execve`` of the program would give.

    A script's interpreter (``#!``) must exist and a file must be a script or a binary, as
    the kernel requires (a wrapper's ``execvp`` would run anything else with ``sh``).

    Raises:
        StartError: the message a failed spawn gives.
    """
    path = check_command(program, cwd, env)
    try:
        with open(path, "rb") as file:
            head = file.read(256)
    except OSError:
        return  # unreadable but executable: the exec itself decides
    if head.startswith(b"#!"):
        words = head[2:].split(b"\n", 1)[0].split()
        if not words or not os.access(os.fsdecode(words[0]), os.X_OK):
            raise StartError(f"command not found: '{program}'")
    elif not head.startswith(b"\x7fELF"):
        raise StartError(f"cannot start '{program}': Exec format error")


def check_command(program: str, cwd: Path, env: Mapping[str, str],
                  sandbox: Sandbox | None = None) -> str:
    """Fail a start that cannot run the way a spawn fails (bwrap or a fork would only exit).

    A program is looked up in ``env``'s ``PATH``, only in the folders ``sandbox`` shows.

    Returns:
        where the program was found.

    Raises:
        StartError: no working folder, or the command is not found or not executable.
    """
    if not program:
        raise StartError("empty command")
    if not cwd.is_dir():
        raise StartError(f"working folder not found: '{cwd}'")
    if "/" not in program:
        search = env.get("PATH", os.defpath)
        found = _which(program, search if sandbox is None else _shown_path(search, sandbox))
        if found is None:
            raise StartError(f"command not found: '{program}'")
        return found
    path = str(cwd / program)
    if not os.path.exists(path):
        raise StartError(f"command not found: '{program}'")
    if not os.access(path, os.X_OK) or os.path.isdir(path):
        raise StartError(f"command not executable: '{program}' (permission denied)")
    return path


@functools.lru_cache(maxsize=64)  # a pool's tasks share a few PATHs
def _shown_path(search: str, sandbox: Sandbox) -> str:
    """``search`` (a ``PATH``) without the folders ``sandbox`` does not show."""
    return os.pathsep.join(p for p in search.split(os.pathsep) if p and sandbox.shows(p))


_FOUND: dict[tuple[str, str], str] = {}  # (program, PATH) → where it was found
_FOUND_MAX = 1024


def _which(program: str, search: str) -> str | None:
    """``shutil.which``, remembered: a program found before is checked in one call.

    (Only whether it can be run matters here; the sandbox's own lookup runs the command.)
    """
    found = _FOUND.get((program, search))
    if found is not None and os.access(found, os.X_OK):
        return found
    found = shutil.which(program, path=search)
    if found is not None:
        if len(_FOUND) >= _FOUND_MAX:
            _FOUND.clear()
        _FOUND[program, search] = found
    return found


def _terminate_inside(pgid: int) -> None:
    """SIGTERM to every process of a sandbox's group but bwrap's own two (the module docstring).

    bwrap's outer process is the group leader; its child is pid 1 of the sandbox.
    """
    for pid in group_members(pgid):
        fields = stat_fields(pid)
        if pid == pgid or fields is None or int(fields[1]) == pgid:
            continue
        try:
            os.kill(pid, signal.SIGTERM)
        except (ProcessLookupError, PermissionError):
            pass


def _start_message(program: str, cwd: Path, exc: OSError) -> str:
    if isinstance(exc, FileNotFoundError):
        if exc.filename is not None and os.fsdecode(exc.filename) == os.fsdecode(cwd):
            return f"working folder not found: '{cwd}'"
        return f"command not found: '{program}'"
    if isinstance(exc, PermissionError):
        return f"command not executable: '{program}' (permission denied)"
    return f"cannot start '{program}': {exc.strerror or exc}"
