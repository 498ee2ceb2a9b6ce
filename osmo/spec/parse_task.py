"""Parsing of one task mapping into a :class:`TaskSpec`.

Owns the task's field table, its scalar/list/map fields and ``exitActions``. Data fields
(files, inputs, outputs, checkpoint) are read by ``parse_io``. Checks that need other tasks
(names, inputs, resources, tokens) belong to ``validate``.
"""

from __future__ import annotations

import posixpath
import re
from typing import Any

from osmo.names import did_you_mean, image_problem
from osmo.spec.localfiles import LocalFiles
from osmo.spec.model import DEFAULT_RESOURCE, ExitAction, ExitRule, TaskSpec
from osmo.spec.parse_io import parse_checkpoint, parse_files, parse_inputs, parse_outputs
from osmo.spec.reader import (
    Ctx,
    is_empty,
    read_bool,
    read_fields,
    read_map,
    read_name,
    read_str,
    read_str_list,
    scalar_text,
)
from osmo.spec.support import UNSUPPORTED
from osmo.spec.units import overlap, parse_exit_codes
from osmo.spec.yamlnodes import Map, Node, Scalar, Seq, to_plain

__all__ = ["TASK_KEYS", "parse_task"]

TASK_KEYS = ("name", "image", "command", "args", "environment", "files", "inputs", "outputs",
             "credentials", "resource", "lead", "exitActions", "checkpoint", "volumeMounts",
             "privileged", "hostNetwork", "type", "params", "cache", "warm")
_ACTIONS = [a.value for a in ExitAction]
_ENV_NAME = re.compile(r"[A-Za-z_][A-Za-z0-9_]*")
_POD_ENV_NAME = re.compile(r"[-._a-zA-Z][-._a-zA-Z0-9]*")  # what a Kubernetes pod takes


def _str_map(ctx: Ctx, node: Node, what: str) -> dict[str, str]:
    """A map whose scalar values are stringified (``true`` → ``"true"``, ``1.0`` → ``"1.0"``)."""
    out: dict[str, str] = {}
    for key, value in read_map(ctx, node, what) or []:
        text = scalar_text(value)
        if text is None:
            ctx.error(value, f"{what} '{key.text}' needs a plain value (write \"\" for empty)")
        else:
            out[key.text] = text
    return out


def _environment(ctx: Ctx, node: Node, what: str) -> dict[str, str]:
    """A task's ``environment``: names a Kubernetes pod takes, values with no NUL.

    The same rule on every runtime: the workflow that runs on a laptop runs as pods too.
    """
    for var, value in read_map(ctx, node, what) or []:
        if not _POD_ENV_NAME.fullmatch(var.text):
            ctx.error(var, f"{what} '{var.text}' is not a usable name (letters, digits, "
                           "'_', '-' and '.', not starting with a digit)")
        text = scalar_text(value)
        if text is not None and "\0" in text:
            ctx.error(value, f"{what} '{var.text}' holds a NUL character, which no process "
                             "can be given")
    return _str_map(ctx, node, what)


def _credential_env(ctx: Ctx, node: Map, name: str) -> dict[str, str]:
    """``{ENV: key}``: names must be usable variable names that osmo does not own."""
    for var, _ in read_map(ctx, node, f"credential '{name}' variable") or []:
        if not _ENV_NAME.fullmatch(var.text):
            ctx.error(var, f"credential '{name}': '{var.text}' is not an environment variable "
                           "name (letters, digits and _, not starting with a digit)")
        elif var.text.startswith("OSMO_"):
            ctx.error(var, f"credential '{name}': variables named OSMO_* are set by osmo; "
                           "choose another name")
    return _str_map(ctx, node, f"credential '{name}' variable")


def _credentials(ctx: Ctx, node: Node, where: str) -> dict[str, Any]:
    """``NAME: /path`` (mount as files) or ``NAME: {ENV: key}`` (inject as env vars)."""
    out: dict[str, Any] = {}
    for key, value in read_map(ctx, node, f"'credentials' of {where}") or []:
        if isinstance(value, Map):
            out[key.text] = _credential_env(ctx, value, key.text)
        elif isinstance(value, Scalar) and isinstance(value.value, str) and value.value:
            normal = posixpath.normpath(value.value)
            if normal == "/" or normal == ".." or normal.startswith("../"):
                ctx.error(value, f"credential '{key.text}' of {where}: mount path "
                                 f"'{value.value}' must name a folder inside the task's files "
                                 "(like /etc/creds)")
            out[key.text] = value.value
        else:
            ctx.error(value, f"credential '{key.text}' of {where} must be a mount path or a "
                             "mapping ENV_NAME: secret_key")
    return out


def _image(ctx: Ctx, node: Node, where: str) -> str | None:
    """An OCI image reference; anything else is refused here, before an engine sees it."""
    image = read_str(ctx, node, f"'image' of {where}")
    problem = image_problem(image) if image is not None else None
    if problem is not None:
        ctx.error(node, f"'image' of {where} is not a usable image reference: {problem}")
    return image


def _codes_value(ctx: Ctx, node: Node, what: str) -> Any:
    if isinstance(node, Scalar):
        return node.value
    if isinstance(node, Seq) and all(isinstance(n, Scalar) for n in node.items):
        return [n.value for n in node.items if isinstance(n, Scalar)]
    ctx.error(node, f"{what} must be exit codes like '0,1-10,16'")
    return None


