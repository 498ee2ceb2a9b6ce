"""The task-type contract: what a plugin implements and what it is given when it runs.

A task type is any object with the attributes of :class:`TaskType` (a class instance, or a
function wrapped by :func:`task_type`). osmo finds it through the ``osmo.task_types``
entry-point group (``"sim.rollout" = "osmo_plugins.sim.rollout:ROLLOUT"``) or, for a
user's own module, through a ``"module:attr"`` string written as the task's ``type:``.
Nothing here is resolved at ``import osmo``; a type is loaded when a spec names it.

A task of type ``T`` runs as a subprocess of the worker (the same process runtime as any
command): osmo builds the :class:`TaskContext` in that process and calls ``T.run(ctx)``.
Returning normally is success (exit 0); raising fails the attempt (exit 1, the traceback in
the task's log); :class:`TaskCancelled` (raised by :meth:`TaskContext.check_cancelled`)
ends it as killed.

This module is pure declarations: it must not import simulators, learners or zenoh.
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Protocol, runtime_checkable

from osmo.errors import OsmoError
from osmo.params import REQUIRED, Param

__all__ = [
    "PROGRESS_PREFIX",
    "REQUIRED",
    "Param",
    "TaskCancelled",
    "TaskContext",
    "TaskType",
    "task_type",
]


PROGRESS_PREFIX = "[osmo:progress]"
"""How a progress line starts in a task's log (``osmo query`` shows the latest one)."""


class TaskCancelled(OsmoError):
    """The attempt was asked to stop (cancel, timeout); raised by ``check_cancelled``."""


@runtime_checkable
class TaskContext(Protocol):
    """What a running task is given.

    Attributes:
        params: the task's parameters, validated, defaults filled in.
        inputs: input folders in the order of the task's ``inputs:`` list.
        input_named: upstream task name (or dataset name) → its folder.
        output: the folder to write outputs into (promoted atomically after success).
        workdir: a private scratch folder.
        log: a logger whose records go to the task's log (``osmo logs``).
        workflow_id, task, attempt_id: who is running.
    """

    params: Mapping[str, Any]
    inputs: Sequence[Path]
    input_named: Mapping[str, Path]
    output: Path
    workdir: Path
    log: logging.Logger
    workflow_id: str
    task: str
    attempt_id: str

    def progress(self, done: float, total: float | None = None, message: str = "") -> None:
        """Report progress: a ``[osmo:progress] done/total message`` line in the task's log.

        ``osmo query`` shows the latest while the task runs.
        """

    def cancelled(self) -> bool:
        """True once the attempt was asked to stop (SIGTERM); finish up quickly."""

    def check_cancelled(self) -> None:
        """Raise :class:`TaskCancelled` if the attempt was asked to stop."""

    def mcap_writer(self, path: str | Path, *, metadata: Mapping[str, str] | None = None) -> Any:
        """Open an ``osmo.record.LineageMcapWriter`` at ``path``.

        A relative ``path`` is under ``output``; the writer stamps this attempt's lineage into the
        file.
        """


@runtime_checkable
class TaskType(Protocol):
    """A task type: declared attributes plus ``run``.

    Attributes:
        name: the name a spec uses (``type: sim.rollout``).
        version: the type's version (part of the cache fingerprint and of lineage).
        params: parameter name → :class:`Param`.
        resources: default resources, spec keys (``{"cpu": 2, "memory": "2Gi"}``); the
            spec's ``resource:`` wins.
        extra: the pip extra that provides its dependencies (``"sim"``), or None.
        description: one line for ``osmo plugins list``.

    A type may also have a ``report`` attribute: what ``osmo eval report`` shows of its
    outputs (``osmo.tasktypes.reports.Report``); not part of the required shape. And a
    ``warm()`` method: a warm runner (``osmo.runtime.process.warm``) calls it once, after
    importing the type, to import what every run needs (a type that imports its libraries
    inside ``run``); it must not start a thread or read the task's environment.
    """

    name: str
    version: str
    params: Mapping[str, Param]
    resources: Mapping[str, Any]
    extra: str | None
    description: str

    def run(self, ctx: TaskContext) -> None:
        """Do the work; return for success, raise for failure."""


@dataclass
class _FunctionTaskType:
    """A :class:`TaskType` made from a function by :func:`task_type`."""

    fn: Callable[[TaskContext], None]
    name: str
    version: str
    params: Mapping[str, Param] = field(default_factory=dict)
    resources: Mapping[str, Any] = field(default_factory=dict)
    extra: str | None = None
    description: str = ""

    def run(self, ctx: TaskContext) -> None:
        """Call the wrapped function."""
        self.fn(ctx)

    def __call__(self, ctx: TaskContext) -> None:
        self.fn(ctx)


def task_type(
    name: str | None = None,
    *,
    version: str = "0",
    params: Mapping[str, Param] | None = None,
    resources: Mapping[str, Any] | None = None,
    extra: str | None = None,
    description: str | None = None,
) -> Callable[[Callable[[TaskContext], None]], _FunctionTaskType]:
    """Make a task type from a function ``fn(ctx)``.

    Example::

        @osmo.task_type(version="1", params={"n": Param(int, default=3)})
        def count(ctx):
            (ctx.output / "n.txt").write_text(str(ctx.params["n"]))

    Args:
        name: defaults to the function's ``module:name``.
        version: the type's version (see :class:`TaskType`).
        params: parameter name → :class:`Param`.
        resources: default resources, spec keys.
        extra: the pip extra that provides its dependencies.
        description: one line for ``osmo plugins list`` (default: the docstring's first
            line).
    """

    def wrap(fn: Callable[[TaskContext], None]) -> _FunctionTaskType:
        doc = (fn.__doc__ or "").strip().splitlines()
        return _FunctionTaskType(
            fn=fn, name=name or f"{fn.__module__}:{fn.__qualname__}", version=version,
            params=dict(params or {}), resources=dict(resources or {}), extra=extra,
            description=description if description is not None else (doc[0] if doc else ""))

    return wrap
