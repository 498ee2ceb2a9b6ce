"""Typed inputs and outputs of the scheduler: resources, nodes, events, commands, changes.

The scheduler is a pure state machine: ``Scheduler.handle(event, now) -> list[Command]``.
Events are facts that happened (a submit, an attempt exited, a clock tick); commands are
side effects the shell around it must perform (prepare, run or kill an attempt). State
changes to persist are taken with ``Scheduler.take_changes()`` after each batch of events and
committed *before* the commands are executed.

Attempt ids are derived, never random: ``"<workflow_id>:<task>:<retry>"``. A report for an
attempt id that is not the task's current attempt is ignored (fencing).
"""

from __future__ import annotations

import re
from dataclasses import dataclass, field

from osmo.scheduler.state import TaskState, WorkflowState
from osmo.spec.model import WorkflowSpec
from osmo.status import PRIORITIES

__all__ = [
    "AttemptExited",
    "AttemptLost",
    "AttemptPrepared",
    "AttemptStarted",
    "AttemptStartFailed",
    "AttemptWaiting",
    "DEFAULT_MAX_RETRIES",
    "DEFAULT_NO_WORKER_TIMEOUT",
    "LOCAL_NODE",
    "MAX_WAIT_REASON",
    "PRIORITIES",
    "PRIORITY_AGEING",
    "CancelWorkflow",
    "Capacity",
    "Changes",
    "Command",
    "Event",
    "KillAttempt",
    "Node",
    "NodeDown",
    "NodeUp",
    "PrepareAttempt",
    "RunAttempt",
    "Tick",
    "Transition",
    "Waiting",
    "WorkflowSubmitted",
    "attempt_id",
    "priority_key",
    "wait_reason",
]


DEFAULT_MAX_RETRIES = 3
"""How many times a task that exits with a RESCHEDULE action is retried, unless its workflow's
``maxRetries`` says otherwise."""

PRIORITY_AGEING = 600.0
"""Seconds of waiting that make up one priority level (the ageing rule).

Waiting requests are placed in order of ``submitted_at + level * PRIORITY_AGEING`` (HIGH
level 0, NORMAL 1, LOW 2), ties in submit order. So a HIGH workflow goes before NORMAL and
LOW ones submitted up to 10 (20) minutes earlier, and a LOW one is never overtaken by work
submitted more than 20 minutes after it: nothing starves."""


def priority_key(priority: str, submitted_at: float) -> float:
    """Where a request of a workflow with ``priority`` submitted at ``submitted_at`` queues."""
    return submitted_at + PRIORITIES.index(priority) * PRIORITY_AGEING

DEFAULT_NO_WORKER_TIMEOUT = 1800.0
"""Seconds a task waits on a pool with no online worker before it fails as
FAILED_QUEUE_TIMEOUT, unless its workflow names a ``queue_timeout`` (which then applies
instead). Counted from the later of: the task started waiting, the pool lost its last worker."""

LOCAL_NODE = "local"
"""The node id of the server's own pool (a remote worker may not call itself so)."""


def attempt_id(workflow_id: str, task: str, retry: int) -> str:
    """The id of retry ``retry`` of ``task`` in ``workflow_id``."""
    return f"{workflow_id}:{task}:{retry}"


@dataclass(frozen=True)
class Capacity:
    """An amount of resources (a request or a node's total). Memory and storage in bytes."""

    cpu: float = 0.0
    gpu: int = 0
    memory: int = 0
    storage: int = 0

    def fits_in(self, other: Capacity) -> bool:
        """True if this amount is ≤ ``other`` in every dimension."""
        return (
            self.cpu <= other.cpu + 1e-9
            and self.gpu <= other.gpu
            and self.memory <= other.memory
            and self.storage <= other.storage
        )

    def __add__(self, other: Capacity) -> Capacity:
        return Capacity(
            self.cpu + other.cpu,
            self.gpu + other.gpu,
            self.memory + other.memory,
            self.storage + other.storage,
        )

    def __sub__(self, other: Capacity) -> Capacity:
        return Capacity(
            self.cpu - other.cpu,
            self.gpu - other.gpu,
            self.memory - other.memory,
            self.storage - other.storage,
        )


@dataclass(frozen=True)
class Waiting:
    """Why a task has not started yet (``Scheduler.waiting``).

    Attributes:
        reason: what it waits for, e.g. ``pool 'gpu' has no online worker`` or ``needs 4
            gpu, largest free is 2``.
        since: when that condition began, when known (a pool's last worker left).
        fails_at: when the task fails if nothing changes (a queue timeout), when known.
    """

    reason: str
    since: float | None = None
    fails_at: float | None = None


