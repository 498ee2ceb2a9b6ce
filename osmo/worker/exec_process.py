"""The process of an ``osmo workflow exec`` session: its terminal or pipes.

What runs, and where, is the attempt's runtime's (``Runtime.exec``, an
``osmo.runtime.api.ExecCommand``): in a container task, ``<engine> exec -i [-t]`` into its
container; in a process task, the command in the attempt's working folder with its complete
environment, in a new sandbox over the attempt's own view when the attempt runs sandboxed.

:class:`ExecProcess` runs it in a session of its own: with a TTY, on a fresh pseudo-terminal
that becomes its controlling terminal (so a Ctrl-C byte from the client is a SIGINT to the
foreground job, and a resize a SIGWINCH); without one, on pipes. It is spawned by the
thread that will wait for it and dies with that thread (``PR_SET_PDEATHSIG``), and its whole
process group is killed when it exits or the session ends: nothing it started outlives the
session (a process the command started inside a container lives until the container ends).
"""

from __future__ import annotations

import fcntl
import os
import select
import signal
import struct
import subprocess
import termios
import threading
from collections.abc import Callable

from osmo.runtime.api import ExecCommand
from osmo.runtime.process.groups import die_with_parent, exit_code_of
from osmo.transport.streams import CHUNK

__all__ = ["DEFAULT_COMMAND", "ExecProcess"]

DEFAULT_COMMAND = ("/bin/sh",)
"""What an exec session runs when its client names no command."""
_POLL = 0.2


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
        fds = command.pass_fds
        entered = command.enter()
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
