"""The workflow model: frozen dataclasses that YAML and the Python builder both produce.

This module owns the *shape* of a validated workflow (OSMO spec version 2 plus osmo's
extensions). It holds no parsing, no I/O and no behaviour beyond small pure helpers. Source
positions (``pos``) are informational and excluded from equality, so a model built in Python
equals the same model loaded from YAML.

Units are normalised at load time: memory/storage in bytes, timeouts in seconds, exit-code
ranges as inclusive ``(low, high)`` pairs. ``files[].localpath`` is read at load time into
``contents`` (binary files become base64), so the model is self-contained.
"""

from __future__ import annotations

import enum
from dataclasses import dataclass, field
from functools import cached_property
from typing import Any

__all__ = [
    "DEFAULT_RESOURCE",
    "ExitAction",
    "ExitRule",
    "FileSpec",
    "GroupSpec",
    "InputSpec",
    "OutputSpec",
    "Pos",
    "ResolvedType",
    "ResourceSpec",
    "TaskSpec",
    "Timeouts",
    "TopologySpec",
    "WorkflowSpec",
]

DEFAULT_RESOURCE = "default"


@dataclass(frozen=True)
class Pos:
    """Where a node came from: file name, 1-based line and column."""

    file: str
    line: int
    col: int


def _pos() -> Any:
    return field(default=None, compare=False, repr=False)


class ExitAction(enum.Enum):
    """What an exit code means for a task's attempt."""

    COMPLETE = "COMPLETE"
    FAIL = "FAIL"
    RESCHEDULE = "RESCHEDULE"


@dataclass(frozen=True)
class ExitRule:
    """One ``exitActions`` entry: an action and its inclusive code ranges."""

    action: ExitAction
    ranges: tuple[tuple[int, int], ...]

    def matches(self, code: int) -> bool:
        """True if ``code`` falls in one of this rule's ranges."""
        return any(low <= code <= high for low, high in self.ranges)


@dataclass(frozen=True)
class TopologySpec:
    """A ``topology`` entry of a resource spec (recorded; placement hint)."""

    key: str
    group: str | None = None
    requirement_type: str | None = None


@dataclass(frozen=True)
class ResourceSpec:
    """A named resource request. ``None`` means "not requested"."""

    cpu: int | None = None
    gpu: int | None = None
    memory: int | None = None  # bytes
    storage: int | None = None  # bytes
    platform: str | None = None
    nodes_excluded: tuple[str, ...] = ()
    topology: tuple[TopologySpec, ...] = ()
    pos: Pos | None = _pos()


@dataclass(frozen=True)
class Timeouts:
    """Per-group timeouts in seconds (OSMO 6.4 semantics).

    ``exec_timeout`` runs from the group's first task RUNNING; ``queue_timeout`` from the
    group entering SCHEDULING until it is placed.
    """

    exec_timeout: float | None = None
    queue_timeout: float | None = None


@dataclass(frozen=True)
class FileSpec:
    """A file written into the task's private file root before its command starts."""

    path: str
    contents: str
    base64: bool = False
    pos: Pos | None = _pos()


@dataclass(frozen=True)
class InputSpec:
    """One ``inputs:`` entry. Exactly one of ``task``/``url``/``dataset`` is set.

    ``task`` is an upstream task name in this workflow; ``workflow`` is set when the entry
    was ``WORKFLOW_ID:NAME`` (another workflow's output).
    """

    task: str | None = None
    workflow: str | None = None
    url: str | None = None
    dataset: str | None = None  # [ext] NAME[:TAG_OR_VERSION]
    regex: str | None = None
    pos: Pos | None = _pos()


@dataclass(frozen=True)
class OutputSpec:
    """One ``outputs:`` entry: a ``url`` upload or an [ext] ``dataset`` version."""

    url: str | None = None
    dataset: str | None = None
    path: str | None = None
    regex: str | None = None
    metadata: dict[str, Any] | None = None
    pos: Pos | None = _pos()


@dataclass(frozen=True)
class ResolvedType:
    """[ext] What submit learned of a typed task's type; derived, never written in YAML.

    Attributes:
        version: the type's version (lineage shows ``type@version``; part of the cache key).
        resources: the type's default resources (used when the task names no resource other
            than ``default``), or None when it declares none.
        paths: folders a custom (``module:attr``) type is imported from (the workflow file's
            folder); the runner puts them on ``PYTHONPATH``.
    """

    version: str
    resources: ResourceSpec | None = None
    paths: tuple[str, ...] = ()

    def to_dict(self) -> dict[str, Any]:
        """Plain data for the store (``from_dict`` reads it back)."""
        res = self.resources
        return {"version": self.version, "paths": list(self.paths),
                "resources": None if res is None else {
                    "cpu": res.cpu, "gpu": res.gpu, "memory": res.memory,
                    "storage": res.storage, "platform": res.platform}}

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> ResolvedType:
        """Inverse of :meth:`to_dict`."""
        res = data.get("resources")
        return cls(str(data["version"]), None if res is None else ResourceSpec(**res),
                   tuple(data.get("paths") or ()))


