"""The public surface of osmo.scheduler and errors for malformed input."""

from __future__ import annotations

import inspect

import pytest

import osmo.scheduler as scheduler
from osmo.scheduler import Scheduler, Tick, WorkflowSubmitted

from .sim import Sim, task, workflow


def test_exported_members_exist_and_are_documented() -> None:
    for name in scheduler.__all__:
        member = getattr(scheduler, name)
        assert inspect.getdoc(member), name


def test_scheduler_api_shape() -> None:
    public = {n for n in dir(Scheduler) if not n.startswith("_")}
    assert public == {"handle", "take_changes", "next_deadline", "check_fit", "restore",
                      "workflow", "tasks", "attempt", "attempts_on", "nodes", "used", "forget",
                      "waiting", "placement"}


@pytest.mark.parametrize(("event", "error"), [
    (WorkflowSubmitted("wf-1", "not a spec"), TypeError),
    (WorkflowSubmitted("wf-1", workflow(task("a", "a"))), ValueError),
    (WorkflowSubmitted("wf-0", workflow(task("a"))), ValueError),  # duplicate id
])
def test_malformed_submit_raises_before_changing_anything(event: WorkflowSubmitted,
                                                          error: type[Exception]) -> None:
    sim = Sim()
    sim.submit(workflow(task("x"), exec_timeout=1), wid="wf-0")
    sim.prepare("x", "wf-0")
    sim.start("x", "wf-0")
    with pytest.raises(error):
        sim.s.handle(event, 5.0)  # the due exec timeout must not fire half-way
    assert sim.status("x", "wf-0") == "RUNNING"
    assert not sim.s.take_changes()
    assert sim.send(Tick(), at=5.0)  # it fires now, with its KillAttempt


def test_unknown_workflow_queries_raise_key_error() -> None:
    s = Scheduler()
    with pytest.raises(KeyError):
        s.workflow("nope")
    with pytest.raises(KeyError):
        s.tasks("nope")
    assert s.attempt("nope:a:0") is None
    s.forget("nope")  # no-op
