"""Runs one typed task inside its own process: ``python -m osmo.tasktypes.runner task.json``.

The worker starts this like any command (same process runtime, logs, kill and exit codes);
the context file's format is in ``osmo.worker.launch``, which writes it. The runner puts the type's
folders on ``sys.path``, resolves the type, checks it is still the version the workflow was
submitted against, fills in parameter defaults, builds a
:class:`~osmo.tasktypes.context.RunContext` and calls ``run(ctx)``.

With ``OSMO_TASK_TIMING=1`` in the task's environment, the runner first imports what the type
declares every run needs (its ``warm()``, as a warm runner does before the attempt), then
reads ``time.perf_counter`` around ``run(ctx)`` and prints one line :data:`TIMING_MARK`
``SECONDS`` to stdout (the task's log): the task's own compute, imports excluded, so a
benchmark can tell it from osmo's overhead under a cold start and a warm one alike.

Exit codes: 0 when ``run`` returns; 1 when it raises (the traceback goes to the task's log)
or the type cannot be loaded or has changed version since submit; 143 (as if killed by
SIGTERM) when it raises ``TaskCancelled`` or returns after being asked to stop. SIGTERM only
sets the cancelled flag: the task decides how to finish, and the worker sends SIGKILL after
its grace period.
"""

from __future__ import annotations

import json
import os
import signal
import sys
import time
import traceback
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from osmo.tasktypes.api import TaskCancelled

__all__ = ["CANCELLED", "FORMAT", "TIMING", "TIMING_MARK", "keep_resolved", "main",
           "run_context_file"]

CANCELLED = 128 + signal.SIGTERM
"""The exit code of a task that stopped because it was asked to."""

FORMAT = 1
"""The version of the context file this runner reads (written by ``osmo.worker.launch``)."""


TIMING = "OSMO_TASK_TIMING"
"""The task environment variable that turns the compute line on (``1``)."""

TIMING_MARK = "osmo: compute "
"""The start of the line a timed run prints; the seconds follow."""

_resolved: dict[tuple[str, tuple[str, ...]], Any] = {}


def keep_resolved(ref: str, obj: Any) -> None:
    """``ref`` resolves to ``obj`` on the current ``sys.path``: a warm runner's, for its forks.

    A fork's run then takes ``obj`` rather than resolving ``ref`` again (which reads every
    installed distribution's entry points: a quarter of a short task's time) when its
    ``sys.path``, once the context's folders are on it, is the one ``ref`` was resolved on.
    The type's module was imported by the runner either way: ``resolve`` would load it from
    ``sys.modules``.
    """
    _resolved[(ref, tuple(sys.path))] = obj


def _fail(message: str) -> int:
    sys.stderr.write(f"osmo: {message}\n")
    sys.stderr.flush()
    return 1


def _context(data: dict[str, Any], params: dict[str, Any], plugin: str) -> Any:
    from osmo.tasktypes.context import RunContext

    inputs = [(i.get("name") or "", Path(i["path"])) for i in data.get("inputs", [])]
    named: dict[str, Path] = {}
    for name, path in inputs:
        if name:
            named.setdefault(name, path)
            named.setdefault(name.split(":", 1)[0], path)  # dataset NAME:TAG → NAME too
    return RunContext(params=params, inputs=[p for _, p in inputs], input_named=named,
                      output=Path(data["output"]), workdir=Path(data["workdir"]),
                      workflow_id=str(data["workflow_id"]), task=str(data["task"]),
                      attempt_id=str(data["attempt_id"]), retry=int(data.get("retry", 0)),
                      plugin=plugin)


def run_context_file(path: Path) -> int:
    """Run the typed task described by the context file at ``path``; return the exit code."""
    from osmo.errors import OsmoError
    from osmo.params import fill_defaults
    from osmo.tasktypes.registry import resolve

    try:
        data = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, ValueError) as exc:
        return _fail(f"cannot read the task's context file {path}: {exc}")
    if data.get("format") != FORMAT:
        return _fail(f"context file {path} has format {data.get('format')!r}; this osmo "
                     f"reads format {FORMAT} (worker and runner differ in version?)")
    for folder in reversed(data.get("paths") or []):
        if folder not in sys.path:
            sys.path.insert(0, folder)
    ref = str(data["type"])
    try:
        target = str(data.get("entry") or ref)  # in an image: an installed type's entry point
        obj = _resolved.get((target, tuple(sys.path)))
        if obj is None:
            obj = resolve(target)
    except OsmoError as exc:
        return _fail(str(exc))
    expected = data.get("type_version")
    if expected is not None and str(obj.version) != str(expected):
        return _fail(f"task type '{ref}' is version {obj.version} here, but the workflow was "
                     f"submitted against version {expected}; install that version where the "
                     "task runs, or submit the workflow again")
    ctx = _context(data, fill_defaults(obj.params, data.get("params") or {}),
                   f"{ref}@{obj.version}")
    signal.signal(signal.SIGTERM, lambda *_: ctx.cancel())
    timing = os.environ.get(TIMING) == "1"
    try:
        if timing and callable(warm := getattr(obj, "warm", None)):
            warm()
        start = time.perf_counter()
        obj.run(ctx)
        if timing:
            print(f"{TIMING_MARK}{time.perf_counter() - start:.6f}", flush=True)
    except TaskCancelled as exc:
        ctx.log.warning("stopped: %s", exc)
        return CANCELLED
    except ModuleNotFoundError as exc:  # what the task's environment lacks: say where
        traceback.print_exc()
        where = f"its image {data['image']!r}" if data.get("image") else "this node's Python"
        return _fail(f"task type '{ref}' needs the module '{exc.name}', which {where} does "
                     "not have; install it there")
    except Exception:  # the task's own failure: its traceback is the log's last word
        traceback.print_exc()
        return 1
    return CANCELLED if ctx.cancelled() else 0


def main(argv: Sequence[str] | None = None) -> int:
    """``python -m osmo.tasktypes.runner CONTEXT_FILE``."""
    args = list(sys.argv[1:] if argv is None else argv)
    if len(args) != 1:
        return _fail("usage: python -m osmo.tasktypes.runner CONTEXT_FILE")
    try:
        return run_context_file(Path(args[0]))
    finally:
        sys.stdout.flush()
        sys.stderr.flush()


if __name__ == "__main__":
    sys.exit(main())
