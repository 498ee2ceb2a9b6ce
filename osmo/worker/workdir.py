"""An attempt's private folder: its preparation and output promotion.

The folder's layout (``work/``, ``inputs/``, ``files/``, ``output.partial/``, ``output/``,
``log.txt``, ``task.json``) is :class:`osmo.layout.AttemptDirs`; this module makes and
fills it.

What the task sees of its attempt — the paths its tokens and ``OSMO_*`` variables name —
is its runtime's (``Runtime.paths``, an ``osmo.runtime.api.Paths``). The host's own paths
(``HOST_PATHS``, the process runtimes') are described here; a container's (OSMO's data
layout) in ``osmo.runtime.container.layout``: there ``{{output}}`` is ``/osmo/data/output``,
``{{input:N}}`` ``/osmo/data/input/N``, files are bound at their declared paths and nothing
is rewritten, and the environment is the task's own, without the worker's base.

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
written (``osmo.spec.tokens.expand_vars``). Where credential variables are handed over apart
(``Paths.hidden_secrets``: a container's, whose args show in ``podman inspect``) they are not
expanded; the shell's ``$NAME`` has them.

Environment: a small base taken from the worker's (``osmo.worker.taskenv``: ``PATH``,
``HOME``, locale; never the whole environment, never ``OSMO_HOME``), then the task's
``environment`` (tokens substituted), then the variables its credentials set (``NAME: {ENV:
key}``, verbatim), then osmo's own variables, which a task cannot override:
``OSMO_WORKFLOW_ID``, ``OSMO_TASK``, ``OSMO_RETRY``, ``OSMO_NODE``, ``OSMO_OUTPUT``,
``OSMO_FILES_ROOT``.

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
import uuid
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path

from osmo.artifacts.fsops import remove_tree
from osmo.layout import AttemptDirs
from osmo.runtime.api import HOST_PATHS, Launch, Paths, PrepareError
from osmo.scheduler.types import PrepareAttempt
from osmo.spec.model import InputSpec, TaskSpec
from osmo.spec.tokens import expand_vars, substitute
from osmo.worker import launch
from osmo.worker.secrets import Secrets, mounts, secret_env, secret_values

__all__ = ["PrepareError", "prepare", "promote", "remove_secret_files"]


def prepare(
    dirs: AttemptDirs, cmd: PrepareAttempt, task: TaskSpec, base_env: Mapping[str, str],
    secrets: Secrets | None = None, *, paths: Paths = HOST_PATHS,
) -> Launch:
    """Create the attempt's folder, write its files and resolve its command.

    Args:
        dirs: the attempt's folder (made here; an earlier one of the same attempt is cleared).
        cmd: the placement: inputs, peers' addresses, the attempt's id.
        task: what to run.
        base_env: the environment the command starts from (unless ``paths.own_env``).
        secrets: the payloads of the credentials ``task`` names (credential name → payload).
        paths: how its runtime shows it its attempt (``Runtime.paths``; the module docstring).

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
    refs = _input_refs(cmd, task)
    rewrite = (lambda value: value) if paths.bound_files else _rewriter(mapping)
    resolve = _resolver(dirs, cmd, task, paths, refs)

    def text(value: str) -> str:
        return substitute(rewrite(value), resolve)

    defined = {key: text(str(value)) for key, value in task.environment.items()}
    credential_env = secret_env(task, secrets)
    # handed over apart (a container's secret file): expanded into args they would show in
    # `podman inspect`, so $(SECRET) stays as written there
    defined.update({} if paths.hidden_secrets else credential_env)
    defined.update(_osmo_env(dirs, cmd, paths))
    # args expand $(NAME) from the variables the task defines, as Kubernetes does
    argv = (*(text(word) for word in task.command),
            *(expand_vars(text(word), defined) for word in task.args))
    env = dict(defined) if paths.own_env else {**base_env, **defined}
    if task.type:  # a typed task: the runner reads its context file (osmo.worker.launch)
        argv = launch.runner_argv(dirs.context, paths.runner)
        env.update(launch.runner_env(task, env, paths.runner))
    try:
        _make_folders(dirs, with_files=bool(task.files or mounted))
        _write_files(mapping, task, text)
        written = _write_mounts(mapping, mounted)
        if task.type:
            _write_context(dirs, cmd, task, paths)
    except OSError as exc:
        raise PrepareError(f"cannot prepare {exc.filename or dirs.root}: {exc.strerror}") from exc
    return Launch(argv, dirs.work, env, tuple(secret_values(task, secrets)),
                  secret_env=credential_env if paths.hidden_secrets else {},
                  secret_files=written, files=mapping, inputs=tuple(refs))


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


def _write_context(dirs: AttemptDirs, cmd: PrepareAttempt, task: TaskSpec,
                   paths: Paths) -> None:
    """The typed task's context file; its inputs resolve like ``{{input:N}}``.

    Its paths are those the task is shown (``paths``: in its image, where it is bound).
    """
    shown = paths.runner
    inputs = []
    for index, spec in enumerate(task.inputs):
        ref = _input_ref(index, spec, cmd.inputs)
        if ref is None:
            raise PrepareError(f"task '{task.name}': input {index} is not available")
        if shown is not None and paths.input_dir is not None and ref.startswith("/"):
            ref = paths.input_dir.format(index)
        inputs.append((launch.input_name(spec), ref))
    launch.write_context(dirs.context, task=task, inputs=inputs,
                         output=paths.output or dirs.output_partial,
                         workdir=shown.workdir if shown else dirs.work,
                         workflow_id=cmd.workflow_id, retry=cmd.retry, attempt_id=cmd.attempt_id,
                         shown=shown)


def _osmo_env(dirs: AttemptDirs, cmd: PrepareAttempt, paths: Paths) -> dict[str, str]:
    """The variables osmo sets (the task cannot override them)."""
    return {
        "OSMO_WORKFLOW_ID": cmd.workflow_id,
        "OSMO_TASK": cmd.task,
        "OSMO_RETRY": str(cmd.retry),
        "OSMO_NODE": cmd.node_id,
        "OSMO_OUTPUT": paths.output or str(dirs.output_partial),
        "OSMO_FILES_ROOT": paths.files_root or str(dirs.files),
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
        remove_secret_files(Launch((), Path(), {}, secret_files=tuple(written)))
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


def _resolver(dirs: AttemptDirs, cmd: PrepareAttempt, task: TaskSpec, paths: Paths,
              refs: Sequence[str | None]) -> Callable[[str], str]:
    attempt_uuid = uuid.uuid4().hex
    hosts = cmd.hosts if paths.hosts is None else paths.hosts

    def resolve(token: str) -> str:
        kind, _, arg = token.partition(":")
        value: str | None = None
        if kind == "output":
            value = paths.output or str(dirs.output_partial)
        elif kind == "workflow_id":
            value = cmd.workflow_id
        elif kind == "uuid":
            value = attempt_uuid
        elif kind == "host":
            value = hosts.get(arg)
        elif kind == "input" and paths.input_dir is not None:  # where the runtime binds it
            value = _shown_input(arg, task, refs, paths.input_dir)
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


def _shown_input(arg: str, task: TaskSpec, refs: Sequence[str | None],
                 input_dir: str) -> str | None:
    """Where an input the attempt has (by index or name) is bound for its task."""
    for index, spec in enumerate(task.inputs):
        names = (str(index),) if arg.isdigit() else (launch.input_name(spec), spec.task)
        if arg in names and refs[index] is not None:
            return input_dir.format(index)
    return None
