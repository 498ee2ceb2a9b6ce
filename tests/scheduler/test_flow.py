"""Dependencies and aggregate statuses: chains, fan-out/join, cascades, reuse, Changes."""

from __future__ import annotations

import pytest

from osmo.scheduler import AttemptPrepared, PrepareAttempt, TaskState, WorkflowState
from osmo.spec.model import ResourceSpec
from osmo.status import ExitCode

from .sim import Sim, node, parse_statuses, play, task, workflow

CHAIN = workflow(task("a"), task("b", "a"), task("c", "b"))
FAN = workflow(task("src"), task("x", "src"), task("y", "src"), task("z", "src"),
               task("join", "x", "y", "z"))


@pytest.mark.parametrize(("script", "expected", "wf_status"), [
    ("", "a=INITIALIZING b=WAITING c=WAITING", "PENDING"),
    ("prepare a; start a", "a=RUNNING b=WAITING c=WAITING", "RUNNING"),
    # the next group is placed in the same event, so the workflow never looks idle
    ("run a", "a=COMPLETED b=INITIALIZING c=WAITING", "RUNNING"),
    ("run a; run b", "a=COMPLETED b=COMPLETED c=INITIALIZING", "RUNNING"),
    ("run a; run b; run c", "a=COMPLETED b=COMPLETED c=COMPLETED", "COMPLETED"),
    ("run a=1", "a=FAILED b=FAILED_UPSTREAM c=FAILED_UPSTREAM", "FAILED"),
    ("run a; run b=2", "a=COMPLETED b=FAILED c=FAILED_UPSTREAM", "FAILED"),
])
def test_serial_chain(script: str, expected: str, wf_status: str) -> None:
    sim = Sim()
    sim.submit(CHAIN)
    play(sim, script)
    assert sim.statuses() == parse_statuses(expected)
    assert sim.wf() == wf_status


@pytest.mark.parametrize(("script", "expected", "wf_status"), [
    ("run src", "src=COMPLETED x=INITIALIZING y=INITIALIZING z=INITIALIZING join=WAITING",
     "RUNNING"),
    ("run src; run x; run y", "src=COMPLETED x=COMPLETED y=COMPLETED z=INITIALIZING "
     "join=WAITING", "RUNNING"),
    ("run src; run x; run y; run z", "src=COMPLETED x=COMPLETED y=COMPLETED z=COMPLETED "
     "join=INITIALIZING", "RUNNING"),
    # a failure waits for the other branches before the workflow aggregates
    ("run src; run x=1; prepare y; start y", "src=COMPLETED x=FAILED y=RUNNING "
     "z=INITIALIZING join=FAILED_UPSTREAM", "RUNNING"),
    ("run src; run x=1; run y; run z", "src=COMPLETED x=FAILED y=COMPLETED z=COMPLETED "
     "join=FAILED_UPSTREAM", "FAILED"),
])
def test_parallel_fan_out_and_join(script: str, expected: str, wf_status: str) -> None:
    sim = Sim(node(cpu=8))
    sim.submit(FAN)
    play(sim, script)
    assert sim.statuses() == parse_statuses(expected)
    assert sim.wf() == wf_status


def test_join_receives_every_upstream_output() -> None:
    sim = Sim(node(cpu=8))
    sim.submit(FAN)
    play(sim, "run src; run x; run y; run z")
    [prepare] = [c for c in sim.last if isinstance(c, PrepareAttempt)]
    assert prepare.task == "join"
    assert prepare.inputs == {"x": "out:x", "y": "out:y", "z": "out:z"}


def test_upstream_failure_cascades_transitively_with_exit_code_and_message() -> None:
    spec = workflow(task("a"), task("b", "a"), task("c", "b"), task("d", "c"), task("e"))
    sim = Sim()
    sim.submit(spec)
    play(sim, "run a=7")
    assert sim.statuses() == parse_statuses(
        "a=FAILED b=FAILED_UPSTREAM c=FAILED_UPSTREAM d=FAILED_UPSTREAM e=INITIALIZING")
    d = sim.task("d")
    assert d.exit_code == ExitCode.UPSTREAM_FAILED
    assert d.message == "upstream group 'a' FAILED"
    assert sim.wf() == "RUNNING"  # e still to run; a failure aggregates after all groups
    play(sim, "run e")
    assert sim.wf() == "FAILED"
    assert "a (FAILED)" in sim.s.workflow("wf-1").message


