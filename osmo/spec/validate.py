"""Whole-workflow checks on a parsed spec: names, resources, inputs, cycles and special tokens.

Rules (documented for users):

- Task and group names share one namespace, unique ignoring case and treating ``-``/``_`` as
  equal. In the bare-tasks form a task's one-task group shares its name, which is fine.
- Resources: if ``workflow.resources`` is written, a task without ``resource:`` uses
  ``default``, and a missing ``default`` entry is an error at that task (unless its task
  type declares resources, which then apply; see ``WorkflowSpec.resource_for``; loaded
  without a type resolver, a typed task's missing ``default`` is not checked, as its
  ``params`` are not); a ``resource:`` naming an unknown entry is an error. Without
  ``workflow.resources`` tasks request nothing specific (``ResourceSpec()``: the pool's
  defaults apply), and only ``resource: default`` may be written.
- ``- task: X`` must name another task of the workflow, not the task itself and not a task of
  the same group (a group's tasks start together, so waiting for a peer would deadlock).
- The groups, linked by their inputs, must form a DAG; a cycle is reported once, by name.
- ``{{input:N}}`` needs N < the number of the task's inputs; ``{{input:NAME}}`` must name one
  of its task inputs; ``{{host:NAME}}`` must name a task of the same group.

Reports into a :class:`Ctx`; never raises and never changes the model.
"""

from __future__ import annotations

from collections.abc import Iterator

from osmo.names import did_you_mean
from osmo.spec.model import DEFAULT_RESOURCE, GroupSpec, Pos, TaskSpec
from osmo.spec.parse import Parsed
from osmo.spec.reader import Ctx
from osmo.spec.tokens import find_tokens
from osmo.spec.yamlnodes import Map, Node, Scalar, Seq

__all__ = ["validate"]

Where = tuple[int, int]  # (group index, task index)


def _key(name: str) -> str:
    return name.lower().replace("_", "-")


def _tasks(parsed: Parsed) -> Iterator[tuple[Where, GroupSpec, TaskSpec, Node]]:
    for gi, group in enumerate(parsed.spec.groups):
        for ti, task in enumerate(group.tasks):
            yield (gi, ti), group, task, parsed.task_nodes[(gi, ti)]


def _field_pos(node: Node, key: str) -> Pos:
    value = node.get(key) if isinstance(node, Map) else None
    return (value or node).pos


def _names(ctx: Ctx, parsed: Parsed) -> dict[str, Where]:
    """Check the shared namespace; return each task's exact name → where it is."""
    seen: dict[str, tuple[str, str, Pos | Node]] = {}
    index: dict[str, Where] = {}

    def claim(kind: str, name: str, where: Pos | Node) -> None:
        if not name:
            return
        key = _key(name)
        first = seen.get(key)
        if first is None:
            seen[key] = (kind, name, where)
            return
        line = _pos_of(first[2]).line
        ctx.error(_pos_of(where), f"duplicate name: {kind} '{name}' clashes with {first[0]} "
                  f"'{first[1]}' at line {line} (names are compared ignoring case, with '-' "
                  "and '_' equal); rename one")

    for gi, group in enumerate(parsed.spec.groups):
        if not parsed.spec.bare_tasks and group.pos is not None:
            claim("group", group.name, group.pos)
        for ti, task in enumerate(group.tasks):
            claim("task", task.name, parsed.task_nodes[(gi, ti)])
            index.setdefault(task.name, (gi, ti))
    return index


def _pos_of(where: Pos | Node) -> Pos:
    """A position, or that of a task node's name (looked up only when needed: it costs)."""
    return _field_pos(where, "name") if isinstance(where, Node) else where


