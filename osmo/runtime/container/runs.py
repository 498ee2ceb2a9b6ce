"""A container run's life: its start through the engine's attached CLI, its kill, its removal.

:class:`ContainerRuns` spawns the engine's attached ``run`` CLI (``run_argv``) through
``ProcessGroups``: the container's output is that process's stdout/stderr, its exit code
the container's (125: the engine failed, its message on stderr; 126/127, or 1 from ``--init``
with a missing program: the command cannot run). A container we removed while it ran (a
forced kill) ends with 137, also when the CLI, finding it gone before it read its exit code,
says 127.

Kill goes to the container by name: ``kill --signal=TERM``, and ``rm -f`` for the forced kill
(it also removes a container still being created), each retried on a background thread until
it takes or the CLI ends. Signalling the CLI instead is unreliable: a SIGTERM that arrives
while it creates the container leaves the container behind and exits 0; a SIGKILL leaves it
running. A killed or failed (125) container is removed after its end, in the background;
whatever a crash leaves is found by label (``ContainerEngine.remove_labelled``).

A run's secret variables are written to its ``secret_env_file`` (0600) just before the spawn
and deleted on ``release``.
"""

from __future__ import annotations

import os
import threading
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, replace
from pathlib import Path

from osmo.runtime.api import ProcessHandle, StartError
from osmo.runtime.background import Background
from osmo.runtime.container.engine import ContainerEngine
from osmo.runtime.container.run import ContainerError, ContainerRun, run_argv, secret_env_text
from osmo.runtime.process.groups import ProcessGroups

__all__ = ["ContainerRuns"]

_KILL_DEADLINE = 60.0  # s: a CLI that neither creates its container nor ends by then is stuck


_VANISHED = 127  # podman's exit when its container is gone before it read its exit code
_KILLED = 128 + 9


@dataclass(eq=False)
class _Live:
    name: str
    secret_file: Path | None
    done: threading.Event
    killed: bool = False
    removed: bool = False  # removed (SIGKILL) by us while it ran: a forced kill or early reap
    code: int | None = None


class ContainerRuns:
    """Container runs through an engine's CLI (see the module docstring).

    ``start(argv, cwd=..., env=..., container=run)`` runs ``argv`` with exactly ``env`` in
    the container ``run`` describes (its own ``argv``/``env`` are replaced by these); with no
    ``container`` it runs a host process, as ``ProcessGroups`` does. The engine's CLI runs
    with the engine's environment in ``cwd``. Kill, reap and release act on the container
    too; see the module docstring. ``close()`` waits for the engine calls still under way.
    """

    def __init__(self, engine: ContainerEngine, *, processes: ProcessGroups | None = None,
                 kill_retry: float = 0.1) -> None:
        self.engine = engine
        self._processes = processes or ProcessGroups()
        self._retry = kill_retry
        self._live: dict[ProcessHandle, _Live] = {}
        self._background = Background("osmo-container-call")
        self._lock = threading.Lock()

    def start(self, argv: Sequence[str], *, cwd: Path, env: Mapping[str, str],
              container: ContainerRun | None = None) -> ProcessHandle:
        """Start the command (in ``container`` if given). Raises StartError."""
        if container is None:
            return self._processes.start(argv, cwd=cwd, env=env)
        run = replace(container, argv=tuple(argv), env=dict(env))
        try:
            cli = run_argv(self.engine.engine, run)
            if run.secret_env and run.secret_env_file is not None:
                _write_private(run.secret_env_file, secret_env_text(run.secret_env))
        except (ContainerError, OSError) as exc:
            if isinstance(exc, OSError):  # a part-written file (or a planted symlink) goes
                _unlink(run.secret_env_file)
            raise StartError(f"cannot start container for image '{run.image}': {exc}") from exc
        try:
            handle = self._processes.start(cli, cwd=cwd, env=self.engine.env)
        except StartError:
            _unlink(run.secret_env_file)
            raise
        with self._lock:
            self._live[handle] = _Live(run.name, run.secret_env_file, threading.Event())
        return handle

    def kill(self, handle: ProcessHandle, *, force: bool = False) -> None:
        """SIGTERM (SIGKILL and removal when ``force``) to the container; never raises."""
        live = self._live.get(handle)
        if live is None:
            self._processes.kill(handle, force=force)
            return
        live.killed = True
        live.removed = live.removed or force
        self.later(self._signal_until_taken, live, force)

    def reap(self, handle: ProcessHandle) -> int:
        """The container's exit code, once the CLI has ended (the engine's 125: it failed)."""
        live = self._live.get(handle)
        if live is not None and handle.popen.poll() is None:
            # reaped before it ended (a pool shutting down): the container must go first,
            # or killing the CLI would leave it running
            live.removed = True
            self._quietly(self.engine.remove, live.name)
        code = self._processes.reap(handle)
        if live is not None and live.removed and code == _VANISHED:
            code = _KILLED  # the CLI lost the race to read its exit: the removal's SIGKILL
        if live is not None:
            live.code = code
            live.done.set()
        return code

    def release(self, handle: ProcessHandle) -> None:
        """Close the handle; delete the secret file; remove a killed or failed container."""
        self._processes.release(handle)
        with self._lock:
            live = self._live.pop(handle, None)
        if live is None:
            return
        live.done.set()
        _unlink(live.secret_file)
        if live.killed or live.code is None or live.code == 125:  # --rm may not have run
            self.later(self._quietly, self.engine.remove, live.name)

    def close(self) -> None:
        """Wait for the engine calls (kills, removals) still under way."""
        self._background.close()

    # -------------------------------------------------------------- internals

    def _signal_until_taken(self, live: _Live, force: bool) -> None:
        deadline = time.monotonic() + _KILL_DEADLINE
        while not live.done.is_set() and time.monotonic() < deadline:
            try:
                taken = (self.engine.remove(live.name) if force
                         else self.engine.kill(live.name, "TERM"))
            except ContainerError:
                taken = False
            if taken:
                return
            live.done.wait(self._retry)  # not created or not running yet

    def later(self, fn: Callable[..., object], *args: object) -> None:
        """Call ``fn(*args)`` on a thread of its own (an engine call); ``close`` waits for it."""
        self._background.later(fn, *args)

    @staticmethod
    def _quietly(fn: Callable[..., object], *args: object) -> None:
        try:
            fn(*args)
        except ContainerError:
            pass  # clean-up: what is left is found by label on the next start


def _write_private(path: Path, text: str) -> None:
    """Write ``text`` to a 0600 file at ``path``, never through a symlink."""
    flags = os.O_WRONLY | os.O_CREAT | os.O_TRUNC | os.O_NOFOLLOW | os.O_CLOEXEC
    fd = os.open(path, flags, 0o600)
    try:
        os.fchmod(fd, 0o600)  # an existing file keeps its mode on O_CREAT
        os.write(fd, text.encode())
    finally:
        os.close(fd)


def _unlink(path: Path | None) -> None:
    if path is not None:
        try:
            path.unlink()
        except FileNotFoundError:
            pass
