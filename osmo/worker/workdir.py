"""An attempt's private folder: its preparation and output promotion.

The folder's layout (``work/``, ``inputs/``, ``files/``, ``output.partial/``, ``output/``,
``log.txt``, ``task.json``) is :class:`osmo.layout.AttemptDirs`; this module makes and
fills it.

File mapping — how two parallel tasks that both declare ``/tmp/run.sh`` never see each
other's file, without containers:

- a declared absolute path ``/a/b`` is written to ``files/a/b``; a relative path ``p`` to
  ``work/p`` (a relative path may not leave ``work/``);
- every occurrence of a declared absolute path in the command, the args, the environment
  values and the contents of the declared (text) files is rewritten to its private location.
  An occurrence counts only as a whole path: not preceded by a word character, ``.``, ``-``
  or ``/``, and not followed by a word character, ``.`` or ``-`` (so ``/tmp/run`` does not
  rewrite ``/tmp/run.sh`` nor ``/x/tmp/run``). Paths built at run time (``$DIR/run.sh``)
  are not rewritten: use ``$OSMO_FILES_ROOT``;
- ``files[].path`` is taken literally (tokens are not substituted in it);
- base64 files are decoded and written as they are (no rewriting, no tokens); a file whose
  content starts with ``#!`` is made executable (0o755), any other is 0o644.
- a credential mounted at a path (``credentials: {NAME: /path}``, ``osmo.worker.secrets``)
  is mapped and rewritten the same way; each of its keys is written as a file in that
  folder, mode 0o600, verbatim. ``remove_secret_files`` deletes them when the attempt ends.

Tokens (``osmo.spec.tokens``), substituted after the rewriting, in command, args, environment
values and text file contents: ``{{output}}`` → ``output.partial``; ``{{input:N}}`` → the
output reference of the N-th ``inputs:`` entry; ``{{input:NAME}}`` → upstream task NAME's
output reference; ``{{workflow_id}}``; ``{{host:NAME}}`` → the address of group member NAME;
``{{uuid}}`` → one random uuid4 hex per attempt. An unknown token fails the preparation.

``args`` (not ``command``) then expand Kubernetes-style ``$(NAME)`` references from the
variables the task defines (its ``environment``, its credentials' variables and osmo's own;
not the base environment): ``$$`` is an escaped ``$``, an undefined ``$(NAME)`` stays as
written (``osmo.spec.tokens.expand_vars``). In a container (``boxed``) credentials'
variables are not expanded: args show in ``podman inspect``; the shell's ``$NAME`` has them.

Environment: a small base taken from the worker's (``osmo.worker.taskenv``: ``PATH``,
``HOME``, locale; never the whole environment, never ``OSMO_HOME``), then the task's
``environment`` (tokens substituted), then the variables its credentials set (``NAME: {ENV:
key}``, verbatim), then osmo's own variables, which a task cannot override:
``OSMO_WORKFLOW_ID``, ``OSMO_TASK``, ``OSMO_RETRY``, ``OSMO_NODE``, ``OSMO_OUTPUT``,
``OSMO_FILES_ROOT``.

Sandbox view (:func:`attempt_view`): what of osmo's home a sandboxed attempt sees: its own
folder read-only, its ``work/``, ``output.partial/`` and ``files/`` writable, its inputs
read-only; the rest of the home is hidden (``osmo.runtime.process.sandbox``). A root pool's
sandboxed task is ``nobody`` on the host: :func:`hand_over` gives it its writable folders.

Promotion: after a COMPLETE exit of an attempt that was not killed, ``output.partial`` is
renamed to ``output`` (atomic) and the attempt folder is fsynced; the output reference is the
absolute path of ``output``. A failed or killed attempt's ``output.partial`` stays where
nobody references it.

Typed tasks (``type:``) run ``python -m osmo.tasktypes.runner <attempt>/task.json``; the
context file is written here (see ``osmo.worker.launch`` for its format).

This module does file-system work only; it spawns nothing and reports nothing.
"""

