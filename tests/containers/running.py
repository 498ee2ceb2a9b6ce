"""Drive a ``ContainerRuns`` handle the way the worker pool does: pipes and the exit fd."""

from __future__ import annotations

import os
import selectors
import time
from dataclasses import dataclass, field
from pathlib import Path

from osmo.runtime import ProcessHandle
from osmo.runtime.container import ContainerRun, ContainerRuns

TIMEOUT = 60.0


@dataclass
class Run:
    """A started container and what it wrote so far."""

    runtime: ContainerRuns
    handle: ProcessHandle
    out: bytearray = field(default_factory=bytearray)
    err: bytearray = field(default_factory=bytearray)
    eof: set[int] = field(default_factory=set)

    def read_until(self, text: bytes, timeout: float = TIMEOUT) -> None:
        """Read both pipes until ``text`` is in stdout (fails after ``timeout``)."""
        deadline = time.monotonic() + timeout
        while text not in self.out:
            ended = len(self.eof) == 2 and self._ended()
            assert not ended and time.monotonic() < deadline, (
                f"no {text!r} in stdout; out={bytes(self.out)!r} err={bytes(self.err)!r}")
            self._pump(0.1)

    def finish(self, timeout: float = TIMEOUT) -> int:
        """Read to the end, reap and release; the exit code."""
        deadline = time.monotonic() + timeout
        while not self._ended():
            assert time.monotonic() < deadline, "the container did not end in time"
            self._pump(0.1)
        while self._pump(0):
            pass
        code = self.runtime.reap(self.handle)
        self.runtime.release(self.handle)
        return code

    def _ended(self) -> bool:
        with selectors.DefaultSelector() as sel:
            sel.register(self.handle.exit_fd, selectors.EVENT_READ)
            return bool(sel.select(0))

    def _pump(self, timeout: float) -> bool:
        """Read what the open pipes have (waiting up to ``timeout``); True if any bytes came."""
        got = False
        with selectors.DefaultSelector() as sel:
            sel.register(self.handle.exit_fd, selectors.EVENT_READ, None)
            for fd, buf in ((self.handle.stdout_fd, self.out), (self.handle.stderr_fd, self.err)):
                if fd not in self.eof:
                    sel.register(fd, selectors.EVENT_READ, buf)
            for key, _ in sel.select(timeout):
                if key.data is None:
                    continue
                try:
                    data = os.read(key.fd, 65536)
                except BlockingIOError:
                    continue
                if not data:
                    self.eof.add(key.fd)
                key.data.extend(data)
                got = got or bool(data)
        return got


def start(runtime: ContainerRuns, run: ContainerRun, cwd: Path,
          env: dict[str, str] | None = None) -> Run:
    """Start ``run`` (its argv; ``env`` as the container's environment)."""
    handle = runtime.start(run.argv, cwd=cwd, env=env if env is not None else dict(run.env),
                           container=run)
    return Run(runtime, handle)
