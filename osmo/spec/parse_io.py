"""Parsing of a task's data fields: ``files``, ``inputs``, ``outputs`` and ``checkpoint``.

Reads ``files[].localpath`` (relative to the spec's folder, and only where
``osmo.spec.localfiles`` allows) into ``FileSpec.contents``; otherwise pure. Cross-task
checks (does an input task exist?) belong to ``validate``.
"""

from __future__ import annotations

import base64
import binascii
import posixpath
import re
from pathlib import PurePosixPath
from typing import Any

from osmo.names import name_problem, ref_problem, shown, workflow_id_problem
from osmo.spec.files import FileRefused
from osmo.spec.localfiles import LocalFiles, LocalPathRefused
from osmo.spec.model import FileSpec, InputSpec, OutputSpec
from osmo.spec.reader import (
    Ctx,
    read_bool,
    read_fields,
    read_list,
    read_map,
    read_name,
    read_str,
)
from osmo.spec.support import UNSUPPORTED
from osmo.spec.units import parse_duration
from osmo.spec.yamlnodes import Map, Node, to_plain

__all__ = ["MAX_LOCAL_FILE", "parse_checkpoint", "parse_files", "parse_inputs", "parse_outputs"]

MAX_LOCAL_FILE = 16 * 1024 * 1024  # bytes read from one ``localpath``
MAX_PATH = 4096  # bytes of a file path (Linux PATH_MAX)
MAX_PATH_PART = 255  # bytes of one of its components (NAME_MAX)

_FILE_KEYS = ("path", "contents", "base64", "localpath")
_INPUT_KINDS = ("task", "url", "dataset")
_CHECKPOINT_KEYS = ("path", "url", "frequency", "regex")


def _read_regex(ctx: Ctx, fields: dict[str, Node], what: str) -> str | None:
    node = fields.get("regex")
    if node is None:
        return None
    pattern = read_str(ctx, node, f"'regex' of {what}")
    if pattern is not None:
        try:
            re.compile(pattern)
        except re.error as exc:
            ctx.error(node, f"'regex' of {what} is not a valid regular expression: {exc}")
    return pattern


def _read_local(ctx: Ctx, node: Node, local: LocalFiles,
                where: str) -> tuple[str, bool] | None:
    """The contents of a ``localpath`` file: text, or base64 for binary/non-UTF-8 data."""
    name = read_str(ctx, node, f"'localpath' in {where}")
    if name is None:
        return None
    try:
        data = local.read(name, limit=MAX_LOCAL_FILE)
    except FileNotFoundError:
        ctx.error(node, f"localpath '{name}' in {where} does not exist (looked for "
                        f"{local.base / name if local.base else name})")
        return None
    except LocalPathRefused as exc:
        ctx.error(node, f"localpath '{name}' in {where} {exc}")
        return None
    except FileRefused as exc:
        ctx.error(node, f"localpath '{name}' in {where} {exc}; it must name a file")
        return None
    except OSError as exc:
        ctx.error(node, f"cannot read localpath '{name}' in {where}: {exc.strerror or exc}")
        return None
    try:
        return data.decode("utf-8"), False
    except UnicodeDecodeError:
        return base64.b64encode(data).decode("ascii"), True


def _file(ctx: Ctx, node: Node, local: LocalFiles, where: str) -> FileSpec | None:
    fields = read_fields(ctx, node, _FILE_KEYS, f"a file of {where}", required=("path",))
    if fields is None or "path" not in fields:
        return None
    path = read_str(ctx, fields["path"], f"'path' of a file in {where}")
    problem = None if path is None else _path_problem(path)
    if problem is not None:
        ctx.error(fields["path"], f"file path {shown(path)} in {where} {problem}")
        path = None
    has_contents, has_local = "contents" in fields, "localpath" in fields
    if has_contents == has_local:
        if not (ctx.hinted(node, "contents") or ctx.hinted(node, "localpath")):
            ctx.error(node, f"a file of {where} needs exactly one of 'contents' or 'localpath'")
        return None
    if has_local:
        if "base64" in fields:
            ctx.error(fields["base64"], "'base64' applies to 'contents', not to 'localpath'")
        read = _read_local(ctx, fields["localpath"], local, where)
        if read is None or path is None:
            return None
        return FileSpec(path, read[0], read[1], pos=node.pos)
    contents = read_str(ctx, fields["contents"], f"'contents' of file '{path}'", allow_empty=True)
    encoded = read_bool(ctx, fields["base64"], "'base64'") if "base64" in fields else False
    if encoded and contents is not None:
        try:
            base64.b64decode(contents, validate=True)
        except binascii.Error:
            ctx.error(fields["contents"], f"contents of file '{path}' are not valid base64")
    if path is None or contents is None:
        return None
    return FileSpec(path, contents, bool(encoded), pos=node.pos)