from __future__ import annotations

import base64
import binascii
import os
import posixpath
import re
import stat
import uuid
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from pathlib import Path

from osmo.artifacts.fsops import remove_tree
from osmo.errors import OsmoError
from osmo.layout import AttemptDirs
from osmo.runtime.container.run import ContainerRun
from osmo.runtime.process.sandbox import View
from osmo.scheduler.types import PrepareAttempt
from osmo.spec.model import InputSpec, TaskSpec
from osmo.spec.tokens import expand_vars, substitute
from osmo.worker import container_layout as containers
from osmo.worker import launch
from osmo.worker.secrets import Secrets, mounts, secret_env, secret_values

__all__ = ["Launch", "PrepareError", "attempt_view", "hand_over", "prepare", "promote",
           "remove_secret_files"]


class PrepareError(OsmoError):
    """An attempt's folder, files or tokens could not be prepared (message says which)."""


@dataclass(frozen=True)
class Launch:
    """What to run for a prepared attempt: argv, working folder and complete environment.

    ``secrets`` are the values of the task's credentials (for masking its logs) and
    ``secret_files`` the files its credential mounts wrote; neither is shown by ``repr``.
    ``view`` is what a sandbox lets it see (None: it runs unsandboxed).
    """

    argv: tuple[str, ...]
    cwd: Path
    env: dict[str, str] = field(repr=False)
    secrets: tuple[str, ...] = field(default=(), repr=False)
    secret_files: tuple[Path, ...] = ()
    scratch: tuple[Path, ...] = ()  # deleted when the attempt ends (large input copies)
    max_output_bytes: int | None = None  # the task's ``storage``: its output may hold no more
    view: View | None = None
    container: ContainerRun | None = None  # run in this container (``osmo.worker.containers``)
    notes: tuple[str, ...] = ()  # osmo lines for its log, from before the log existed (a pull)


def prepare(
    dirs: AttemptDirs, cmd: PrepareAttempt, task: TaskSpec, base_env: Mapping[str, str],
    secrets: Secrets | None = None, *, boxed: bool = False,
) -> Launch:
    """Create the attempt's folder, write its files and resolve its command.

    Args:
        dirs: the attempt's folder (made here; an earlier one of the same attempt is cleared).
        cmd: the placement: inputs, peers' addresses, the attempt's id.
        task: what to run.
        base_env: the environment the command starts from.
        secrets: the payloads of the credentials ``task`` names (credential name → payload).
        boxed: the task runs in its image (``osmo.worker.containers``): tokens name the
            container's paths, nothing is rewritten, ``base_env`` is not used, and the launch
            carries the container's layout (``containers.layout``) for the pool to finish.

    Raises:
        PrepareError: a token cannot be resolved, a file path is unusable, or the folder
            cannot be written (the message names the path).
        SecretError: a credential the task names is not in ``secrets`` or lacks a key.
    """
    if not task.command and not task.type:
        raise PrepareError(f"task '{task.name}' has no command to run")
    secrets = secrets or {}
    mounted = mounts(task, secrets)
    mapping = _file_mapping(dirs, task, mounted)
    rewrite = (lambda value: value) if boxed else _rewriter(mapping)
    resolve = _resolver(dirs, cmd, task, boxed=boxed)

    def text(value: str) -> str:
        return substitute(rewrite(value), resolve)

    defined = {key: text(str(value)) for key, value in task.environment.items()}
    # boxed: credential variables live in the container's secret file; expanded into args
    # they would show in `podman inspect`, so $(SECRET) stays as written there
    defined.update({} if boxed else secret_env(task, secrets))
    defined.update(containers.osmo_env(cmd) if boxed else _osmo_env(dirs, cmd))
    # args expand $(NAME) from the variables the task defines, as Kubernetes does
    argv = (*(text(word) for word in task.command),
            *(expand_vars(text(word), defined) for word in task.args))
    env = dict(defined) if boxed else {**base_env, **defined}
    if task.type:  # a typed task: the runner reads its context file (osmo.worker.launch)
        argv = launch.runner_argv(dirs.context)
        env.update(launch.runner_env(task, env))
    try:
        _make_folders(dirs, with_files=bool(task.files or mounted))
        _write_files(mapping, task, text)
        written = _write_mounts(mapping, mounted)
        if task.type:
            _write_context(dirs, cmd, task)
    except OSError as exc:
        raise PrepareError(f"cannot prepare {exc.filename or dirs.root}: {exc.strerror}") from exc
    box = containers.layout(dirs, task, mapping, _input_refs(cmd, task),
                            secret_env(task, secrets)) if boxed else None
    return Launch(argv, dirs.work, env, tuple(secret_values(task, secrets)), written,
                  container=box)