def test_workflow_times_and_transitions() -> None:
    sim = Sim()
    sim.submit(CHAIN)
    sim.now = 5
    play(sim, "prepare a; start a")
    sim.now = 9
    play(sim, "exit a; run b; run c")
    state = sim.s.workflow("wf-1")
    assert (state.submitted_at, state.started_at, state.ended_at) == (0, 5, 9)
    assert [t.status for t in sim.transitions if t.task is None] == [
        "PENDING", "RUNNING", "COMPLETED"]
    assert [t.status for t in sim.transitions if t.task == "a"] == [
        "SCHEDULING", "INITIALIZING", "RUNNING", "COMPLETED"]


def test_workflow_waits_while_nothing_of_it_is_active() -> None:
    big = {"default": ResourceSpec(cpu=1), "big": ResourceSpec(cpu=2)}
    sim = Sim(node(cpu=2))
    sim.submit(workflow(task("a"), task("b", "a", resource="big"), resources=big))
    play(sim, "prepare a; start a")
    sim.submit(workflow(task("x")), wid="wf-2")  # takes the second cpu
    play(sim, "exit a")
    assert (sim.status("b"), sim.wf()) == ("SCHEDULING", "WAITING")
    play(sim, "run x", wid="wf-2")
    assert (sim.status("b"), sim.wf()) == ("INITIALIZING", "WAITING")
    play(sim, "start b")
    assert sim.wf() == "RUNNING"
    play(sim, "exit b")
    assert [t.status for t in sim.transitions if t.task is None and t.workflow_id == "wf-1"] \
        == ["PENDING", "RUNNING", "WAITING", "RUNNING", "COMPLETED"]


def test_reused_groups_complete_at_once_and_feed_downstream() -> None:
    sim = Sim()
    sim.submit(CHAIN, reused={"a": "old:a", "b": "old:b"})
    assert sim.statuses() == parse_statuses("a=COMPLETED b=COMPLETED c=INITIALIZING")
    a = sim.task("a")
    assert (a.reused, a.output, a.attempt_id) == (True, "old:a", None)
    [prepare] = sim.last
    assert isinstance(prepare, PrepareAttempt) and prepare.inputs == {"b": "old:b"}


def test_fully_reused_workflow_completes_on_submit() -> None:
    sim = Sim()
    sim.submit(CHAIN, reused={"a": "1", "b": "2", "c": "3"})
    assert sim.wf() == "COMPLETED"
    assert sim.last == []


def test_changes_hold_copies_once_per_take() -> None:
    sim = Sim()
    sim.submit(CHAIN)
    tasks = [t for t in sim.changes.tasks if isinstance(t, TaskState)]
    assert sorted(t.name for t in tasks) == ["a", "b", "c"]
    assert [w.id for w in sim.changes.workflows if isinstance(w, WorkflowState)] == ["wf-1"]
    snapshot = next(t for t in tasks if t.name == "a")
    play(sim, "prepare a; start a")
    assert snapshot.status.name == "INITIALIZING"  # not mutated later
    assert sim.s.take_changes().tasks == []  # already taken
    assert not sim.s.take_changes()


def test_barrier_free_single_task_runs_right_after_prepared() -> None:
    sim = Sim()
    sim.submit(CHAIN)
    [placed] = [c for c in sim.commands if isinstance(c, PrepareAttempt)]
    assert placed.run  # no barrier: the worker starts it as soon as it is prepared
    assert sim.s.handle(AttemptPrepared("wf-1:a:0"), sim.now) == []  # no RunAttempt needed
    assert sim.s.handle(AttemptPrepared("wf-1:a:0"), sim.now) == []  # duplicate: nothing