def _path_problem(path: str) -> str | None:
    """Why a ``files:`` path cannot name a file the task gets, or None.

    See ``workdir``: absolute paths go under the attempt's ``files/``, relative ones under
    ``work/``.
    """
    if ".." in PurePosixPath(path).parts:
        return "must not contain '..'"
    if "\0" in path:
        return "must not contain a NUL character"
    if posixpath.normpath(path) in ("/", ".", "//") or path.endswith("/"):
        return "names a folder, not a file; give the file's name (e.g. /etc/app.conf)"
    encoded = path.encode("utf-8", "surrogateescape")
    if len(encoded) > MAX_PATH or any(len(p) > MAX_PATH_PART for p in encoded.split(b"/")):
        return (f"is too long: at most {MAX_PATH} bytes, and {MAX_PATH_PART} bytes per "
                "folder or file name")
    return None


def _clash(spec: FileSpec, out: list[FileSpec], where: str) -> str | None:
    """Why ``spec`` cannot be written beside the earlier files of its task, or None."""
    mine = posixpath.normpath(spec.path)
    for first in out:
        theirs, line = posixpath.normpath(first.path), first.pos.line if first.pos else 0
        if theirs == mine:
            return (f"file path '{spec.path}' appears twice in {where} (first at line {line}); "
                    "paths must be unique per task")
        if mine.startswith(theirs + "/") or theirs.startswith(mine + "/"):
            return (f"file paths '{spec.path}' and '{first.path}' (line {line}) of {where} "
                    "cannot both be files: one is inside the other")
    return None


def parse_files(ctx: Ctx, node: Node, local: LocalFiles, where: str) -> tuple[FileSpec, ...]:
    """``files:`` entries; paths that are the same file, or one inside another, are reported.

    ``localpath`` files are read through ``local`` (``osmo.spec.localfiles``).
    """
    out: list[FileSpec] = []
    for item in read_list(ctx, node, f"'files' of {where}"):
        spec = _file(ctx, item, local, where)
        if spec is None:
            continue
        clash = _clash(spec, out, where)
        if clash is not None:
            ctx.error(item, clash)
            continue
        out.append(spec)
    return tuple(out)


def _unsupported(ctx: Ctx, node: Node, key: str, where: str) -> None:
    """Report ``key`` if this release does not support it (see ``support.UNSUPPORTED``)."""
    if key in UNSUPPORTED:
        ctx.error(node, f"{where}: {UNSUPPORTED[key]}")


def _dataset(ctx: Ctx, node: Node, keys: tuple[str, ...], what: str) -> dict[str, Node]:
    fields = read_fields(ctx, node, keys, what, required=("name",))
    return fields or {}


