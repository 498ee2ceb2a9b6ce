"""Parsing of the document and ``workflow:`` mapping.

Name, pool, labels, timeouts, resources, groups and bare tasks. Produces a :class:`WorkflowSpec`
plus the task nodes that ``validate`` needs for positions. Per-task fields live in ``parse_task``;
cross-references in ``validate``.
"""

from __future__ import annotations

from dataclasses import dataclass, field

from osmo.spec.localfiles import LocalFiles
from osmo.spec.model import (
    GroupSpec,
    Pos,
    ResourceSpec,
    TaskSpec,
    Timeouts,
    TopologySpec,
    WorkflowSpec,
)
from osmo.spec.parse_task import parse_task, task_name
from osmo.spec.reader import (
    Ctx,
    is_empty,
    read_bool,
    read_fields,
    read_int,
    read_list,
    read_map,
    read_name,
    read_str,
    read_str_list,
    scalar_text,
)
from osmo.spec.units import parse_duration, parse_size
from osmo.spec.yamlnodes import Map, Node, Scalar

__all__ = ["Parsed", "parse_document"]

DOC_KEYS = ("version", "workflow", "default-values")
WORKFLOW_KEYS = ("name", "pool", "labels", "timeout", "resources", "tasks", "groups", "maxRetries",
                 "cache")
GROUP_KEYS = ("name", "tasks", "barrier", "ignoreNonleadStatus")
RESOURCE_KEYS = ("cpu", "gpu", "memory", "storage", "platform", "nodesExcluded", "topology")
TOPOLOGY_KEYS = ("key", "group", "requirementType")
TIMEOUT_KEYS = ("exec_timeout", "queue_timeout")
MAX_LABELS = 16


@dataclass
class Parsed:
    """A parsed workflow and what validation needs beyond the model.

    Attributes:
        task_nodes: ``(group index, task index)`` → the task's mapping node.
        has_resources: whether ``workflow.resources`` was written at all.
    """

    spec: WorkflowSpec
    task_nodes: dict[tuple[int, int], Node] = field(default_factory=dict)
    has_resources: bool = False


def _labels(ctx: Ctx, node: Node) -> dict[str, str]:
    entries = read_map(ctx, node, "'labels'") or []
    if len(entries) > MAX_LABELS:
        ctx.error(node, f"'labels' has {len(entries)} entries; at most {MAX_LABELS} are allowed")
    out = {}
    for key, value in entries:
        text = scalar_text(value)
        if not text:
            ctx.error(value, f"label '{key.text}' needs a non-empty value")
        else:
            out[key.text] = text
    return out


def _duration(ctx: Ctx, node: Node, what: str) -> int | None:
    try:
        return parse_duration(node.value if isinstance(node, Scalar) else node)
    except ValueError as exc:
        ctx.error(node, f"{what}: {exc}")
        return None


def _timeouts(ctx: Ctx, node: Node) -> Timeouts:
    fields = read_fields(ctx, node, TIMEOUT_KEYS, "'timeout'") or {}
    values = {k: _duration(ctx, v, f"timeout '{k}'") for k, v in fields.items()}
    return Timeouts(values.get("exec_timeout"), values.get("queue_timeout"))


def _size(ctx: Ctx, node: Node, what: str) -> int | None:
    try:
        return parse_size(node.value if isinstance(node, Scalar) else node)
    except ValueError as exc:
        ctx.error(node, f"{what}: {exc}")
        return None


def _topology(ctx: Ctx, node: Node, where: str) -> tuple[TopologySpec, ...]:
    out = []
    for item in read_list(ctx, node, f"'topology' of {where}"):
        fields = read_fields(ctx, item, TOPOLOGY_KEYS, f"a topology entry of {where}",
                             required=("key",))
        if not fields or "key" not in fields:
            continue
        values = {k: read_str(ctx, v, f"topology '{k}'") for k, v in fields.items()}
        out.append(TopologySpec(values["key"] or "", values.get("group"),
                                values.get("requirementType")))
    return tuple(out)


def _resource(ctx: Ctx, name: str, node: Node) -> ResourceSpec:
    where = f"resource '{name}'"
    f = read_fields(ctx, node, RESOURCE_KEYS, where) or {}
    return ResourceSpec(
        cpu=read_int(ctx, f["cpu"], f"'cpu' of {where}") if "cpu" in f else None,
        gpu=read_int(ctx, f["gpu"], f"'gpu' of {where}") if "gpu" in f else None,
        memory=_size(ctx, f["memory"], f"'memory' of {where}") if "memory" in f else None,
        storage=_size(ctx, f["storage"], f"'storage' of {where}") if "storage" in f else None,
        platform=read_str(ctx, f["platform"], f"'platform' of {where}") if "platform" in f
        else None,
        nodes_excluded=read_str_list(ctx, f["nodesExcluded"], f"'nodesExcluded' of {where}")
        if "nodesExcluded" in f else (),
        topology=_topology(ctx, f["topology"], where) if "topology" in f else (),
        pos=node.pos,
    )


def _resources(ctx: Ctx, node: Node) -> dict[str, ResourceSpec]:
    entries = read_map(ctx, node, "'resources'") or []
    return {key.text: _resource(ctx, key.text, value) for key, value in entries}


