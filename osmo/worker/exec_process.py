"""The process of an ``osmo workflow exec`` session: what it runs, and its terminal or pipes.

:func:`exec_argv` decides what runs: in a container task, ``<engine> exec -i [-t]`` into the
attempt's container (its working folder and environment are the container's); in a
process task, the command in the attempt's working folder with the attempt's complete
environment, wrapped in a new bubblewrap sandbox over the attempt's own view when the
attempt runs sandboxed (so it sees what the task sees, the node's network and uid included:
a pid namespace of its own, not the task's processes).

:class:`ExecProcess` runs it in a session of its own: with a TTY, on a fresh pseudo-terminal
that becomes its controlling terminal (so a Ctrl-C byte from the client is a SIGINT to the
foreground job, and a resize a SIGWINCH); without one, on pipes. It is spawned by the
thread that will wait for it and dies with that thread (``PR_SET_PDEATHSIG``), and its whole
process group is killed when it exits or the session ends: nothing it started outlives the
session (a process the command started inside a container lives until the container ends).
"""

from __future__ import annotations

import contextlib
import fcntl
import os
import select
import signal
import struct
import subprocess
import termios
import threading
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

from osmo.runtime.container.engine import ContainerEngine
from osmo.runtime.process.groups import die_with_parent, exit_code_of
from osmo.runtime.process.sandbox import Sandbox
from osmo.transport.streams import CHUNK, SessionGrant
from osmo.worker.workdir import Launch

__all__ = ["DEFAULT_COMMAND", "ExecCommand", "ExecProcess", "exec_argv"]

DEFAULT_COMMAND = ("/bin/sh",)
_POLL = 0.2


@dataclass(frozen=True)
class ExecCommand:
    """What an exec session runs; ``ctty``: its terminal becomes the spawned process's.

    ``sandbox``: the sandbox ``argv`` runs in (it is spawned as that sandbox says: in the
    node's network, with its descriptors).
    """

    argv: list[str]
    cwd: Path
    env: dict[str, str] = field(repr=False)
    ctty: bool = True
    sandbox: Sandbox | None = None


def exec_argv(launch: Launch, grant: SessionGrant, sandbox: Sandbox | None,
              engine: ContainerEngine | None) -> ExecCommand:
    """What runs ``grant``'s command for the attempt ``launch`` describes.

    In a sandbox with a TTY, the command is started by ``setsid -w -c`` inside it: a
    session leader in the sandbox's own pid namespace, whose shell can then move its jobs
    to the terminal's foreground (a leader outside the namespace is invisible to it).
    """
    command = list(grant.command or DEFAULT_COMMAND)
    term = {"TERM": grant.term} if grant.tty else {}
    if launch.container is not None and engine is not None:
        argv = [engine.engine.path, "exec", "-i", *(["-t"] if grant.tty else []),
                *(f"--env={k}={v}" for k, v in term.items()), launch.container.name, *command]
        return ExecCommand(argv, launch.cwd, engine.env)
    env = {**launch.env, **term}
    if launch.view is not None and sandbox is not None:
        inner = ["setsid", "-w", "-c", *command] if grant.tty else command
        return ExecCommand(sandbox.argv(inner, launch.view), launch.cwd, env, ctty=False,
                           sandbox=sandbox)
    return ExecCommand(command, launch.cwd, env)


def _winsize(rows: int, cols: int) -> bytes:
    return struct.pack("HHHH", max(1, min(rows, 10_000)), max(1, min(cols, 10_000)), 0, 0)


class ExecProcess:
    """One exec command (see the module docstring); spawned by the constructor.

    Args:
        out: receives ``(1, bytes)`` for stdout (and the terminal), ``(2, bytes)`` for stderr.

    Raises:
        OSError: it cannot be spawned (FileNotFoundError: no such command).
    """

    def __init__(self, command: ExecCommand, *, tty: bool, size: tuple[int, int],
                 out: Callable[[int, bytes], object]) -> None:
        argv, cwd, env = command.argv, command.cwd, command.env
        self._out = out
        self._lock = threading.Lock()
        self._reaped = False
        self._master: int | None = None
        pdeath = die_with_parent()
        box = command.sandbox
        fds = box.fds if box is not None else ()
        entered = box.entered() if box is not None else contextlib.nullcontext()
        if tty:
            master, slave = os.openpty()
            fcntl.ioctl(slave, termios.TIOCSWINSZ, _winsize(*size))

            def child() -> None:
                if command.ctty:
                    fcntl.ioctl(0, termios.TIOCSCTTY, 0)
                pdeath()

            try:
                with entered:
                    self.proc = subprocess.Popen(argv, cwd=cwd, env=env, stdin=slave,
                                                 stdout=slave, stderr=slave,
                                                 start_new_session=True, preexec_fn=child,
                                                 pass_fds=fds)
            except BaseException:
                os.close(master)
                raise
            finally:
                os.close(slave)
            self._master = master
            self._readers = {master: 1}
        else:
            with entered:
                self.proc = subprocess.Popen(argv, cwd=cwd, env=env, stdin=subprocess.PIPE,
                                             stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                                             bufsize=0, start_new_session=True,
                                             preexec_fn=pdeath, pass_fds=fds)
            assert self.proc.stdout is not None and self.proc.stderr is not None
            self._readers = {self.proc.stdout.fileno(): 1, self.proc.stderr.fileno(): 2}

    def run(self) -> int:
        """Relay its output until it exits; kill what it left; return its exit code."""
        fds = dict(self._readers)
        while fds:
            ready, _, _ = select.select(list(fds), [], [], _POLL)
            for fd in ready:
                if not self._read(fd, fds[fd]):
                    del fds[fd]
            if not ready and self.proc.poll() is not None:
                for fd, channel in fds.items():  # what is left, then stop (a child may hold it)
                    while select.select([fd], [], [], 0)[0] and self._read(fd, channel):
                        pass
                break
        code = exit_code_of(self.proc.wait())
        self.kill()
        with self._lock:
            self._reaped = True
        self._close_fds()
        return code

    def _read(self, fd: int, channel: int) -> bool:
        try:
            data = os.read(fd, CHUNK)
        except OSError:  # EIO: the terminal's last user closed it
            return False
        if data:
            self._out(channel, data)
        return bool(data)

    def write(self, data: bytes) -> None:
        """Give the command input (a TTY's keys, Ctrl-C as the byte 0x03)."""
        try:
            if self._master is not None:
                os.write(self._master, data)
            elif self.proc.stdin is not None:
                self.proc.stdin.write(data)
        except (OSError, ValueError):
            pass  # it stopped reading, or exited

    def close_input(self) -> None:
        """End of input (pipes; a terminal gets Ctrl-D from its user instead)."""
        if self._master is None and self.proc.stdin is not None:
            try:
                self.proc.stdin.close()
            except OSError:
                pass

    def resize(self, rows: int, cols: int) -> None:
        """The client's terminal changed size (the foreground job gets SIGWINCH)."""
        if self._master is not None:
            try:
                fcntl.ioctl(self._master, termios.TIOCSWINSZ, _winsize(rows, cols))
            except OSError:
                pass

    def kill(self) -> None:
        """SIGKILL its process group (idempotent; never after it was reaped)."""
        with self._lock:
            if self._reaped:
                return
            try:
                os.killpg(self.proc.pid, signal.SIGKILL)
            except OSError:
                pass

    def _close_fds(self) -> None:
        if self._master is not None:
            os.close(self._master)
            self._master = None
        for pipe in (self.proc.stdin, self.proc.stdout, self.proc.stderr):
            if pipe is not None:
                try:
                    pipe.close()
                except OSError:
                    pass