def _input(ctx: Ctx, node: Node, where: str) -> InputSpec | None:
    what = f"an input of {where}"
    fields = read_fields(ctx, node, (*_INPUT_KINDS, "regex"), what)
    if fields is None:
        return None
    kinds = [k for k in _INPUT_KINDS if k in fields]
    if not kinds and any(ctx.hinted(node, k) for k in _INPUT_KINDS):
        return None
    if len(kinds) != 1:
        ctx.error(node, f"{what} needs exactly one of 'task', 'url' or 'dataset'")
        return None
    kind = kinds[0]
    _unsupported(ctx, node, f"inputs.{kind}", where)
    regex = _read_regex(ctx, fields, what)
    if kind == "dataset":
        ds = _dataset(ctx, fields["dataset"], ("name", "regex"), f"'dataset' of {what}")
        name = read_str(ctx, ds["name"], "dataset name") if "name" in ds else None
        problem = None if name is None else ref_problem(name)
        if problem is not None:
            ctx.error(ds["name"], f"{problem} (a dataset input is NAME[:TAG|VERSION|latest])")
        return InputSpec(dataset=name, regex=_read_regex(ctx, ds, what) or regex, pos=node.pos)
    value = read_str(ctx, fields[kind], f"'{kind}' of {what}")
    if value is None:
        return None
    if kind == "url":
        return InputSpec(url=value, regex=regex, pos=node.pos)
    workflow, _, task = value.rpartition(":")
    if ":" in value and not (workflow and task):
        ctx.error(fields["task"], f"'{value}' in {where} must be NAME or WORKFLOW_ID:NAME")
        return None
    if workflow:
        problem = workflow_id_problem(workflow) or name_problem(task, "task name")
        if problem is not None:
            ctx.error(fields["task"], f"{problem} (in '- task: WORKFLOW_ID:NAME')")
    return InputSpec(task=task, workflow=workflow or None, regex=regex, pos=node.pos)


def parse_inputs(ctx: Ctx, node: Node, where: str) -> tuple[InputSpec, ...]:
    """``inputs:`` entries (``task``, ``url``, [ext] ``dataset``), in list order."""
    items = read_list(ctx, node, f"'inputs' of {where}")
    return tuple(i for i in (_input(ctx, item, where) for item in items) if i is not None)


def _output(ctx: Ctx, node: Node, where: str) -> OutputSpec | None:
    what = f"an output of {where}"
    fields = read_fields(ctx, node, ("url", "dataset", "regex"), what)
    if fields is None:
        return None
    kinds = [k for k in ("url", "dataset") if k in fields]
    if len(kinds) != 1:
        ctx.error(node, f"{what} needs exactly one of 'url' or 'dataset'")
        return None
    _unsupported(ctx, node, f"outputs.{kinds[0]}", where)
    regex = _read_regex(ctx, fields, what)
    if kinds[0] == "url":
        url = read_str(ctx, fields["url"], f"'url' of {what}")
        return OutputSpec(url=url, regex=regex, pos=node.pos)
    ds = _dataset(ctx, fields["dataset"], ("name", "path", "regex", "metadata"), what)
    name = read_name(ctx, ds["name"], "dataset name") if "name" in ds else None
    path = read_str(ctx, ds["path"], "dataset 'path'") if "path" in ds else None
    metadata = ds.get("metadata")
    meta = None
    if metadata is not None and read_map(ctx, metadata, "dataset 'metadata'") is not None:
        meta = to_plain(metadata) if isinstance(metadata, Map) else {}
    return OutputSpec(dataset=name, path=path, regex=_read_regex(ctx, ds, what) or regex,
                      metadata=meta, pos=node.pos)


def parse_outputs(ctx: Ctx, node: Node, where: str) -> tuple[OutputSpec, ...]:
    """``outputs:`` entries (``url``, [ext] ``dataset``)."""
    items = read_list(ctx, node, f"'outputs' of {where}")
    return tuple(o for o in (_output(ctx, item, where) for item in items) if o is not None)


def parse_checkpoint(ctx: Ctx, node: Node, where: str) -> tuple[dict[str, Any], ...]:
    """``checkpoint:`` entries as plain dicts (``path``, ``url``, ``frequency``, ``regex``)."""
    out = []
    for item in read_list(ctx, node, f"'checkpoint' of {where}"):
        fields = read_fields(ctx, item, _CHECKPOINT_KEYS, f"a checkpoint of {where}",
                             required=("path", "url", "frequency"))
        if fields is None or not isinstance(item, Map):
            continue
        if "frequency" in fields:
            try:
                parse_duration(to_plain(fields["frequency"]))
            except ValueError as exc:
                ctx.error(fields["frequency"], f"'frequency' of a checkpoint of {where}: {exc}")
                continue
        if "regex" in fields:
            _read_regex(ctx, fields, f"a checkpoint of {where}")
        out.append(to_plain(item))
    return tuple(out)
