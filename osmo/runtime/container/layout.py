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
  credential variables go through the runtime's 0600 secret file, never ``--env``;
- a typed task (``type:``) runs the image's ``python3`` on osmo's runner
  (:data:`RUNNER_PATHS`): its context file is bound read-only at ``/osmo/run/task.json``,
  its working folder at ``/osmo/run/work``, osmo's own packages (``osmo``,
  ``osmo_plugins``) read-only under ``/osmo/lib`` and a custom type's folders read-only at
  ``/osmo/types/N`` (:func:`runner_mounts`). The image brings Python and the type's
  libraries; nothing else of the host's install is shown. A type's folder is the client's
  word (the workflow file's folder): what of osmo it holds (its home, a token file) is
  covered, an empty read-only folder or ``/dev/null`` bound over it, and a type folder inside
  one of osmo's homes is refused, as the sandbox does for process tasks.

Must not call an engine; ``osmo.runtime.container.run`` turns a run into argv.
"""

from __future__ import annotations

import os
import posixpath
from collections.abc import Mapping, Sequence
from pathlib import Path

from osmo.layout import AttemptDirs
from osmo.runtime.api import Paths, RunnerPaths
from osmo.runtime.container.run import DATA_INPUT, DATA_OUTPUT, Mount, data_input

__all__ = ["DATA_LAYOUT", "RUNNER_PATHS", "WORKDIR", "CoverError", "code_mounts", "mounts",
           "runner_mounts"]

WORKDIR = "/osmo/run/work"
"""Where the attempt's working folder is bound (relative ``files:``, a typed task)."""

RUNNER_PATHS = RunnerPaths(python="python3", context="/osmo/run/task.json", workdir=WORKDIR,
                           code="/osmo/lib", types="/osmo/types/{}")
"""Where a typed task's runner finds itself in its image (see the module docstring)."""

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


class CoverError(ValueError):
    """A type folder that cannot be shown: it lies in what no task may see."""


def runner_mounts(dirs: AttemptDirs, packages: Mapping[str, Path], type_paths: Sequence[str],
                  hidden: Sequence[Path] = (), empty: Path | None = None) -> tuple[Mount, ...]:
    """The binds a typed task's runner needs in its image (:data:`RUNNER_PATHS`).

    Its context file and working folder, then :func:`code_mounts`.

    Args:
        dirs: the attempt's folder (its context file and working folder).
        packages: as :func:`code_mounts`.
        type_paths: as :func:`code_mounts`.
        hidden: as :func:`code_mounts`.
        empty: as :func:`code_mounts`.

    Raises:
        CoverError: a type folder is, or lies inside, a hidden path.
    """
    shown = RUNNER_PATHS
    return (Mount(dirs.context, shown.context), Mount(dirs.work, shown.workdir, read_only=False),
            *code_mounts(packages, type_paths, hidden, empty))


def code_mounts(packages: Mapping[str, Path], type_paths: Sequence[str],
                hidden: Sequence[Path] = (), empty: Path | None = None) -> tuple[Mount, ...]:
    """The binds of osmo's own packages and a custom type's folders, read-only.

    Args:
        packages: osmo's own packages by name (``osmo.tasktypes.registry.shipped_packages``).
        type_paths: the folders a custom type is imported from (the client's word).
        hidden: what no task may see (osmo's homes, token files): covered where a type
            folder holds it.
        empty: an empty folder, bound read-only over a hidden folder (needed when one is
            covered).

    Raises:
        CoverError: a type folder is, or lies inside, a hidden path.
    """
    shown = RUNNER_PATHS
    binds = [Mount(folder, posixpath.join(shown.code, name)) for name, folder in packages.items()]
    secret = [Path(os.path.realpath(path)) for path in hidden]
    for index, folder in enumerate(type_paths):
        real, target = Path(os.path.realpath(folder)), shown.types.format(index)
        if any(real.is_relative_to(path) for path in secret):
            raise CoverError(f"its task type's folder {folder} is inside osmo's own files, "
                             "which no task may see")
        binds.append(Mount(real, target))
        for path in secret:
            if path.is_relative_to(real) and os.path.lexists(path):
                source = Path(os.devnull) if not path.is_dir() else empty
                if source is None:
                    raise CoverError(f"no empty folder to cover {path} with")
                binds.append(Mount(source, posixpath.join(target, str(path.relative_to(real)))))
    return tuple(binds)
