"""osmo: a workflow orchestrator for robotics and physical-AI pipelines.

The public API is what ``__all__`` lists (a test checks it). Names load lazily, so
``import osmo`` imports no transport, template engine or simulator::

    import osmo

    wf = osmo.Workflow("hello")
    wf.task("greet", ["echo", "hello"])
    with osmo.Client() as client:
        result = client.wait(client.submit(wf))
        print(result.status)
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, Any

from osmo.version import __version__ as __version__

__all__ = [
    "Client",
    "Diagnostic",
    "InfrastructureError",
    "LogRecord",
    "NotFoundError",
    "OsmoError",
    "Param",
    "ServerUnreachable",
    "SpecError",
    "SubmitError",
    "TaskContext",
    "TaskInfo",
    "TaskStatus",
    "UsageError",
    "Workflow",
    "WorkflowFailed",
    "WorkflowInfo",
    "WorkflowSpec",
    "WorkflowStatus",
    "load_spec",
    "task_type",
]

_WHERE = {
    "Client": "osmo.sdk.client",
    "LogRecord": "osmo.sdk.client",
    "TaskInfo": "osmo.sdk.client",
    "WorkflowInfo": "osmo.sdk.client",
    "Workflow": "osmo.spec",
    "load_spec": "osmo.spec",
    "WorkflowSpec": "osmo.spec.model",
    "TaskStatus": "osmo.status",
    "WorkflowStatus": "osmo.status",
    "Diagnostic": "osmo.errors",
    "InfrastructureError": "osmo.errors",
    "NotFoundError": "osmo.errors",
    "OsmoError": "osmo.errors",
    "ServerUnreachable": "osmo.errors",
    "SpecError": "osmo.errors",
    "SubmitError": "osmo.errors",
    "UsageError": "osmo.errors",
    "WorkflowFailed": "osmo.errors",
    "Param": "osmo.tasktypes.api",
    "TaskContext": "osmo.tasktypes.api",
    "task_type": "osmo.tasktypes.api",
}

if TYPE_CHECKING:
    from osmo.errors import (
        Diagnostic,
        InfrastructureError,
        NotFoundError,
        OsmoError,
        ServerUnreachable,
        SpecError,
        SubmitError,
        UsageError,
        WorkflowFailed,
    )
    from osmo.sdk.client import Client, LogRecord, TaskInfo, WorkflowInfo
    from osmo.spec import Workflow, load_spec
    from osmo.spec.model import WorkflowSpec
    from osmo.status import TaskStatus, WorkflowStatus
    from osmo.tasktypes.api import Param, TaskContext, task_type


def __getattr__(name: str) -> Any:
    module = _WHERE.get(name)
    if module is None:
        raise AttributeError(f"module 'osmo' has no attribute '{name}'")
    value = getattr(importlib.import_module(module), name)
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return sorted(__all__)
