"""[ext] Checks of typed tasks (``type:`` + ``params:``) against their task types.

A spec is checked against task types only when the caller passes a :class:`TypeResolver`
(the CLI and SDK pass one built by ``osmo.tasktypes.registry``; the server its own). Without
one, ``type`` is a name and ``params`` any mapping: that is how stored specs are re-read.
The spec layer never imports the registry or the server: it only calls ``resolve``.

For each typed task: the type must resolve (its error is reported at the ``type:`` value);
every param must be declared by the type (with "did you mean"), of its type, within
``min``/``max`` and ``choices``; every required param must be given. The type's declared
``resources`` must use resource-spec keys. Each checked task gets a :class:`ResolvedType`.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Iterator, Mapping
from typing import Any, Protocol

from osmo.errors import OsmoError
from osmo.names import did_you_mean
from osmo.params import REQUIRED, type_label, value_problem
from osmo.spec.model import Pos, ResolvedType, ResourceSpec, TaskSpec, WorkflowSpec
from osmo.spec.parse import Parsed
from osmo.spec.reader import Ctx
from osmo.spec.units import parse_size
from osmo.spec.yamlnodes import Map, Node, to_plain

__all__ = ["TypeResolver", "apply_resolved", "check_types"]

_RESOURCE_KEYS = ("cpu", "gpu", "memory", "storage", "platform")


class TypeResolver(Protocol):
    """Finds a task type by the name a spec writes (``osmo.tasktypes.registry.Resolver``)."""

    def resolve(self, ref: str) -> Any:
        """The task type (see ``osmo.tasktypes.api.TaskType``).

        Raises ``OsmoError`` with a message saying what is wrong and how to fix it.
        """

    def paths_for(self, ref: str) -> tuple[str, ...]:
        """Folders the resolved type is imported from; empty for installed types.

        Recorded with the task, so the worker imports it from the same place.
        """


def _key_pos(node: Node, key: str) -> Pos | None:
    for k, _ in node.entries if isinstance(node, Map) else ():
        if k.text == key:
            return k.pos
    return None


def _value_pos(node: Node, key: str) -> Pos:
    value = node.get(key) if isinstance(node, Map) else None
    return (value or node).pos


def _typed_tasks(parsed: Parsed) -> Iterator[tuple[TaskSpec, Node]]:
    for gi, group in enumerate(parsed.spec.groups):
        for ti, task in enumerate(group.tasks):
            if task.type is not None:
                yield task, parsed.task_nodes[(gi, ti)]


def _check_params(ctx: Ctx, task: TaskSpec, node: Node, obj: Any) -> None:
    schema: Mapping[str, Any] = obj.params
    where, ref = f"task '{task.name}'", task.type
    params_node = node.get("params") if isinstance(node, Map) else None
    entries = params_node.entries if isinstance(params_node, Map) else []
    for key, value in entries:
        param = schema.get(key.text)
        if param is None:
            takes = f"it takes: {', '.join(schema)}" if schema else "it takes no params"
            ctx.error(key, f"{where}: unknown param '{key.text}' for type '{ref}'"
                           f"{did_you_mean(key.text, schema)}; {takes}")
            continue
        problem = value_problem(param, to_plain(value))
        if problem:
            ctx.error(value, f"param '{key.text}' of {where} {problem}")
    given = {k.text for k, _ in entries}
    pos = _key_pos(node, "params") or _value_pos(node, "type")
    for name, param in schema.items():
        if param.default is REQUIRED and name not in given:
            help_text = f": {param.help}" if param.help else ""
            ctx.error(pos, f"{where} needs param '{name}' ({type_label(param.type)}{help_text})"
                           f" for type '{ref}'; add it under 'params:'")


def _resources(ctx: Ctx, task: TaskSpec, node: Node, obj: Any) -> ResourceSpec | None:
    declared: Mapping[str, Any] = obj.resources
    if not declared:
        return None
    pos = _value_pos(node, "type")
    values: dict[str, Any] = {}
    for key, value in declared.items():
        try:
            if key not in _RESOURCE_KEYS:
                raise ValueError(f"unknown key '{key}'{did_you_mean(key, _RESOURCE_KEYS)}")
            if key in ("memory", "storage"):
                value = parse_size(value)
            elif key in ("cpu", "gpu") and (isinstance(value, bool) or not isinstance(value, int)):
                raise ValueError(f"'{key}' must be an integer, got {value!r}")
            values[key] = value
        except ValueError as exc:
            ctx.error(pos, f"type '{task.type}' of task '{task.name}' declares unusable "
                           f"resources: {exc}; fix the type's 'resources'")
    return ResourceSpec(**values)


def check_types(ctx: Ctx, parsed: Parsed, types: TypeResolver) -> dict[str, ResolvedType]:
    """Check every typed task; report problems into ``ctx``.

    Returns:
        task name → what was resolved, for the tasks whose type resolved.
    """
    out: dict[str, ResolvedType] = {}
    for task, node in _typed_tasks(parsed):
        ref = task.type or ""
        if not ref.strip():
            ctx.error(_value_pos(node, "type"), f"task '{task.name}' has an empty 'type'")
            continue
        try:
            obj = types.resolve(ref)
        except OsmoError as exc:
            ctx.error(_value_pos(node, "type"), f"task '{task.name}': {exc}")
            continue
        _check_params(ctx, task, node, obj)
        resources = _resources(ctx, task, node, obj)
        out[task.name] = ResolvedType(str(obj.version), resources, types.paths_for(ref))
    return out


def apply_resolved(spec: WorkflowSpec, resolved: Mapping[str, ResolvedType]) -> WorkflowSpec:
    """``spec`` with each named task's ``resolved`` set (tasks not named are unchanged)."""
    if not resolved:
        return spec
    groups = tuple(dataclasses.replace(g, tasks=tuple(
        dataclasses.replace(t, resolved=resolved[t.name]) if t.name in resolved else t
        for t in g.tasks)) for g in spec.groups)
    return dataclasses.replace(spec, groups=groups)
