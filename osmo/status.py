"""Workflow and task statuses (OSMO names) and the orchestrator's own exit codes.

Shared by every layer; depends on nothing. Names and meanings follow OSMO's lifecycle page.
"""

from __future__ import annotations

import enum

__all__ = ["CACHED_MESSAGE", "PRIORITIES", "ExitCode", "TaskStatus", "WorkflowStatus",
           "reused_attempt"]

PRIORITIES = ("HIGH", "NORMAL", "LOW")
"""A workflow's priority (``submit --priority``), highest first; NORMAL by default."""

CACHED_MESSAGE = "cached: outputs of "
"""The message of a task completed from the cache, before the id of the attempt it reused."""


def reused_attempt(message: str) -> tuple[str, str, int] | None:
    """``(workflow id, task, retry)`` of the attempt a cached task's message names, else None."""
    if not message.startswith(CACHED_MESSAGE):
        return None
    parts = message[len(CACHED_MESSAGE):].rsplit(":", 2)
    if len(parts) != 3 or not parts[2].isdigit():
        return None
    return parts[0], parts[1], int(parts[2])


class TaskStatus(enum.Enum):
    """Status of one task (of its current retry)."""

    SUBMITTING = "SUBMITTING"
    WAITING = "WAITING"  # upstream groups not done
    PROCESSING = "PROCESSING"
    SCHEDULING = "SCHEDULING"  # ready, queued for resources
    INITIALIZING = "INITIALIZING"  # placed; inputs and files being prepared
    RUNNING = "RUNNING"
    COMPLETED = "COMPLETED"
    RESCHEDULED = "RESCHEDULED"  # this retry ended; a new retry follows
    FAILED = "FAILED"
    FAILED_UPSTREAM = "FAILED_UPSTREAM"
    FAILED_CANCELED = "FAILED_CANCELED"
    FAILED_EXEC_TIMEOUT = "FAILED_EXEC_TIMEOUT"
    FAILED_QUEUE_TIMEOUT = "FAILED_QUEUE_TIMEOUT"
    FAILED_START_ERROR = "FAILED_START_ERROR"
    FAILED_SERVER_ERROR = "FAILED_SERVER_ERROR"

    @property
    def terminal(self) -> bool:
        """True once nothing more will happen to this task (RESCHEDULED is not terminal)."""
        return self is TaskStatus.COMPLETED or self.name.startswith("FAILED")

    @property
    def failed(self) -> bool:
        """True for every FAILED_* status."""
        return self.name.startswith("FAILED")

    @property
    def active(self) -> bool:
        """True while an attempt holds resources (placed, preparing or running)."""
        return self in (TaskStatus.INITIALIZING, TaskStatus.RUNNING)


class WorkflowStatus(enum.Enum):
    """Status of a workflow; a failure aggregates only after every group has ended."""

    PENDING = "PENDING"
    RUNNING = "RUNNING"
    WAITING = "WAITING"  # started, nothing running right now
    COMPLETED = "COMPLETED"
    FAILED = "FAILED"
    FAILED_SUBMISSION = "FAILED_SUBMISSION"
    FAILED_SERVER_ERROR = "FAILED_SERVER_ERROR"
    FAILED_EXEC_TIMEOUT = "FAILED_EXEC_TIMEOUT"
    FAILED_QUEUE_TIMEOUT = "FAILED_QUEUE_TIMEOUT"
    FAILED_CANCELED = "FAILED_CANCELED"

    @property
    def terminal(self) -> bool:
        """True for COMPLETED and every FAILED_* status."""
        return self is WorkflowStatus.COMPLETED or self.name.startswith("FAILED")


class ExitCode:
    """Exit codes osmo records for a task when the user's command did not provide one.

    1–255 are the user's command; 3000+ are the orchestrator's own bands.
    """

    UPSTREAM_FAILED = 3000
    CANCELED = 3001
    EXEC_TIMEOUT = 3002
    QUEUE_TIMEOUT = 3003
    START_ERROR = 3004  # could not prepare inputs/files or spawn the command
    OUTPUT_ERROR = 3005  # outputs could not be promoted
    LOST = 3006  # the worker or server running the attempt went away
    STOPPED = 3007  # a non-lead stopped because its group's lead finished
