"""Task types (plugins): the contract in ``osmo.tasktypes.api``; lookup and running live beside it."""

from osmo.tasktypes.api import REQUIRED, Param, TaskCancelled, TaskContext, TaskType, task_type

__all__ = ["REQUIRED", "Param", "TaskCancelled", "TaskContext", "TaskType", "task_type"]
