"""Task types (plugins): the contract is ``osmo.tasktypes.api``; lookup and running beside it."""

from osmo.tasktypes.api import REQUIRED, Param, TaskCancelled, TaskContext, TaskType, task_type

__all__ = ["REQUIRED", "Param", "TaskCancelled", "TaskContext", "TaskType", "task_type"]
