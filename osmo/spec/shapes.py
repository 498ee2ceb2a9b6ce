"""Bare tasks that differ only by their name, parsed once: the fast way for big fan-outs.

A spec given as data (``spec_from_dict``: the SDK's, a submitted one) is often a fan-out of
thousands of tasks written alike: ``{"name": "m17", "command": ["true"], "inputs": [...]}``.
Parsing a task reads nothing but its own mapping, and its name only for messages, so two tasks
whose mappings are equal but for the name parse to the same :class:`TaskSpec` but for the
name. :func:`reduce_tasks` keeps the first task of each such *shape* in ``workflow.tasks``;
after that smaller document is parsed, :func:`expand` puts every task back, each a copy of its
shape's task under its own name, so the whole-workflow checks (``validate``: names, inputs,
cycles, tokens) still see every task.

This is only a shortcut to the same model: it gives up (None) on anything unusual, and any
problem sends the caller back to the full check (``osmo.spec.loader.spec_from_dict``), which
reports every problem with its position. Tasks inside ``groups`` are not reduced: a group's
checks (its lead, its peers) read its tasks together.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Any, TypeVar

from osmo.names import name_problem
from osmo.spec.model import GroupSpec, TaskSpec
from osmo.spec.parse import Parsed
from osmo.spec.reader import Ctx

__all__ = ["Reduced", "expand", "reduce_tasks"]

_NAME = "name"
_Frozen = TypeVar("_Frozen", GroupSpec, TaskSpec)


@dataclass(frozen=True)
class Reduced:
    """A document with one task per shape, and how to put the others back.

    Attributes:
        data: the document to parse (``workflow.tasks`` holds one task per shape).
        plan: for every task of the original list, in order: (index of its shape's task in
            the reduced list, its own name).
    """

    data: dict[str, Any]
    plan: tuple[tuple[int, str], ...]


def reduce_tasks(data: dict[str, Any]) -> Reduced | None:
    """``data`` with repeated task shapes left out, or None when nothing would be saved.

    None too for anything this shortcut does not handle (no bare ``workflow.tasks`` list, a
    task that is not a mapping or whose name is not a string): the caller parses ``data``.
    """
    workflow = data.get("workflow")
    if not isinstance(workflow, dict):
        return None
    tasks = workflow.get("tasks")
    if not isinstance(tasks, list) or len(tasks) < 2:
        return None
    shapes: dict[str, int] = {}
    kept: list[dict[str, Any]] = []
    plan: list[tuple[int, str]] = []
    try:
        for task in tasks:
            if type(task) is not dict or type(task.get(_NAME)) is not str:
                return None
            # repr tells str from int, list from tuple, 1 from 1.0 and True: equal texts are
            # equal data; the name's place is kept (None), not its value
            shape = repr([None if k == _NAME else (k, v) for k, v in task.items()])
            index = shapes.setdefault(shape, len(kept))
            if index == len(kept):
                kept.append(task)
            plan.append((index, task[_NAME]))
    except RecursionError:  # nested deeper than repr goes; the full check refuses it
        return None
    if len(kept) == len(tasks):
        return None
    return Reduced({**data, "workflow": {**workflow, "tasks": kept}}, tuple(plan))


def expand(ctx: Ctx, parsed: Parsed, reduced: Reduced) -> None:
    """Put every task of the original list back into ``parsed`` (a parse of ``reduced.data``).

    A name that would not parse is reported into ``ctx`` (at its shape's task), so the caller
    takes the full way. ``parsed`` must hold no problem: one group per kept task.
    """
    kept = parsed.spec.groups
    groups: list[GroupSpec] = []
    nodes = {}
    for i, (index, name) in enumerate(reduced.plan):
        group, node = kept[index], parsed.task_nodes[(index, 0)]
        if group.name != name:
            problem = name_problem(name, "task name")
            if problem is not None:
                ctx.error(node, problem)
            # a bare task's group is named after it and holds only it
            group = _renamed(group, name=name, tasks=(_renamed(group.tasks[0], name=name),))
        groups.append(group)
        nodes[(i, 0)] = node
    parsed.spec = replace(parsed.spec, groups=tuple(groups))
    parsed.task_nodes = nodes


def _renamed(spec: _Frozen, **changes: Any) -> _Frozen:
    """A copy of a frozen model record with ``changes``; its other fields are shared.

    Ten times cheaper than ``dataclasses.replace`` (which runs ``__init__`` again): the fresh
    instance's ``__dict__`` is filled before anyone sees it. Every field is copied from
    ``spec``, so none can be missed.
    """
    new = object.__new__(type(spec))
    new.__dict__.update(spec.__dict__, **changes)
    return new