@dataclass(frozen=True)
class Node:
    """A place tasks can run: the local pool's host, or (later) one remote worker.

    Attributes:
        id: unique node id (:data:`LOCAL_NODE` for the server's own pool).
        pool: the pool this node belongs to.
        capacity: total resources it offers.
        platform: platform name (matched against a resource spec's ``platform``).
        address: where its tasks can be reached by peers (``{{host:task}}``).
        platforms: every platform the node serves, each with what it offers tasks that ask
            for it (a cluster node's gpu nodes and cpu nodes): a task with ``platform: X``
            fits only within X's capacity (and the node's). Empty: it serves ``platform``
            (if any) with its whole capacity, as a worker from before this field does.
    """

    id: str
    pool: str
    capacity: Capacity
    platform: str | None = None
    address: str = "127.0.0.1"
    labels: dict[str, str] = field(default_factory=dict)
    platforms: dict[str, Capacity] = field(default_factory=dict)

    def offers(self, platform: str | None) -> Capacity | None:
        """What the node offers a task asking for ``platform`` (None: it does not serve it)."""
        if platform is None:
            return self.capacity
        found = self.platforms.get(platform)
        if found is not None:
            return found
        return self.capacity if platform == self.platform else None

    def served(self) -> list[str]:
        """The platforms it serves, sorted."""
        return sorted(self.platforms or ([self.platform] if self.platform else []))


# ---------------------------------------------------------------- events (facts, inputs)


@dataclass(frozen=True)
class WorkflowSubmitted:
    """A validated workflow was accepted.

    Attributes:
        reused: task name → output reference of an earlier successful attempt to reuse
            instead of running (``osmo restart``); such tasks complete at once.
        max_retries: the RESCHEDULE cap for this workflow (spec's value or server default).
        pool: the target pool (``--pool`` or ``workflow.pool``); ``None`` = any pool.
        priority: one of :data:`PRIORITIES` (see :data:`PRIORITY_AGEING`).
    """

    workflow_id: str
    spec: WorkflowSpec
    max_retries: int = DEFAULT_MAX_RETRIES
    pool: str | None = None
    reused: dict[str, str] = field(default_factory=dict)
    priority: str = "NORMAL"


@dataclass(frozen=True)
class AttemptPrepared:
    """The worker finished INITIALIZING an attempt (private folder, files, inputs ready)."""

    attempt_id: str


@dataclass(frozen=True)
class AttemptStarted:
    """The attempt's command (process) is running.

    Attributes:
        pid: the process (group) id when it runs as a process of the server's own host (the
            local pool), with ``pid_start`` its start time: the scheduler ignores both, the
            server records them so that a restarted server can kill what is left over.
    """

    attempt_id: str
    pid: int | None = None
    pid_start: float | None = None


@dataclass(frozen=True)
class AttemptExited:
    """The attempt's command ended.

    Attributes:
        exit_code: the command's code (128+N when killed by signal N).
        output: reference to the promoted output folder when the outputs were promoted
            (only after a COMPLETE exit), else ``None``.
        message: optional detail (e.g. why outputs could not be promoted).
        manifest: JSON of the promoted output's manifest (``osmo.artifacts.Manifest``)
            when the worker ingested it into the artifact store; the scheduler ignores it,
            the server records it with the attempt's lineage.
    """

    attempt_id: str
    exit_code: int
    output: str | None = None
    message: str = ""
    manifest: str | None = None
    cached: bool = False  # the outputs are an earlier identical attempt's (no process ran)
    command: tuple[str, ...] | None = None  # the argv that ran, tokens resolved (lineage)
    image_id: str | None = None  # the id of the image it ran in (a container task; lineage)


@dataclass(frozen=True)
class AttemptStartFailed:
    """Preparing or spawning the attempt failed (bad command, unwritable file...)."""

    attempt_id: str
    message: str


@dataclass(frozen=True)
class AttemptLost:
    """The attempt's worker (or the server that ran it) went away; outcome unknown.

    Attributes:
        server_restart: the attempt died with the server that ran it (a crash of the
            server, not of the task): if its command had not started yet (INITIALIZING),
            the loss is not counted against the lost-attempt cap.
    """

    attempt_id: str
    message: str = "worker lost"
    server_restart: bool = False


