"""OSMO's data layout inside a task's container (pure: builds descriptions, runs nothing).

Built when the attempt's folder is prepared (``workdir.prepare(boxed=True)``); the pool's
container side (``osmo.worker.containers``) completes the run it describes.

The layout (:func:`layout`):

- ``{{output}}`` is ``/osmo/data/output``, a read-write bind of the attempt's private
  ``output.partial`` (promotion, ingest and lineage are unchanged);
- ``{{input:N}}`` and ``{{input:NAME}}`` are ``/osmo/data/input/N``, read-only binds of the
  attempt's own input copies;
- ``files:`` and credential mounts are bound read-only at their declared absolute paths (no
  path rewriting); relative ones live in the working folder, bound at ``/osmo/run/work``,
  which is then the container's working folder (else the image's own);
- the environment is the task's, then osmo's (``OSMO_OUTPUT`` etc.), never the host's;
  credential variables go through the runtime's 0600 secret file, never ``--env``.

Must not call an engine; ``osmo.runtime.container.run`` turns the description into argv.
"""

from __future__ import annotations

import posixpath
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import TYPE_CHECKING

from osmo.runtime.container.run import DATA_OUTPUT, ContainerRun, Mount, data_input
from osmo.scheduler.types import PrepareAttempt
from osmo.spec.model import TaskSpec
from osmo.worker import launch as typed

if TYPE_CHECKING:
    from osmo.layout import AttemptDirs

__all__ = ["WORKDIR", "data_path", "layout", "osmo_env"]

WORKDIR = "/osmo/run/work"
"""Where the attempt's working folder is bound when the task has relative ``files:``."""


def osmo_env(cmd: PrepareAttempt) -> dict[str, str]:
    """The variables osmo sets inside a container (the task cannot override them)."""
    return {"OSMO_WORKFLOW_ID": cmd.workflow_id, "OSMO_TASK": cmd.task,
            "OSMO_RETRY": str(cmd.retry), "OSMO_NODE": cmd.node_id,
            "OSMO_OUTPUT": DATA_OUTPUT, "OSMO_FILES_ROOT": "/"}


def data_path(token: str, task: TaskSpec, refs: Sequence[str | None]) -> str | None:
    """The container path of an ``output``/``input:N``/``input:NAME`` token (None: unknown).

    An input resolves only when the attempt has it (``refs``: each input's reference).
    """
    kind, _, arg = token.partition(":")
    if kind == "output":
        return DATA_OUTPUT
    for index, spec in enumerate(task.inputs):
        names = (str(index),) if arg.isdigit() else (typed.input_name(spec), spec.task)
        if arg in names and refs[index] is not None:
            return data_input(index)
    return None


def layout(dirs: AttemptDirs, task: TaskSpec, files: Mapping[str, Path],
           refs: Sequence[str | None], secret_env: Mapping[str, str]) -> ContainerRun:
    """The container's data layout for a prepared attempt (see the module docstring).

    Args:
        dirs: the attempt's folder.
        task: what runs (its image).
        files: each declared ``files:``/credential path → where it was written.
        refs: each input's reference (a folder on this node), None when it has none.
        secret_env: the credential variables (written to the runtime's secret file).

    The result still lacks its name, labels, user and image id (:meth:`ContainerTasks.finish`).
    """
    assert task.image is not None
    mounts = [Mount(dirs.output_partial, DATA_OUTPUT, read_only=False)]
    mounts += [Mount(Path(ref), data_input(i)) for i, ref in enumerate(refs)
               if ref is not None and ref.startswith("/")]
    relative = False
    for declared, written in files.items():
        if declared.startswith("/"):
            mounts.append(Mount(written, posixpath.normpath(declared)))
        else:
            relative = True
    if relative:
        mounts.append(Mount(dirs.work, WORKDIR, read_only=False))
    return ContainerRun(image=task.image, name="", secret_env=dict(secret_env),
                        mounts=tuple(mounts), workdir=WORKDIR if relative else None)
