"""The process runtime: an attempt's command runs as host processes, with no sandbox.

A node runs its tasks so when no sandbox works there or none is wanted (``--sandbox off``;
``osmo.runtime.choose``): the command then sees the host as the worker's user. What it owns:

- the launch: the pool's as made, with the host's paths (``HOST_PATHS``); ``prepare`` only
  adds the osmo log lines that say how the task runs (no sandbox, and why; an ``image:`` it
  does not use).
- start, kill, reap, release: one process group per command, dying with its worker
  (:class:`~osmo.runtime.process.groups.ProcessGroups`); a typed task's, with ``warm``
  runners, forked from a runner that imported its type
  (:class:`~osmo.runtime.process.warm.WarmRunners`), unless the task says ``warm: false``.
- exec: the command in the attempt's working folder with its environment.
- port-forward: only to a port a process of the task listens on, at the address it listens
  on (``osmo.runtime.process.ports``), never to another process's port on the node.
- clean-up: nothing of its own (the pool deletes what preparing wrote).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import replace
from pathlib import Path

from osmo.runtime.api import (
    HOST_PATHS,
    Attempt,
    Connector,
    ExecCommand,
    Launch,
    Paths,
    ProcessHandle,
    Runtime,
)
from osmo.runtime.process.groups import ProcessGroups
from osmo.runtime.process.ports import listener_connector
from osmo.runtime.process.sandbox import Sandbox
from osmo.runtime.process.warm import (
    WarmHandle,
    WarmKey,
    WarmRunners,
    WarmStart,
    commands_key,
    warm_key,
)
from osmo.scheduler.types import PrepareAttempt
from osmo.spec.model import TaskSpec

__all__ = ["ProcessRuntime", "image_note", "term_env"]


def image_note(task: TaskSpec) -> str | None:
    """The osmo log line of a process task's ``image:``, which it does not run in."""
    if task.image is None:
        return None
    return f"image '{task.image}' recorded; the process runtime runs commands on the host"


def term_env(tty: bool, term: str | None) -> dict[str, str]:
    """``TERM`` for an exec session: the client's, with a TTY."""
    return {"TERM": term} if tty and term is not None else {}


class ProcessRuntime:
    """Host processes with no sandbox (see the module docstring).

    Args:
        note: a line for each attempt's log (that it runs unsandboxed, and why).
        why: why there is no sandbox, in a few words (``osmo resource list``).
        warning: what the node says once at start (``auto`` found no sandbox: nobody chose
            to run tasks unsandboxed); None when the operator chose it.
        groups: what spawns its commands (default: unsandboxed process groups).
        warm: the node's warm runners: typed tasks start as forks of them (None: cold).
        warm_commands: every command starts from a warm runner (a fork, then its exec),
            not only typed tasks: what the runtime contract checks of the warm path.

    Attributes:
        sandbox: the bubblewrap its commands run in: None here (``SandboxRuntime``'s).
    """

    def __init__(self, *, note: str | None = None, why: str | None = None,
                 warning: str | None = None, groups: ProcessGroups | None = None,
                 warm: WarmRunners | None = None, warm_commands: bool = False) -> None:
        self.note, self.why, self.warning = note, why, warning
        self.sandbox: Sandbox | None = None
        self._groups = groups or ProcessGroups()
        self.warm, self._warm_commands = warm, warm_commands

    def describe(self) -> str:
        """``process``."""
        return "process"

    def hide(self, path: Path) -> None:
        """Nothing to hide: an unsandboxed task sees the host (``path`` included)."""

    def paths(self, cmd: PrepareAttempt) -> Paths:
        """The host's own paths."""
        return HOST_PATHS

    def prepare(self, launch: Launch, attempt: Attempt, *,
                progress: Callable[[str], None]) -> Launch:
        """``launch`` with the log lines that say how it runs; warm when it can be.

        A typed task's first attempt of its kind waits here for its runner's import.
        """
        notes = tuple(n for n in (self.note, image_note(attempt.task)) if n)
        key = self._warm_key(launch, attempt)
        if key is not None and self.warm is not None and self.warm.ready(key):
            warm = f"warm start: forked from a runner of {key.type or 'commands'}"
            return replace(launch, run=WarmStart(key), notes=(*launch.notes, *notes, warm))
        return replace(launch, notes=(*launch.notes, *notes)) if notes else launch

    def _warm_key(self, launch: Launch, attempt: Attempt) -> WarmKey | None:
        """What runner ``launch`` starts from (None: it starts cold)."""
        task = attempt.task
        if self.warm is None or task.warm is False:
            return None
        if task.type is not None:
            resolved = task.resolved
            return warm_key(launch, task.type, resolved.version if resolved else None,
                            resolved.paths if resolved else ())
        if self._warm_commands:
            return commands_key()
        return None

    def start(self, launch: Launch) -> ProcessHandle:
        """Spawn the command in its own process group, or fork it warm. Raises StartError."""
        if isinstance(launch.run, WarmStart) and self.warm is not None:
            return self.warm.start(launch.run.key, launch)
        return self._groups.start(launch.argv, cwd=launch.cwd, env=launch.env)

    def kill(self, handle: ProcessHandle, *, force: bool = False) -> None:
        """SIGTERM (SIGKILL when ``force``) to its process group.

        In a sandbox, SIGTERM goes to every process in it but bwrap's (``ProcessGroups``).
        """
        if isinstance(handle, WarmHandle) and self.warm is not None:
            self.warm.kill(handle, force=force)
            return
        self._groups.kill(handle, force=force)

    def reap(self, handle: ProcessHandle) -> int:
        """Its exit code; what is left of its group is killed.

        ``handle.setup_failed``: a sandbox's command never ran; ``handle.lost``: its warm
        runner died under it.
        """
        if isinstance(handle, WarmHandle) and self.warm is not None:
            return self.warm.reap(handle)
        return self._groups.reap(handle)

    def release(self, handle: ProcessHandle) -> None:
        """Close its descriptors."""
        if isinstance(handle, WarmHandle) and self.warm is not None:
            self.warm.release(handle)
            return
        self._groups.release(handle)

    def exec(self, launch: Launch, command: Sequence[str], *, tty: bool,
             term: str | None) -> ExecCommand:
        """``command`` in the attempt's working folder, with its environment."""
        return ExecCommand(list(command), launch.cwd, {**launch.env, **term_env(tty, term)})

    def connector(self, launch: Launch, handle: ProcessHandle) -> Connector:
        """To the ports a process of the task listens on, from the node."""
        return listener_connector(handle.pid)

    def cleanup(self, launch: Launch) -> None:
        """Nothing of its own to remove."""

    def close(self) -> None:
        """Its warm runners end (and what still runs of them)."""
        if self.warm is not None:
            self.warm.close()


def _conforms(runtime: ProcessRuntime) -> Runtime:
    """Never called: mypy checks here that ProcessRuntime keeps the runtime contract."""
    return runtime