_MAX_INPUT_BINDS = 2000  # each is 3 bubblewrap arguments; bubblewrap takes at most 9,000


def attempt_view(dirs: AttemptDirs, cmd: PrepareAttempt, hidden: tuple[Path, ...],
                 masked: tuple[Path, ...] = (), code: tuple[Path, ...] = ()) -> View:
    """What a sandboxed attempt sees of the ``hidden`` folders (osmo's homes; the docstring).

    ``cmd.inputs`` are its resolved input references; those that are folders are bound
    read-only (a ``url`` input's download and a copy sit in paths bound read-only already).
    ``masked``: files it must not see; ``code``: folders a typed task imports its type from
    (``TaskSpec.resolved.paths``), shown read-only.
    """
    bound: list[Path] = []
    for path in sorted({Path(ref) for ref in cmd.inputs.values() if ref.startswith("/")}):
        # inputs inside the attempt's folder (its checked links) are bound with it, and a
        # folder inside one already bound needs nothing more (bubblewrap takes ≤ 9,000 args)
        if not path.is_relative_to(dirs.root) and not (bound and path.is_relative_to(bound[-1])):
            bound.append(path)
    if len(bound) > _MAX_INPUT_BINDS:
        raise PrepareError(f"{len(bound):,} input folders outside osmo's store are more than a "
                           f"sandbox can bind ({_MAX_INPUT_BINDS:,}); run it with --sandbox off "
                           "or give it fewer, larger inputs")
    return View(hidden=hidden, readonly=(dirs.root, dirs.url_inputs, *bound),
                writable=(dirs.work, dirs.output_partial, dirs.files), cwd=dirs.work,
                masked=masked, code=code)


def hand_over(dirs: AttemptDirs, owner: tuple[int, int]) -> None:
    """Give a sandboxed attempt of a root pool what it writes (``owner``: its host ids).

    Its ``work/``, ``output.partial/`` and ``files/``, and what preparing wrote in them (its
    files, its credentials' files), become ``owner``'s; its folder and its inputs' folders
    get the search bit for others if they lack it (the umask's), so that it can reach its
    inputs, never the right to list or write them. Inputs themselves (links of blobs) are
    left alone. The pool (root) still reads, ingests and removes all of it.
    """
    uid, gid = owner
    for top in (dirs.work, dirs.output_partial, dirs.files):
        if not top.exists():
            continue
        os.chown(top, uid, gid)
        for folder, subfolders, names in os.walk(top):
            for name in (*subfolders, *names):
                os.lchown(os.path.join(folder, name), uid, gid)
    for reached in (dirs.root, dirs.inputs, dirs.url_inputs):
        try:
            mode = os.stat(reached).st_mode
        except FileNotFoundError:
            continue
        if not mode & 0o001:
            os.chmod(reached, stat.S_IMODE(mode) | 0o001)


def remove_secret_files(launch: Launch) -> None:
    """Delete the files an attempt's credential mounts wrote (missing ones are fine)."""
    for path in launch.secret_files:
        try:
            path.unlink()
        except FileNotFoundError:
            pass