def _resources(ctx: Ctx, parsed: Parsed) -> None:
    defined = parsed.spec.resources
    for _, _, task, node in _tasks(parsed):
        if task.resource in defined or (not parsed.has_resources
                                        and task.resource == DEFAULT_RESOURCE):
            continue  # fine, whether written or not (most tasks: checked first, cheaply)
        explicit = isinstance(node, Map) and node.get("resource") is not None
        where = f"task '{task.name}'"
        if not parsed.has_resources:
            if explicit and task.resource != DEFAULT_RESOURCE:
                ctx.error(_field_pos(node, "resource"), f"{where} asks for resource "
                          f"'{task.resource}' but the workflow has no 'resources' section")
        elif task.resource not in defined and explicit:
            ctx.error(_field_pos(node, "resource"), f"resource '{task.resource}' of {where} is "
                      f"not in 'workflow.resources'{did_you_mean(task.resource, defined)}")
        elif task.type is not None and task.resolved is None:
            continue  # its type's resources are unknown without a resolver (not checked)
        elif task.resource not in defined and not (task.resolved and task.resolved.resources):
            ctx.error(node, f"{where} has no 'resource:' and 'workflow.resources' has no "
                            "'default' entry; add 'resource: NAME' or a 'default' resource")


def _inputs(ctx: Ctx, parsed: Parsed, index: dict[str, Where]) -> dict[tuple[int, int], Pos]:
    """Check task inputs; return the group edges ``(upstream, downstream)`` → an input's pos."""
    edges: dict[tuple[int, int], Pos] = {}
    for (gi, _), group, task, node in _tasks(parsed):
        for entry in task.inputs:
            if entry.task is None or entry.workflow is not None:
                continue
            pos = entry.pos or node.pos
            target = index.get(entry.task)
            if entry.task == task.name:
                ctx.error(pos, f"task '{task.name}' takes its own output as input; remove it")
            elif target is None:
                hint = did_you_mean(entry.task, index)
                ctx.error(pos, f"input task '{entry.task}' of task '{task.name}' is not a task "
                               f"of this workflow{hint}")
            elif target[0] == gi:
                ctx.error(pos, f"task '{task.name}' takes input from '{entry.task}' of its own "
                               f"group '{group.name}'; tasks of a group start together, so it "
                               "would wait forever: move one to another group, or use "
                               f"{{{{host:{entry.task}}}}} to talk to it")
            else:
                edges.setdefault((target[0], gi), pos)
    return edges


def _acyclic(count: int, edges: dict[tuple[int, int], Pos]) -> bool:
    """True if the groups form no cycle (Kahn's sort: cheaper than finding components)."""
    waits = [0] * count
    out: list[list[int]] = [[] for _ in range(count)]
    for u, v in edges:
        out[u].append(v)
        waits[v] += 1
    ready = [n for n in range(count) if not waits[n]]
    done = 0
    while ready:
        done += 1
        for v in out[ready.pop()]:
            waits[v] -= 1
            if not waits[v]:
                ready.append(v)
    return done == count


def _components(count: int, edges: dict[tuple[int, int], Pos]) -> list[list[int]]:
    """Strongly connected components (Kosaraju, iterative: specs may be long chains)."""
    out: dict[int, list[int]] = {n: [] for n in range(count)}
    back: dict[int, list[int]] = {n: [] for n in range(count)}
    for u, v in edges:
        out[u].append(v)
        back[v].append(u)
    order: list[int] = []
    seen: set[int] = set()
    for root in range(count):
        stack = [(root, iter(out[root]))] if root not in seen else []
        seen.add(root)
        while stack:
            node, children = stack[-1]
            child = next((c for c in children if c not in seen), None)
            if child is None:
                order.append(node)
                stack.pop()
            else:
                seen.add(child)
                stack.append((child, iter(out[child])))
    assigned: set[int] = set()
    components = []
    for root in reversed(order):
        if root in assigned:
            continue
        component, todo = [], [root]
        assigned.add(root)
        while todo:
            node = todo.pop()
            component.append(node)
            for prev in back[node]:
                if prev not in assigned:
                    assigned.add(prev)
                    todo.append(prev)
        components.append(sorted(component))
    return components


