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

A typed task that runs in its image (its runtime's ``Paths.runner``) runs the image's
``python3`` on the same file, its paths being those the image shows (the type's folders
and osmo's packages bound read-only), and an installed type also named by its entry point
(``"entry": "module:attr"``); ``"image"`` names the image.

File-system work only; imports no plugin. The runner that reads the file is
``osmo.tasktypes.runner``, which owns the format's version.
"""

from __future__ import annotations

import json
import os
import sys
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

from osmo.runtime.api import RunnerPaths
from osmo.spec.model import InputSpec, TaskSpec
from osmo.tasktypes.registry import entry_target, shipped_packages
from osmo.tasktypes.runner import FORMAT

__all__ = ["input_name", "osmo_paths", "runner_argv", "runner_env", "write_context"]


def input_name(spec: InputSpec) -> str:
    """The name an input has in ``TaskContext.input_named``."""
    if spec.task is not None:
        return f"{spec.workflow}:{spec.task}" if spec.workflow else spec.task
    return spec.dataset or spec.url or ""


def runner_argv(context_file: Path, shown: RunnerPaths | None = None) -> tuple[str, ...]:
    """The argv that runs a typed task from its context file (``shown``: in its image)."""
    if shown is not None:
        return (shown.python, "-m", "osmo.tasktypes.runner", shown.context)
    return (sys.executable, "-m", "osmo.tasktypes.runner", str(context_file))


def runner_env(task: TaskSpec, env: Mapping[str, str],
               shown: RunnerPaths | None = None) -> dict[str, str]:
    """Variables to add for a typed task: ``PYTHONPATH`` with the type's folders first.

    Then the spec's own ``PYTHONPATH`` (in ``env``), then osmo's install (:func:`osmo_paths`);
    with ``shown`` (the task runs in its image), where the image shows them.
    """
    paths = list(task.resolved.paths) if task.resolved else []
    code = osmo_paths()
    if shown is not None:
        paths = [shown.types.format(index) for index in range(len(paths))]
        code = (shown.code,)
    current = env.get("PYTHONPATH", "")
    parts = [*paths, *([current] if current else []), *code]
    return {"PYTHONPATH": os.pathsep.join(dict.fromkeys(parts))}


def osmo_paths() -> tuple[str, ...]:
    """The folders that hold the ``osmo`` and ``osmo_plugins`` packages this process uses."""
    return tuple(dict.fromkeys(str(folder.parent) for folder in shipped_packages().values()))


def write_context(path: Path, *, task: TaskSpec, inputs: Sequence[tuple[str, str]],
                  output: Path | str, workdir: Path | str, workflow_id: str, retry: int,
                  attempt_id: str, shown: RunnerPaths | None = None) -> None:
    """Write the context file of a typed task (atomically: temp file + rename).

    With ``shown`` (the task runs in its image), its paths are the image's view and an
    installed type is also named by its entry point (``entry``: the image has osmo's code,
    not the install's metadata that names it).
    """
    paths = list(task.resolved.paths) if task.resolved else []
    data: dict[str, Any] = {
        "format": FORMAT,
        "type": task.type,
        "type_version": task.resolved.version if task.resolved else None,
        "paths": paths if shown is None else [shown.types.format(i) for i in range(len(paths))],
        "params": dict(task.params),
        "inputs": [{"name": name, "path": ref} for name, ref in inputs],
        "output": str(output),
        "workdir": str(workdir),
        "workflow_id": workflow_id,
        "task": task.name,
        "retry": retry,
        "attempt_id": attempt_id,
    }
    if shown is not None:
        data["image"] = task.image
    entry = entry_target(task.type) if shown is not None and task.type else None
    if entry is not None:
        data["entry"] = entry
    temp = path.with_name(path.name + ".tmp")
    temp.write_text(json.dumps(data, indent=1, default=str), encoding="utf-8")
    os.replace(temp, path)
