"""Drive a ``ContainerRuns`` handle the way the worker pool does: pipes and the exit fd."""

from __future__ import annotations

import time
from pathlib import Path

from osmo.runtime import ProcessHandle
from osmo.runtime.container import ContainerRun, ContainerRuns
from osmo.testing.runtimes import Pipes

TIMEOUT = 60.0


class Run(Pipes):
    """A started container and what it wrote so far."""

    def __init__(self, runtime: ContainerRuns, handle: ProcessHandle) -> None:
        super().__init__(handle)
        self.runtime = runtime

    def read_until(self, text: bytes, timeout: float = TIMEOUT) -> None:
        """Read both pipes until ``text`` is in stdout (fails after ``timeout``)."""
        assert self.until(text, timeout), (
            f"no {text!r} in stdout; out={bytes(self.out)!r} err={bytes(self.err)!r}")

    def finish(self, timeout: float = TIMEOUT) -> int:
        """Read to the end, reap and release; the exit code."""
        deadline = time.monotonic() + timeout
        while not self.ended():
            assert time.monotonic() < deadline, "the container did not end in time"
            self.pump(0.1)
        while self.pump(0):
            pass
        code = self.runtime.reap(self.handle)
        self.runtime.release(self.handle)
        return code


def start(runtime: ContainerRuns, run: ContainerRun, cwd: Path,
          env: dict[str, str] | None = None) -> Run:
    """Start ``run`` (its argv; ``env`` as the container's environment)."""
    handle = runtime.start(run.argv, cwd=cwd, env=env if env is not None else dict(run.env),
                           container=run)
    return Run(runtime, handle)