def promote(dirs: AttemptDirs) -> str:
    """Rename ``output.partial`` to ``output`` and make the rename durable.

    Returns:
        the output reference (absolute path of ``output``).

    Raises:
        OSError: the rename or the fsync failed.
    """
    os.rename(dirs.output_partial, dirs.output)
    fd = os.open(dirs.root, os.O_RDONLY | os.O_DIRECTORY | os.O_CLOEXEC)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)
    return str(dirs.output)


# ---------------------------------------------------------------- helpers


def _write_context(dirs: AttemptDirs, cmd: PrepareAttempt, task: TaskSpec) -> None:
    """The typed task's context file; its inputs resolve like ``{{input:N}}``."""
    inputs = []
    for index, spec in enumerate(task.inputs):
        ref = _input_ref(index, spec, cmd.inputs)
        if ref is None:
            raise PrepareError(f"task '{task.name}': input {index} is not available")
        inputs.append((launch.input_name(spec), ref))
    launch.write_context(dirs.context, task=task, inputs=inputs,
                         output=dirs.output_partial, workdir=dirs.work,
                         workflow_id=cmd.workflow_id, retry=cmd.retry, attempt_id=cmd.attempt_id)


def _osmo_env(dirs: AttemptDirs, cmd: PrepareAttempt) -> dict[str, str]:
    return {
        "OSMO_WORKFLOW_ID": cmd.workflow_id,
        "OSMO_TASK": cmd.task,
        "OSMO_RETRY": str(cmd.retry),
        "OSMO_NODE": cmd.node_id,
        "OSMO_OUTPUT": str(dirs.output_partial),
        "OSMO_FILES_ROOT": str(dirs.files),
    }


def _make_folders(dirs: AttemptDirs, *, with_files: bool) -> None:
    # Each mkdir costs tens of microseconds here; only the folders an attempt needs are made,
    # and the parents only when missing (the common case is a new task folder per attempt).
    if dirs.root.name == "0":  # a first attempt: its task's folder is new too, as a rule
        try:
            os.mkdir(dirs.root.parent)
        except FileExistsError:
            pass
        except FileNotFoundError:
            dirs.root.parent.mkdir(parents=True, exist_ok=True)
    try:
        dirs.root.mkdir()
    except FileExistsError:  # the same attempt prepared again (e.g. after a server restart)
        remove_tree(dirs.root)  # iterative: the last run may have left a very deep tree
        dirs.root.mkdir()
    except FileNotFoundError:
        dirs.root.parent.mkdir(parents=True, exist_ok=True)
        dirs.root.mkdir()
    folders = (dirs.work, dirs.files, dirs.output_partial) if with_files else (
        dirs.work, dirs.output_partial)
    for folder in folders:
        folder.mkdir()


def _file_mapping(dirs: AttemptDirs, task: TaskSpec,
                  mounted: Mapping[str, object]) -> dict[str, Path]:
    """Declared path → private location, for every file and credential mount of the task."""
    mapping: dict[str, Path] = {}
    for path, what in [*((f.path, "file") for f in task.files),
                       *((m, "credential mount") for m in mounted)]:
        normal = posixpath.normpath(path)
        if not path or normal == "/":
            raise PrepareError(f"{what} path {path!r} names no {what.split()[-1]}")
        if normal.startswith("/"):
            mapping[path] = dirs.files / normal.lstrip("/")
        elif normal == ".." or normal.startswith("../"):
            raise PrepareError(f"{what} path {path!r} leaves the working folder")
        else:
            mapping[path] = dirs.work / normal
    return mapping


def _rewriter(mapping: Mapping[str, Path]) -> Callable[[str], str]:
    """A function that rewrites whole occurrences of declared absolute paths."""
    absolute = {p: str(target) for p, target in mapping.items() if p.startswith("/")}
    if not absolute:
        return lambda value: value
    alternatives = "|".join(re.escape(p) for p in sorted(absolute, key=len, reverse=True))
    pattern = re.compile(rf"(?<![\w./-])(?:{alternatives})(?![\w.-])")
    return lambda value: pattern.sub(lambda m: absolute[m.group(0)], value)