def _cycle_path(start: int, members: set[int], edges: dict[tuple[int, int], Pos]) -> list[int]:
    """A shortest cycle through ``start`` within one component: ``[start, ..., last]``."""
    out: dict[int, list[int]] = {}
    for a, b in edges:
        if a in members and b in members:
            out.setdefault(a, []).append(b)
    parents: dict[int, int] = {start: start}
    frontier = [start]
    while frontier:
        nxt = []
        for u in frontier:
            for v in out.get(u, []):
                if v == start:
                    path = [u]
                    while path[-1] != start:
                        path.append(parents[path[-1]])
                    return path[::-1]
                if v not in parents:
                    parents[v] = u
                    nxt.append(v)
        frontier = nxt
    return [start]


def _cycles(ctx: Ctx, parsed: Parsed, edges: dict[tuple[int, int], Pos]) -> None:
    groups = parsed.spec.groups
    if _acyclic(len(groups), edges):
        return
    for component in _components(len(groups), edges):
        if len(component) < 2:
            continue
        path = _cycle_path(component[0], set(component), edges)
        names = [groups[i].name for i in [*path, path[0]]]
        if len(names) > 12:  # keep the message readable
            names = [*names[:5], f"... ({len(path) - 8} more)", *names[-4:]]
        kind = "cycle" if parsed.spec.bare_tasks else "cycle between groups"
        what = "task" if parsed.spec.bare_tasks else "group"
        ctx.error(edges[(path[-1], path[0])], f"{kind}: {' -> '.join(names)}; a {what} "
                                              "cannot wait for itself: remove one of these inputs")


def _strings(task: TaskSpec, node: Node) -> Iterator[tuple[str, Pos]]:
    """Every string of the task that may hold special tokens, with its position."""
    if isinstance(node, Map):
        for key in ("command", "args"):
            value = node.get(key)
            items = value.items if isinstance(value, Seq) else []
            yield from ((n.value, n.pos) for n in items if isinstance(n, Scalar)
                        and isinstance(n.value, str))
        env = node.get("environment")
        for _, value in env.entries if isinstance(env, Map) else []:
            if isinstance(value, Scalar) and isinstance(value.value, str):
                yield value.value, value.pos
    for spec in task.files:
        if not spec.base64 and spec.pos is not None:
            yield spec.contents, spec.pos


def _token_problem(token: str, task: TaskSpec, group: GroupSpec) -> str | None:
    kind, _, arg = token.partition(":")
    if kind == "input" and arg.isdigit():
        if int(arg) < len(task.inputs):
            return None
        return (f"refers to input {arg}, but task '{task.name}' has {len(task.inputs)} "
                "input(s), numbered from 0")
    if kind == "input":
        names = [i.task for i in task.inputs if i.task] + [
            f"{i.workflow}:{i.task}" for i in task.inputs if i.task and i.workflow]
        if arg in names:
            return None
        return (f"'{arg}' is not one of the task inputs of task '{task.name}'"
                f"{did_you_mean(arg, names)}; add '- task: {arg}' to its inputs")
    if kind == "host":
        peers = [t.name for t in group.tasks]
        if arg in peers:
            return None
        return (f"'{arg}' is not a task of group '{group.name}'{did_you_mean(arg, peers)}; "
                "a task can reach only tasks of its own group")
    return None


def _tokens(ctx: Ctx, parsed: Parsed) -> None:
    # tasks written alike share their node and files (osmo.spec.shapes): their strings are
    # read once; most hold no token at all
    marked: dict[tuple[int, int], list[tuple[str, Pos]]] = {}
    for _, group, task, node in _tasks(parsed):
        key = (id(node), id(task.files))
        found = marked.get(key)
        if found is None:
            found = marked[key] = [(t, p) for t, p in _strings(task, node) if "{{" in t]
        for text, pos in found:
            for token in dict.fromkeys(find_tokens(text)):
                problem = _token_problem(token, task, group)
                if problem:
                    ctx.error(pos, f"{{{{{token}}}}}: {problem}")


def validate(ctx: Ctx, parsed: Parsed) -> None:
    """Run every whole-workflow check, reporting problems into ``ctx``."""
    index = _names(ctx, parsed)
    _resources(ctx, parsed)
    edges = _inputs(ctx, parsed, index)
    _cycles(ctx, parsed, edges)
    _tokens(ctx, parsed)
