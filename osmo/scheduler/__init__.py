"""The scheduler: a pure state machine ``handle(event, now) -> commands`` (no I/O).

Public names: :class:`Scheduler`, the persisted state records (:class:`TaskState`,
:class:`WorkflowState`) and the contract types of ``osmo.scheduler.types`` (events,
commands, ``Capacity``, ``Node``, ``Changes``, ``Transition``, ``attempt_id``). Every other
module of this package is private.
"""

from osmo.scheduler.core import Scheduler
from osmo.scheduler.state import TaskState, WorkflowState
from osmo.scheduler.types import (
    DEFAULT_MAX_RETRIES,
    LOCAL_NODE,
    PRIORITIES,
    AttemptExited,
    AttemptLost,
    AttemptPrepared,
    AttemptStarted,
    AttemptStartFailed,
    CancelWorkflow,
    Capacity,
    Changes,
    Command,
    Event,
    KillAttempt,
    Node,
    NodeDown,
    NodeUp,
    PrepareAttempt,
    RunAttempt,
    Tick,
    Transition,
    WorkflowSubmitted,
    attempt_id,
)

__all__ = [
    "DEFAULT_MAX_RETRIES",
    "LOCAL_NODE",
    "PRIORITIES",
    "AttemptExited",
    "AttemptLost",
    "AttemptPrepared",
    "AttemptStartFailed",
    "AttemptStarted",
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
    "Scheduler",
    "TaskState",
    "Tick",
    "Transition",
    "WorkflowState",
    "WorkflowSubmitted",
    "attempt_id",
]
