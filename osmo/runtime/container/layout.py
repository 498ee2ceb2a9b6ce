"""OSMO's data layout inside a task's container (pure: builds descriptions, runs nothing).

What the task sees (:data:`DATA_LAYOUT`, the container runtime's ``Runtime.paths``), and the
binds that make it so (:func:`mounts`), as in OSMO:

- ``{{output}}`` and ``OSMO_OUTPUT`` are ``/osmo/data/output``, a read-write bind of the
  attempt's private ``output.partial`` (promotion, ingest and lineage are unchanged);
- ``{{input:N}}`` and ``{{input:NAME}}`` are ``/osmo/data/input/N``, read-only binds of the
  attempt's own input copies;
- ``files:`` and credential mounts are bound read-only at their declared absolute paths (no
  path rewriting); relative ones live in the working folder, bound at ``/osmo/run/work``,
  which is then the container's working folder (else the image's own);
- the environment is the task's, then osmo's (``OSMO_OUTPUT`` etc.), never the host's;
  credential variables go through the runtime's 0600 secret file, never ``--env``.

Must not call an engine; ``osmo.runtime.container.run`` turns a run into argv.
"""

from __future__ import annotations

import posixpath
from collections.abc import Mapping, Sequence
from pathlib import Path

from osmo.layout import AttemptDirs
from osmo.runtime.api import Paths
from osmo.runtime.container.run import DATA_INPUT, DATA_OUTPUT, Mount, data_input

__all__ = ["DATA_LAYOUT", "WORKDIR", "mounts"]

WORKDIR = "/osmo/run/work"
"""Where the attempt's working folder is bound when the task has relative ``files:``."""

DATA_LAYOUT = Paths(output=DATA_OUTPUT, input_dir=DATA_INPUT, files_root="/", bound_files=True,
                    own_env=True, hidden_secrets=True)
"""What a container task sees of its attempt (see the module docstring)."""


def mounts(dirs: AttemptDirs, files: Mapping[str, Path], inputs: Sequence[str | None]
           ) -> tuple[tuple[Mount, ...], str | None]:
    """The binds of a prepared attempt, and its working folder (None: the image's own).

    Args:
        dirs: the attempt's folder.
        files: each declared ``files:``/credential path → where it was written.
        inputs: each input's folder on this node, None when it has none.
    """
    binds = [Mount(dirs.output_partial, DATA_OUTPUT, read_only=False)]
    binds += [Mount(Path(ref), data_input(i)) for i, ref in enumerate(inputs)
              if ref is not None and ref.startswith("/")]
    relative = False
    for declared, written in files.items():
        if declared.startswith("/"):
            binds.append(Mount(written, posixpath.normpath(declared)))
        else:
            relative = True
    if relative:
        binds.append(Mount(dirs.work, WORKDIR, read_only=False))
    return tuple(binds), WORKDIR if relative else None