def _check_leads(ctx: Ctx, node: Node, name: str, tasks: list[tuple[TaskSpec, Node]]) -> None:
    leads = [n for t, n in tasks if t.lead]
    if len(tasks) > 1 and not leads:
        ctx.error(node, f"group '{name}' has {len(tasks)} tasks but no lead; mark exactly one "
                        "with 'lead: true'")
    for extra in leads[1:]:
        where = extra.get("lead") if isinstance(extra, Map) else None
        ctx.error(where or extra, f"group '{name}' has more than one lead; keep 'lead: true' "
                                  "on one task")


def _group(ctx: Ctx, node: Node, local: LocalFiles) -> tuple[GroupSpec, list[Node]] | None:
    label = task_name(node)
    where = f"group '{label}'" if label else "a group"
    fields = read_fields(ctx, node, GROUP_KEYS, where, required=("name", "tasks"))
    if fields is None:
        return None
    name = read_name(ctx, fields["name"], "group name") if "name" in fields else None
    items = read_list(ctx, fields["tasks"], f"'tasks' of {where}") if "tasks" in fields else []
    if "tasks" in fields and is_empty(fields["tasks"]):
        ctx.error(fields["tasks"], f"{where} has no tasks; add at least one")
    parsed = [(t, item) for item in items if (t := parse_task(ctx, item, local)) is not None]
    _check_leads(ctx, node, name or label, parsed)
    barrier = read_bool(ctx, fields["barrier"], "'barrier'") if "barrier" in fields else None
    ignore = fields.get("ignoreNonleadStatus")
    ignore_value = read_bool(ctx, ignore, "'ignoreNonleadStatus'") if ignore else None
    group = GroupSpec(name or "", tuple(t for t, _ in parsed), barrier is not False,
                      ignore_value is not False, pos=node.pos)
    return group, [n for _, n in parsed]


def _task_list(ctx: Ctx, fields: dict[str, Node], key: str) -> list[Node]:
    items = read_list(ctx, fields[key], f"'workflow.{key}'")
    if is_empty(fields[key]):
        ctx.error(fields[key], f"'workflow.{key}' is empty; add at least one")
    return items


def _body(ctx: Ctx, node: Node, fields: dict[str, Node], local: LocalFiles,
          ) -> tuple[list[GroupSpec], dict[tuple[int, int], Node], bool]:
    """Groups (or bare tasks as one-task groups), their task nodes, and ``bare_tasks``."""
    if "tasks" in fields and "groups" in fields:
        ctx.error(fields["groups"], "'workflow' has both 'tasks' and 'groups'; use one: bare "
                                    "tasks, or groups of tasks")
    elif "tasks" not in fields and "groups" not in fields:
        if not (ctx.hinted(node, "tasks") or ctx.hinted(node, "groups")):
            ctx.error(node, "'workflow' needs 'tasks' (a list of tasks) or 'groups'")
        return [], {}, True
    groups: list[GroupSpec] = []
    nodes: dict[tuple[int, int], Node] = {}
    if "tasks" in fields:
        for item in _task_list(ctx, fields, "tasks"):
            task = parse_task(ctx, item, local)
            if task is not None:
                nodes[(len(groups), 0)] = item
                groups.append(GroupSpec(task.name, (task,), pos=task.pos))
        return groups, nodes, True
    for item in _task_list(ctx, fields, "groups"):
        parsed = _group(ctx, item, local)
        if parsed is not None:
            nodes.update({(len(groups), i): n for i, n in enumerate(parsed[1])})
            groups.append(parsed[0])
    return groups, nodes, False


def _workflow(ctx: Ctx, node: Node, local: LocalFiles) -> Parsed | None:
    f = read_fields(ctx, node, WORKFLOW_KEYS, "'workflow'", required=("name",))
    if f is None:
        return None
    groups, nodes, bare = _body(ctx, node, f, local)
    spec = WorkflowSpec(
        name=(read_name(ctx, f["name"], "workflow name") if "name" in f else None) or "",
        groups=tuple(groups),
        bare_tasks=bare,
        pool=read_str(ctx, f["pool"], "'pool'") if "pool" in f else None,
        labels=_labels(ctx, f["labels"]) if "labels" in f else {},
        timeout=_timeouts(ctx, f["timeout"]) if "timeout" in f else Timeouts(),
        resources=_resources(ctx, f["resources"]) if "resources" in f else {},
        max_retries=read_int(ctx, f["maxRetries"], "'maxRetries'") if "maxRetries" in f else None,
        cache=read_bool(ctx, f["cache"], "'cache' of the workflow") if "cache" in f else None,
        pos=node.pos,
    )
    return Parsed(spec, nodes, "resources" in f)


def parse_document(ctx: Ctx, root: Node | None, local: LocalFiles) -> Parsed | None:
    """The whole document (``version``, ``workflow``, ``default-values``) → ``Parsed``.

    Returns None when there is no workflow to validate further (already reported).
    """
    if root is None:
        ctx.error(Pos(ctx.file, 1, 1), "the spec is empty; it needs a 'workflow:' mapping")
        return None
    fields = read_fields(ctx, root, DOC_KEYS, "the document", required=("workflow",))
    if fields is None:
        return None
    version = fields.get("version")
    if version is not None and not (isinstance(version, Scalar) and version.value == 2
                                    and not isinstance(version.value, bool)):
        ctx.error(version, "'version' must be 2 (the only spec version osmo reads)")
    if "default-values" in fields:
        read_map(ctx, fields["default-values"], "'default-values'")
    return _workflow(ctx, fields["workflow"], local) if "workflow" in fields else None