MAX_WAIT_REASON = 300
"""Characters of a waiting reason kept (:func:`wait_reason`); the rest is cut."""

_UNPRINTABLE = re.compile(r"[\x00-\x1f\x7f-\x9f\u2028\u2029\u200b-\u200f\u202a-\u202e"
                          r"\u2066-\u2069\ufeff]+")


def wait_reason(text: object) -> str:
    """A node's waiting reason as osmo keeps and shows it: one line of plain text.

    It is a cluster's (or a hostile worker's) text: control, format and bidirectional
    characters become spaces, runs of white space one space, and it is cut to
    :data:`MAX_WAIT_REASON` characters (``...`` marks a cut).
    """
    line = " ".join(_UNPRINTABLE.sub(" ", str(text)[:4 * MAX_WAIT_REASON]).split())
    return line if len(line) <= MAX_WAIT_REASON else line[:MAX_WAIT_REASON - 3] + "..."


@dataclass(frozen=True)
class AttemptWaiting:
    """A node says why a placed attempt waits on its cluster's scheduler, or that it no longer does.

    A Kubernetes pod Pending (``0/2 nodes are available: 2 Insufficient cpu.``) or a Slurm
    job PENDING (``Resources``): the attempt holds its place, and ``osmo query`` and
    ``osmo events`` say why it has not started. Fenced like every report.

    Attributes:
        reason: why it waits (cleaned by :func:`wait_reason`); empty: it waits no more.
    """

    attempt_id: str
    reason: str = ""


@dataclass(frozen=True)
class CancelWorkflow:
    """A user asked to cancel a workflow."""

    workflow_id: str


@dataclass(frozen=True)
class NodeUp:
    """A node joined (or changed capacity)."""

    node: Node


@dataclass(frozen=True)
class NodeDown:
    """A node left; its active attempts are lost."""

    node_id: str


@dataclass(frozen=True)
class Tick:
    """Time passed; lets timeouts fire. Carries nothing: ``now`` comes with every event."""


Event = (
    WorkflowSubmitted
    | AttemptPrepared
    | AttemptStarted
    | AttemptExited
    | AttemptStartFailed
    | AttemptLost
    | AttemptWaiting
    | CancelWorkflow
    | NodeUp
    | NodeDown
    | Tick
)

# ---------------------------------------------------------------- commands (side effects)


@dataclass(frozen=True)
class PrepareAttempt:
    """Place an attempt on a node and prepare it (status INITIALIZING).

    Attributes:
        inputs: upstream task name → output reference, for every ``- task:`` input.
        hosts: task name → address, for every task of the same group (``{{host:x}}``).
        run: True when no barrier holds this attempt: the worker starts the command as
            soon as it is prepared and no ``RunAttempt`` follows (saves a round trip per
            task). False: wait for ``RunAttempt`` (the group's barrier).
    """

    attempt_id: str
    workflow_id: str
    task: str
    retry: int
    node_id: str
    inputs: dict[str, str]
    hosts: dict[str, str]
    run: bool = False


@dataclass(frozen=True)
class RunAttempt:
    """Start a prepared attempt's command (the group's barrier, if any, is released)."""

    attempt_id: str
    node_id: str


@dataclass(frozen=True)
class KillAttempt:
    """Stop an attempt (its whole process group). Its exit report is still expected."""

    attempt_id: str
    node_id: str
    reason: str


Command = PrepareAttempt | RunAttempt | KillAttempt
"""Every command names the node its attempt was placed on: its executor is found by it."""

# ---------------------------------------------------------------- changes (to persist)


@dataclass(frozen=True)
class Transition:
    """One status change, for the event log, ``osmo logs`` [osmo] lines and the run record."""

    at: float
    workflow_id: str
    task: str | None  # None: a workflow-level transition
    retry: int | None
    status: str  # a TaskStatus or WorkflowStatus name
    message: str = ""


@dataclass
class Changes:
    """What changed since the last ``take_changes()``: snapshots to upsert, transitions to log.

    ``workflows``/``tasks`` hold the *current* snapshot of each changed workflow and task
    (see ``osmo.scheduler.state``); the store writes them and appends ``transitions``.
    """

    workflows: list[WorkflowState] = field(default_factory=list)
    tasks: list[TaskState] = field(default_factory=list)
    transitions: list[Transition] = field(default_factory=list)

    def __bool__(self) -> bool:
        return bool(self.workflows or self.tasks or self.transitions)
