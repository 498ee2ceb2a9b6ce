"""How a worker launches a typed task: the context file and the runner's argv.

A typed task runs like any command, through the worker's process runtime::

    [sys.executable, "-m", "osmo.tasktypes.runner", "<attempt>/task.json"]

``task.json`` (format 1: ``osmo.tasktypes.runner.FORMAT``) holds everything the runner needs;
paths are absolute::

    {"format": 1,
     "type": "tasks:count",            # what the spec's ``type:`` says
     "type_version": "2",              # resolved at submit (null if unknown)
     "paths": ["/home/me/project"],    # folders to import a custom type from
     "params": {"n": 3},               # as written; the runner fills defaults
     "inputs": [{"name": "make", "path": "/.../make/0/output"}],   # ``inputs:`` order
     "output": "/.../output.partial", "workdir": "/.../work",
     "workflow_id": "wf-1", "task": "count", "retry": 0, "attempt_id": "wf-1:count:0"}

An input's ``name`` is the upstream task (``WORKFLOW_ID:TASK`` for another workflow's),
the dataset (``NAME[:TAG]`` as written) or the URL. The environment gets ``PYTHONPATH``: the
``paths`` first (so processes the task starts can import the same modules), then the folders
osmo and ``osmo_plugins`` were imported from (the worker's install; a task's environment does
not inherit the worker's ``PYTHONPATH``, see ``osmo.worker.taskenv``).

File-system work only; imports no plugin. The runner that reads the file is
``osmo.tasktypes.runner``, which owns the format's version.
"""

from __future__ import annotations

import functools
import importlib.util
import json
import os
import sys
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

from osmo.spec.model import InputSpec, TaskSpec
from osmo.tasktypes.runner import FORMAT

__all__ = ["input_name", "osmo_paths", "runner_argv", "runner_env", "write_context"]


def input_name(spec: InputSpec) -> str:
    """The name an input has in ``TaskContext.input_named``."""
    if spec.task is not None:
        return f"{spec.workflow}:{spec.task}" if spec.workflow else spec.task
    return spec.dataset or spec.url or ""


def runner_argv(context_file: Path) -> tuple[str, ...]:
    """The argv that runs a typed task from its context file."""
    return (sys.executable, "-m", "osmo.tasktypes.runner", str(context_file))


def runner_env(task: TaskSpec, env: Mapping[str, str]) -> dict[str, str]:
    """Variables to add for a typed task: ``PYTHONPATH`` with the type's folders first.

    Then the spec's own ``PYTHONPATH`` (in ``env``), then osmo's install (:func:`osmo_paths`).
    """
    paths = list(task.resolved.paths) if task.resolved else []
    current = env.get("PYTHONPATH", "")
    parts = [*paths, *([current] if current else []), *osmo_paths()]
    return {"PYTHONPATH": os.pathsep.join(dict.fromkeys(parts))}


@functools.cache  # where a package was imported from does not change while we run
def osmo_paths() -> tuple[str, ...]:
    """The folders that hold the ``osmo`` and ``osmo_plugins`` packages this process uses."""
    out = [str(Path(__file__).resolve().parents[2])]  # .../osmo/worker/launch.py
    spec = importlib.util.find_spec("osmo_plugins")  # locates it without importing it
    if spec is not None and spec.submodule_search_locations:
        out.append(str(Path(next(iter(spec.submodule_search_locations))).resolve().parent))
    return tuple(dict.fromkeys(out))


def write_context(path: Path, *, task: TaskSpec, inputs: Sequence[tuple[str, str]],
                  output: Path, workdir: Path, workflow_id: str, retry: int,
                  attempt_id: str) -> None:
    """Write the context file of a typed task (atomically: temp file + rename)."""
    data: dict[str, Any] = {
        "format": FORMAT,
        "type": task.type,
        "type_version": task.resolved.version if task.resolved else None,
        "paths": list(task.resolved.paths) if task.resolved else [],
        "params": dict(task.params),
        "inputs": [{"name": name, "path": ref} for name, ref in inputs],
        "output": str(output),
        "workdir": str(workdir),
        "workflow_id": workflow_id,
        "task": task.name,
        "retry": retry,
        "attempt_id": attempt_id,
    }
    temp = path.with_name(path.name + ".tmp")
    temp.write_text(json.dumps(data, indent=1, default=str), encoding="utf-8")
    os.replace(temp, path)