@dataclass(frozen=True)
class TaskSpec:
    """One task. Either ``command`` (a process) or [ext] ``type`` (a plugin task type)."""

    name: str
    image: str | None = None
    command: tuple[str, ...] = ()
    args: tuple[str, ...] = ()
    environment: dict[str, str] = field(default_factory=dict)
    files: tuple[FileSpec, ...] = ()
    inputs: tuple[InputSpec, ...] = ()
    outputs: tuple[OutputSpec, ...] = ()
    credentials: dict[str, Any] = field(default_factory=dict)
    resource: str = DEFAULT_RESOURCE
    lead: bool = False
    exit_actions: tuple[ExitRule, ...] = ()
    checkpoint: tuple[dict[str, Any], ...] = ()
    type: str | None = None  # [ext]
    params: dict[str, Any] = field(default_factory=dict)  # [ext]
    cache: bool | None = None  # [ext] None: the default (``WorkflowSpec.reuses_by_default``)
    warm: bool | None = None  # [ext] False: never from a warm runner (None: the pool's choice)
    pos: Pos | None = _pos()
    resolved: ResolvedType | None = field(default=None, compare=False, repr=False)  # [ext]

    def upstream_tasks(self) -> tuple[str, ...]:
        """Names of same-workflow tasks this task takes as inputs, in list order."""
        return tuple(i.task for i in self.inputs if i.task is not None and i.workflow is None)

    def exit_action(self, code: int) -> ExitAction:
        """The action for ``code``: the first matching rule, else 0 → COMPLETE, other → FAIL."""
        for rule in self.exit_actions:
            if rule.matches(code):
                return rule.action
        return ExitAction.COMPLETE if code == 0 else ExitAction.FAIL


@dataclass(frozen=True)
class GroupSpec:
    """Co-scheduled tasks. A bare task in ``workflow.tasks`` is a one-task group of its name."""

    name: str
    tasks: tuple[TaskSpec, ...]
    barrier: bool = True
    ignore_nonlead_status: bool = True
    pos: Pos | None = _pos()

    @property
    def lead(self) -> TaskSpec:
        """The group's lead: the task marked ``lead: true``, or the only task."""
        for task in self.tasks:
            if task.lead:
                return task
        return self.tasks[0]


@dataclass(frozen=True)
class WorkflowSpec:
    """A whole validated workflow.

    Attributes:
        bare_tasks: True when written as ``workflow.tasks`` (each group has one task of the
            same name); kept so dumping reproduces the author's form.
        max_retries: [ext] ``workflow.maxRetries``: cap on RESCHEDULE retries per task
            (``None`` = the server's default, documented as 3).
        cache: [ext] ``workflow.cache``: whether its tasks may reuse an identical earlier
            success, for each task that does not say (``None``: the default).
    """

    name: str
    groups: tuple[GroupSpec, ...]
    bare_tasks: bool = True
    pool: str | None = None
    labels: dict[str, str] = field(default_factory=dict)
    timeout: Timeouts = Timeouts()
    resources: dict[str, ResourceSpec] = field(default_factory=dict)
    max_retries: int | None = None
    cache: bool | None = None
    pos: Pos | None = _pos()

    def all_tasks(self) -> tuple[TaskSpec, ...]:
        """Every task of every group, in spec order."""
        return tuple(t for g in self.groups for t in g.tasks)

    def task(self, name: str) -> TaskSpec:
        """The task called ``name``; KeyError if absent. O(1) after the first call."""
        return self._task_index[name]

    @cached_property
    def _task_index(self) -> dict[str, TaskSpec]:
        # cached_property writes the instance __dict__ directly, so it works on a frozen
        # dataclass and does not take part in equality.
        return {t.name: t for t in self.all_tasks()}

    def reuses_by_default(self, task: TaskSpec) -> bool:
        """[ext] Whether ``task`` reuses an identical earlier success when nobody says.

        Nobody: neither the task's nor the workflow's ``cache:``, nor the submission. True for
        a typed task and for a task whose output another task of this workflow takes as an
        input (a pipeline's data); False for a bare command task that feeds no other, which
        runs every time it is submitted, as in OSMO (its effect may be the point).
        """
        return task.type is not None or task.name in self._fed

    @cached_property
    def _fed(self) -> frozenset[str]:
        return frozenset(name for t in self.all_tasks() for name in t.upstream_tasks())

    def resource_for(self, task: TaskSpec) -> ResourceSpec:
        """The resource spec a task requests (an empty spec if the workflow defines none).

        Precedence: a ``resource:`` other than ``default`` named by the task, then its type's
        declared resources, then the workflow's ``default`` entry, then nothing specific.
        """
        if task.resource == DEFAULT_RESOURCE and task.resolved and task.resolved.resources:
            return task.resolved.resources
        return self.resources.get(task.resource, ResourceSpec())