def _exit_actions(ctx: Ctx, node: Node, where: str) -> tuple[ExitRule, ...]:
    """``exitActions``: action names are case-insensitive; ranges may not overlap anywhere."""
    rules: list[ExitRule] = []
    for key, value in read_map(ctx, node, f"'exitActions' of {where}") or []:
        name = key.text.upper()
        if name not in _ACTIONS:
            hint = did_you_mean(name, _ACTIONS)
            ctx.error(key, f"unknown exit action '{key.text}' in {where}{hint}; use "
                           "COMPLETE, FAIL or RESCHEDULE")
            continue
        action = ExitAction(name)
        if any(r.action is action for r in rules):
            ctx.error(key, f"exit action {name} appears twice in {where}")
            continue
        raw = _codes_value(ctx, value, f"exit action {name}")
        if raw is None:
            continue
        try:
            ranges = parse_exit_codes(raw)
        except ValueError as exc:
            ctx.error(value, f"exit action {name} of {where}: {exc}")
            continue
        clashes = [(r.action.value, overlap(r.ranges, ranges)) for r in rules]
        clash = next(((a, c) for a, c in clashes if c), None)
        if clash:
            ctx.error(value, f"exit codes {clash[1]} of {where} are in both {clash[0]} and "
                             f"{name}; each code may have one action")
            continue
        rules.append(ExitRule(action, ranges))
    return tuple(rules)


def _command(ctx: Ctx, fields: dict[str, Node], node: Node, where: str) -> tuple[str, ...]:
    has_type = "type" in fields
    if "command" not in fields:
        if not has_type and not ctx.hinted(node, "command"):
            ctx.error(node, f"{where} has no 'command'; add one, e.g. command: [python, run.py]")
        return ()
    if has_type:
        ctx.error(fields["command"], f"{where} has both 'command' and 'type'; keep one")
        return ()
    value = fields["command"]
    if isinstance(value, Scalar) and isinstance(value.value, str):
        words = ", ".join(value.value.split()[:3]) or "python, run.py"
        ctx.error(value, f"'command' of {where} must be a list of words, e.g. [{words}]")
        return ()
    command = read_str_list(ctx, value, f"'command' of {where}")
    if is_empty(value):
        ctx.error(value, f"'command' of {where} must not be empty")
    return command


def _optional(ctx: Ctx, fields: dict[str, Node], key: str, reader: Any, *args: Any) -> Any:
    node = fields.get(key)
    return None if node is None else reader(ctx, node, *args)


def task_name(node: Node) -> str:
    """The name written in a task/group mapping (for messages), or ``""``."""
    name = node.get("name") if isinstance(node, Map) else None
    return name.value if isinstance(name, Scalar) and isinstance(name.value, str) else ""


def parse_task(ctx: Ctx, node: Node, local: LocalFiles) -> TaskSpec | None:
    """One task mapping → ``TaskSpec`` (None if it is not a mapping).

    A missing name is reported and kept as ``""`` so positions stay aligned; validation skips empty
    names.
    """
    label = task_name(node)
    where = f"task '{label}'" if label else "a task"
    fields = read_fields(ctx, node, TASK_KEYS, where, required=("name",))
    if fields is None:
        return None
    for key in fields:
        if f"task.{key}" in UNSUPPORTED:
            ctx.error(fields[key], f"{where}: {UNSUPPORTED['task.' + key]}")
    _typed_fields(ctx, fields, where)
    name = _optional(ctx, fields, "name", read_name, "task name")
    f = fields  # short alias: the constructor call below reads one field per line
    return TaskSpec(
        name=name or "",
        image=_optional(ctx, f, "image", _image, where),
        command=_command(ctx, f, node, where),
        args=_optional(ctx, f, "args", read_str_list, f"'args' of {where}") or (),
        environment=_optional(ctx, f, "environment", _environment, "environment variable")
        or {},
        files=_optional(ctx, f, "files", parse_files, local, where) or (),
        inputs=_optional(ctx, f, "inputs", parse_inputs, where) or (),
        outputs=_optional(ctx, f, "outputs", parse_outputs, where) or (),
        credentials=_optional(ctx, f, "credentials", _credentials, where) or {},
        resource=_optional(ctx, f, "resource", read_str, f"'resource' of {where}")
        or DEFAULT_RESOURCE,
        lead=bool(_optional(ctx, f, "lead", read_bool, f"'lead' of {where}")),
        exit_actions=_optional(ctx, f, "exitActions", _exit_actions, where) or (),
        checkpoint=_optional(ctx, f, "checkpoint", parse_checkpoint, where) or (),
        type=_optional(ctx, f, "type", read_str, f"'type' of {where}"),
        params=_params(ctx, f.get("params"), where),
        cache=_optional(ctx, f, "cache", read_bool, f"'cache' of {where}"),
        warm=_optional(ctx, f, "warm", read_bool, f"'warm' of {where}"),
        pos=node.pos,
    )


def _typed_fields(ctx: Ctx, fields: dict[str, Node], where: str) -> None:
    """``params`` and ``warm`` belong to a ``type``; ``args`` to a ``command``."""
    if "params" in fields and "type" not in fields:
        ctx.error(fields["params"], f"{where} has 'params' but no 'type'; params configure a "
                                    "task type (type: NAME), a command takes 'args'")
    if "args" in fields and "type" in fields:
        ctx.error(fields["args"], f"{where} has 'args' and 'type'; a task type takes 'params'")
    if "warm" in fields and "type" not in fields:
        ctx.error(fields["warm"], f"{where} has 'warm' but no 'type'; only a task type's "
                                  "attempts start from a warm runner")


def _params(ctx: Ctx, node: Node | None, where: str) -> dict[str, Any]:
    if node is None or read_map(ctx, node, f"'params' of {where}") is None:
        return {}
    return to_plain(node) if isinstance(node, Map) else {}
