"""TaskState/WorkflowState: JSON-safe round trips."""

from __future__ import annotations

import json

import pytest

from osmo.scheduler import TaskState, WorkflowState
from osmo.status import TaskStatus, WorkflowStatus


@pytest.mark.parametrize("state", [
    TaskState("wf-1", "a", "g"),
    TaskState("wf-1", "a", "g", TaskStatus.RUNNING, 2, "wf-1:a:2", "n1", None, None, "m",
              False, 1, 1, 1.0, 2.0, 3.0, None),
    TaskState("wf-1", "a", "g", TaskStatus.COMPLETED, exit_code=0, output="ref", reused=True),
])
def test_task_state_round_trips_through_json(state: TaskState) -> None:
    data = json.loads(json.dumps(state.to_dict()))
    assert data["status"] == state.status.name
    assert TaskState.from_dict(data) == state


def test_workflow_state_round_trips_and_ignores_unknown_keys() -> None:
    state = WorkflowState("wf-1", "wf", WorkflowStatus.FAILED_CANCELED, "local", 3, 1.0, 2.0,
                          3.0, "canceled")
    data = json.loads(json.dumps(state.to_dict()))
    assert WorkflowState.from_dict({**data, "future_field": 1}) == state


def test_copy_is_independent() -> None:
    state = TaskState("wf-1", "a", "g")
    snapshot = state.copy()
    state.status = TaskStatus.RUNNING
    assert snapshot.status is TaskStatus.SUBMITTING
