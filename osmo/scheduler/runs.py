"""The scheduler's private bookkeeping for one workflow: groups, batches, queued requests.

This module owns the in-memory records the engine updates in O(affected) per event
(per-group counters, the barrier batch, placement requests) and the two pure aggregation
rules: a group's outcome from its tasks, and a workflow's status from its groups' outcomes.
Nothing here is persisted: it is rebuilt from ``TaskState``/``WorkflowState`` on restore.
"""

from __future__ import annotations

from collections.abc import Hashable, Iterable, Mapping
from dataclasses import dataclass, field

from osmo.graph import WorkflowGraph
from osmo.scheduler.resources import Request, requests_of
from osmo.scheduler.state import TaskState, WorkflowState
from osmo.spec.model import GroupSpec, TaskSpec, WorkflowSpec
from osmo.status import TaskStatus, WorkflowStatus

__all__ = ["Batch", "Group", "Queued", "Run", "group_outcome", "workflow_outcome"]

# Most significant first: a workflow's failure status is the first of these any group ended
# with. A group's outcome is likewise the most significant failure among the tasks that count.
_SIGNIFICANCE = (
    TaskStatus.FAILED_CANCELED,
    TaskStatus.FAILED_EXEC_TIMEOUT,
    TaskStatus.FAILED_QUEUE_TIMEOUT,
    TaskStatus.FAILED_SERVER_ERROR,
    TaskStatus.FAILED_UPSTREAM,
    TaskStatus.FAILED_START_ERROR,
)
_WORKFLOW_FAILURE = {
    TaskStatus.FAILED_CANCELED: WorkflowStatus.FAILED_CANCELED,
    TaskStatus.FAILED_EXEC_TIMEOUT: WorkflowStatus.FAILED_EXEC_TIMEOUT,
    TaskStatus.FAILED_QUEUE_TIMEOUT: WorkflowStatus.FAILED_QUEUE_TIMEOUT,
    TaskStatus.FAILED_SERVER_ERROR: WorkflowStatus.FAILED_SERVER_ERROR,
}


@dataclass(eq=False)
class Batch:
    """Tasks gang-placed together whose commands start together (the group barrier).

    ``members`` shrinks when a member leaves INITIALIZING without being released (it failed
    or was rescheduled), so the rest are not held forever.
    """

    members: list[str]
    released: bool = False


@dataclass(eq=False)
class Group:
    """Live bookkeeping of one group.

    Attributes:
        waiting_on: upstream groups not yet COMPLETED.
        closing: the group's end has been decided; no more placement or barrier release.
        outcome: COMPLETED or the group's failure status once ended.
        prepared: tasks whose current attempt reported AttemptPrepared.
        exec_deadline: when the group's exec timeout fires (set at its first RUNNING).
    """

    spec: GroupSpec
    index: int
    waiting_on: int
    closing: bool = False
    outcome: TaskStatus | None = None
    batch: Batch | None = None
    prepared: set[str] = field(default_factory=set)
    exec_deadline: float | None = None

    @property
    def name(self) -> str:
        """The group's name."""
        return self.spec.name


@dataclass(eq=False)
class Run:
    """Everything the engine tracks for one workflow."""

    spec: WorkflowSpec
    graph: WorkflowGraph
    state: WorkflowState
    seq: int
    max_retries: int
    groups: dict[str, Group]
    task_specs: dict[str, TaskSpec]
    requests: dict[str, Request]
    tasks: dict[str, TaskState] = field(default_factory=dict)
    open_groups: int = 0
    running: int = 0  # tasks RUNNING now
    active: int = 0  # tasks INITIALIZING or RUNNING now

    @property
    def id(self) -> str:
        """The workflow id."""
        return self.state.id

    @classmethod
    def build(cls, spec: WorkflowSpec, state: WorkflowState, seq: int,
              max_retries: int) -> Run:
        """Records for ``spec`` with no tasks yet (every group waiting on its upstream)."""
        graph = WorkflowGraph.from_spec(spec)
        groups = {g.name: Group(g, i, len(graph.upstream(g.name)))
                  for i, g in enumerate(spec.groups)}
        return cls(spec=spec, graph=graph, state=state, seq=seq, max_retries=max_retries,
                   groups=groups,
                   task_specs={t.name: t for t in spec.all_tasks()},
                   requests=requests_of(spec),
                   open_groups=len(groups))

    def group_of(self, task: TaskState) -> Group:
        """The live group record of ``task``."""
        return self.groups[task.group]


@dataclass(eq=False)
class Queued:
    """A request to place ``tasks`` (a whole group, or one retried task) all at once.

    ``retries`` pins the retry of each task: the request is stale as soon as any of them is
    no longer SCHEDULING at that retry.
    """

    run: Run
    group: Group
    tasks: tuple[str, ...]
    retries: tuple[int, ...]
    # priority then FIFO: priority_key, workflow submit order, group order, enqueue order
    key: tuple[float, int, int, int]
    shape: Hashable  # equal shapes fit or fail alike in one placement pass
    gang: bool
    since: float = 0.0  # when it started waiting (queue timeouts count from here)
    live: bool = True

    def valid(self) -> bool:
        """True while the request still waits to be placed."""
        if not self.live or self.group.closing:
            return False
        tasks = self.run.tasks
        return all(tasks[n].status is TaskStatus.SCHEDULING and tasks[n].retry == r
                   for n, r in zip(self.tasks, self.retries, strict=True))


def group_outcome(spec: GroupSpec, tasks: Mapping[str, TaskState]) -> TaskStatus:
    """The outcome of an ended group: COMPLETED, or its most significant failure.

    With ``ignore_nonlead_status`` only the lead counts; otherwise every task does.
    """
    if spec.ignore_nonlead_status:
        counted: Iterable[TaskState] = (tasks[spec.lead.name],)
    else:
        counted = (tasks[t.name] for t in spec.tasks)
    failed = {t.status for t in counted if t.status.failed}
    if not failed:
        return TaskStatus.COMPLETED
    for status in _SIGNIFICANCE:
        if status in failed:
            return status
    return TaskStatus.FAILED


def workflow_outcome(outcomes: Iterable[TaskStatus]) -> WorkflowStatus:
    """The terminal status of a workflow whose groups ended with ``outcomes``."""
    seen = set(outcomes)
    if seen <= {TaskStatus.COMPLETED}:
        return WorkflowStatus.COMPLETED
    for status in _SIGNIFICANCE:
        if status in seen and status in _WORKFLOW_FAILURE:
            return _WORKFLOW_FAILURE[status]
    return WorkflowStatus.FAILED