def _write_files(mapping: Mapping[str, Path], task: TaskSpec, text: Callable[[str], str]) -> None:
    for spec in task.files:
        data = _decode(spec.contents, spec.path) if spec.base64 else text(spec.contents).encode()
        target = mapping[spec.path]
        target.parent.mkdir(parents=True, exist_ok=True)
        mode = 0o755 if data.startswith(b"#!") else 0o644
        fd = os.open(target, os.O_WRONLY | os.O_CREAT | os.O_TRUNC | os.O_CLOEXEC, mode)
        try:
            os.write(fd, data)
            os.fchmod(fd, mode)  # the umask must not strip the executable bit
        finally:
            os.close(fd)


def _write_mounts(mapping: Mapping[str, Path],
                  mounted: Mapping[str, Mapping[str, str]]) -> tuple[Path, ...]:
    written: list[Path] = []
    try:
        for path, payload in mounted.items():
            folder = mapping[path]
            folder.mkdir(parents=True, exist_ok=True)
            for key, value in payload.items():
                target = folder / key
                flags = os.O_WRONLY | os.O_CREAT | os.O_TRUNC | os.O_CLOEXEC
                fd = os.open(target, flags, 0o600)
                written.append(target)
                try:
                    os.fchmod(fd, 0o600)  # an existing file keeps its mode on O_CREAT
                    os.write(fd, value.encode())
                finally:
                    os.close(fd)
    except OSError:  # a failed preparation leaves no secret behind
        remove_secret_files(Launch((), Path(), {}, (), tuple(written)))
        raise
    return tuple(written)


def _decode(contents: str, path: str) -> bytes:
    try:
        return base64.b64decode(contents, validate=False)
    except (binascii.Error, ValueError) as exc:
        raise PrepareError(f"file {path!r}: invalid base64 contents ({exc})") from exc


def _input_refs(cmd: PrepareAttempt, task: TaskSpec) -> list[str | None]:
    """The reference of each ``inputs:`` entry, in order (None: not available)."""
    return [_input_ref(i, spec, cmd.inputs) for i, spec in enumerate(task.inputs)]


def _input_ref(index: int, spec: InputSpec, inputs: Mapping[str, str]) -> str | None:
    """The reference of one ``inputs:`` entry, looked up by its most specific key."""
    keys: list[str | None]
    if spec.task is not None:
        keys = [f"{spec.workflow}:{spec.task}" if spec.workflow else None, spec.task]
    else:
        keys = [spec.url, spec.dataset]
    for key in [*keys, str(index)]:
        if key is not None and key in inputs:
            return inputs[key]
    return None


def _resolver(dirs: AttemptDirs, cmd: PrepareAttempt, task: TaskSpec, *,
              boxed: bool = False) -> Callable[[str], str]:
    attempt_uuid = uuid.uuid4().hex

    def resolve(token: str) -> str:
        kind, _, arg = token.partition(":")
        value: str | None = None
        if boxed and kind in ("output", "input"):  # the container's own paths
            value = containers.data_path(token, task, _input_refs(cmd, task))
        elif kind == "output":
            value = str(dirs.output_partial)
        elif kind == "workflow_id":
            value = cmd.workflow_id
        elif kind == "uuid":
            value = attempt_uuid
        elif kind == "host":
            value = cmd.hosts.get(arg)
        elif kind == "input" and arg.isdigit():
            index = int(arg)
            if index < len(task.inputs):
                value = _input_ref(index, task.inputs[index], cmd.inputs)
        elif kind == "input":
            value = cmd.inputs.get(arg)
        if value is None:
            raise PrepareError(f"task '{task.name}': cannot resolve {{{{{token}}}}}")
        return value

    return resolve
