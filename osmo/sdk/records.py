"""What the SDK returns: workflows, tasks, log lines and events, read from the API's replies."""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Any

from osmo.status import TaskStatus, WorkflowStatus

__all__ = ["EventInfo", "LogRecord", "TaskInfo", "TaskWaiting", "WorkflowInfo", "log_record",
           "task_info", "workflow_info"]


@dataclass(frozen=True)
class TaskWaiting:
    """Why a WAITING or SCHEDULING task waits (computed by the server's scheduler).

    Attributes:
        reason: e.g. ``pool 'gpu' has no online worker`` or ``needs 4 gpu, largest free is 2``.
        since: when that condition began, when known.
        fails_at: when the task fails if nothing changes (a queue timeout), when known.
    """

    reason: str
    since: float | None = None
    fails_at: float | None = None


@dataclass(frozen=True)
class TaskInfo:
    """One task of a workflow as the server sees it now (its latest retry)."""

    name: str
    group: str
    status: TaskStatus
    retry: int
    exit_code: int | None
    started_at: float | None
    ended_at: float | None
    output: str | None
    message: str
    reused: bool  # its outputs came from an earlier identical run (cache or restart)
    node: str | None = None  # where its latest attempt was placed ("local" or a worker)
    progress: str | None = None  # a running typed task's latest progress ("3/10 message")
    waiting: TaskWaiting | None = None  # why it waits: WAITING, SCHEDULING, or its pod/job held

    @property
    def duration(self) -> float | None:
        """Seconds from RUNNING to end (or until now while running)."""
        if self.started_at is None:
            return None
        return (self.ended_at or time.time()) - self.started_at


@dataclass(frozen=True)
class WorkflowInfo:
    """A workflow's status and its tasks."""

    id: str
    name: str
    status: WorkflowStatus
    submitted_at: float
    started_at: float | None
    ended_at: float | None
    pool: str | None
    tasks: list[TaskInfo] = field(default_factory=list)
    reused_from: str | None = None
    submitted_by: str | None = None  # the name of the token it was submitted with
    labels: dict[str, str] = field(default_factory=dict)
    tags: list[str] = field(default_factory=list)
    priority: str = "NORMAL"
    counts: dict[str, int] = field(default_factory=dict)  # status → tasks; asked with a limit
    matched: int | None = None  # tasks with the statuses asked for; None: all are in ``tasks``

    @property
    def not_shown(self) -> int:
        """How many tasks the query matched but left out of :attr:`tasks` (its ``limit``)."""
        return 0 if self.matched is None else self.matched - len(self.tasks)

    @property
    def ok(self) -> bool:
        """True iff the workflow COMPLETED."""
        return self.status is WorkflowStatus.COMPLETED

    def task(self, name: str) -> TaskInfo:
        """The task called ``name`` (KeyError if absent)."""
        for t in self.tasks:
            if t.name == name:
                return t
        raise KeyError(name)


@dataclass(frozen=True)
class LogRecord:
    """One log line: time, task, retry, stream (stdout/stderr/osmo) and text."""

    ts: float
    task: str | None
    retry: int | None
    stream: str
    text: str


@dataclass(frozen=True)
class EventInfo:
    """One scheduling event of a workflow (``task`` None) or of a task retry.

    Attributes:
        at: unix seconds.
        task: the task, None for the workflow's own events.
        retry: the task's retry.
        status: the status it entered.
        message: why (waiting, failed, retried...), "" when nothing was said.
        node: the node the retry's attempt was placed on (None until placed).
    """

    at: float
    task: str | None
    retry: int | None
    status: str
    message: str
    node: str | None


def task_info(d: dict[str, Any]) -> TaskInfo:
    """A task of a ``get`` reply."""
    return TaskInfo(d["name"], d.get("group", d["name"]), TaskStatus[d["status"]],
                    d.get("retry", 0), d.get("exit_code"), d.get("started_at"),
                    d.get("ended_at"), d.get("output"), d.get("message", ""),
                    bool(d.get("reused")), d.get("node_id"), d.get("progress"),
                    _waiting_of(d.get("waiting")))


def _waiting_of(d: Any) -> TaskWaiting | None:
    if not isinstance(d, dict) or not isinstance(d.get("reason"), str):
        return None
    since, fails_at = d.get("since"), d.get("fails_at")
    return TaskWaiting(d["reason"], float(since) if isinstance(since, (int, float)) else None,
                       float(fails_at) if isinstance(fails_at, (int, float)) else None)


def workflow_info(wf: dict[str, Any], tasks: list[dict[str, Any]] = (),  # type: ignore[assignment]
                  counts: dict[str, int] | None = None,
                  matched: int | None = None) -> WorkflowInfo:
    """A workflow of a ``get`` or ``list`` reply (with its tasks when given)."""
    return WorkflowInfo(wf["id"], wf["name"], WorkflowStatus[wf["status"]],
                        wf.get("submitted_at", 0.0), wf.get("started_at"), wf.get("ended_at"),
                        wf.get("pool"), [task_info(t) for t in tasks], wf.get("reused_from"),
                        wf.get("submitted_by"),
                        dict(wf.get("labels") or {}), list(wf.get("tags") or []),
                        wf.get("priority") or "NORMAL", dict(counts or {}), matched)


def log_record(r: dict[str, Any]) -> LogRecord:
    """A record of a ``logs`` reply."""
    return LogRecord(r["ts"], r.get("task"), r.get("retry"), r["stream"], r["text"])
