"""The :class:`~osmo.tasktypes.api.TaskContext` a typed task gets when it runs.

:class:`RunContext` is built by the runner (``osmo.tasktypes.runner``) inside the task's own
process, and by ``osmo.testing.check_task_type`` in a temporary folder:

- ``log`` writes to stdout (INFO and below) and stderr (WARNING and above), which the
  worker captures into the task's log (``osmo logs``);
- ``progress(done, total, message)`` writes one line ``[osmo:progress] 3/10 message``
  (``[osmo:progress] 3 message`` without a total) to stdout;
- ``cancelled()`` turns true once the process got SIGTERM (cancel, timeout): the runner
  installs the handler; the worker sends SIGKILL after its grace period anyway;
- ``mcap_writer(path)`` opens an ``osmo.record.LineageMcapWriter`` under ``output`` that
  stamps this attempt's lineage (``Lineage.from_env()`` plus the attempt id, the
  ``type@version`` and the params) into the file.
"""

from __future__ import annotations

import logging
import os
import sys
import threading
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

from osmo.tasktypes.api import PROGRESS_PREFIX, TaskCancelled

__all__ = ["PROGRESS_PREFIX", "RunContext", "task_logger"]


class _Below(logging.Filter):
    def __init__(self, level: int) -> None:
        super().__init__()
        self.level = level

    def filter(self, record: logging.LogRecord) -> bool:
        return record.levelno < self.level


class _Std(logging.Handler):
    """Writes to ``sys.stdout``/``sys.stderr`` as they are when a record comes.

    Not as they were when the logger was made: test runners swap them.
    """

    def __init__(self, which: str) -> None:
        super().__init__()
        self.which = which

    def emit(self, record: logging.LogRecord) -> None:
        try:
            stream = getattr(sys, self.which)
            stream.write(self.format(record) + "\n")
            stream.flush()
        except Exception:  # noqa: BLE001 - logging must never fail the task
            self.handleError(record)


def task_logger(task: str) -> logging.Logger:
    """A logger for task ``task`` writing plain lines to stdout and warnings to stderr."""
    logger = logging.getLogger(f"osmo.task.{task}")
    if not logger.handlers:
        out = _Std("stdout")
        out.addFilter(_Below(logging.WARNING))
        out.setFormatter(logging.Formatter("%(message)s"))
        err = _Std("stderr")
        err.setLevel(logging.WARNING)
        err.setFormatter(logging.Formatter("%(levelname)s: %(message)s"))
        logger.addHandler(out)
        logger.addHandler(err)
        logger.setLevel(logging.INFO)
        logger.propagate = False
    return logger


@dataclass
class RunContext:
    """A running typed task's context (implements ``TaskContext``; see the module docstring).

    Attributes:
        plugin: ``type@version`` as lineage records it.
        env: the environment lineage is read from (default: this process's).
    """

    params: Mapping[str, Any]
    inputs: Sequence[Path]
    input_named: Mapping[str, Path]
    output: Path
    workdir: Path
    workflow_id: str
    task: str
    attempt_id: str
    retry: int = 0
    plugin: str | None = None
    env: Mapping[str, str] | None = None
    log: logging.Logger = field(init=False)
    _cancel: threading.Event = field(default_factory=threading.Event, init=False, repr=False)

    def __post_init__(self) -> None:
        self.log = task_logger(self.task)

    def progress(self, done: float, total: float | None = None, message: str = "") -> None:
        """Write a ``[osmo:progress] done/total message`` line to the task's log."""
        amount = f"{done:g}" if total is None else f"{done:g}/{total:g}"
        line = f"{PROGRESS_PREFIX} {amount}" + (f" {message}" if message else "")
        sys.stdout.write(line + "\n")
        sys.stdout.flush()

    def cancel(self) -> None:
        """Mark the attempt as asked to stop (the runner's SIGTERM handler calls this)."""
        self._cancel.set()

    def cancelled(self) -> bool:
        """True once the attempt was asked to stop."""
        return self._cancel.is_set()

    def check_cancelled(self) -> None:
        """Raise :class:`TaskCancelled` if the attempt was asked to stop."""
        if self._cancel.is_set():
            raise TaskCancelled(f"task '{self.task}' was asked to stop")

    def mcap_writer(self, path: str | Path, *, metadata: Mapping[str, str] | None = None) -> Any:
        """Open a ``LineageMcapWriter`` at ``path`` (relative: under ``output``).

        ``metadata`` is written as an MCAP metadata record named ``osmo.task``.
        """
        from osmo.record import Lineage, LineageMcapWriter

        target = Path(path)
        target = target if target.is_absolute() else self.output / target
        target.parent.mkdir(parents=True, exist_ok=True)
        own = {"OSMO_WORKFLOW_ID": self.workflow_id, "OSMO_TASK": self.task,
               "OSMO_RETRY": str(self.retry)}
        lineage = Lineage.from_env({**own, **(os.environ if self.env is None else self.env)})
        lineage = replace(lineage, attempt_id=lineage.attempt_id or self.attempt_id,
                          plugin=lineage.plugin or self.plugin, params=dict(self.params))
        writer = LineageMcapWriter(target, lineage)
        if metadata:
            writer.add_metadata("osmo.task", dict(metadata))
        return writer
