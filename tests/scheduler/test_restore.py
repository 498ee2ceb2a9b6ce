"""restore(): rebuild from persisted states mid-run, then finish correctly."""

from __future__ import annotations

import pytest

from osmo.scheduler import (
    AttemptLost,
    NodeUp,
    PrepareAttempt,
    Scheduler,
    TaskState,
    WorkflowState,
)
from osmo.spec.model import ResourceSpec

from .sim import Sim, group, node, parse_statuses, play, task, workflow

SPEC = workflow(task("a"), group("g", task("b", "a", lead=True), task("c")), task("d", "b"),
                exec_timeout=100)


def mid_run() -> Sim:
    sim = Sim(node(cpu=2))
    sim.submit(SPEC)
    sim.now = 10
    play(sim, "run a; prepare b; prepare c; start b")
    sim.submit(workflow(task("x")), wid="wf-2")  # queued: the node is full
    return sim


def test_a_restored_scheduler_knows_how_each_active_attempt_was_placed() -> None:
    before = mid_run()
    placed = {c.attempt_id: c for c in before.commands if isinstance(c, PrepareAttempt)}
    sim = before.restored({"wf-1": SPEC, "wf-2": workflow(task("x"))}, node(cpu=2))
    for aid in ("wf-1:b:0", "wf-1:c:0"):
        original = placed[aid]
        assert sim.s.placement(aid) == PrepareAttempt(
            aid, "wf-1", original.task, 0, "n1", original.inputs, original.hosts, run=False)
    assert sim.s.placement("wf-1:b:0").inputs == {"a": "out:a"}  # type: ignore[union-attr]
    assert sim.s.placement("wf-1:a:0") is None  # completed: not active
    assert sim.s.placement("wf-9:z:0") is None
    assert sim.send(AttemptLost("wf-1:b:0", "lost")) is not None
    assert sim.s.placement("wf-1:b:0") is None  # superseded by retry 1


@pytest.mark.parametrize("node_first", [False, True])
def test_restore_mid_run_then_lost_attempts_are_rescheduled(node_first: bool) -> None:
    before = mid_run()
    assert before.statuses() == parse_statuses("a=COMPLETED b=RUNNING c=INITIALIZING d=WAITING")
    specs = {"wf-1": SPEC, "wf-2": workflow(task("x"))}
    if node_first:
        sim = before.restored(specs, node(cpu=2))
    else:
        sim = before.restored(specs)
        assert sim.s.used("n1").cpu == 2  # reserved on a node not announced yet
        assert sim.s.attempt("wf-1:b:0") is not None
        sim.send(NodeUp(node(cpu=2)))
    assert sim.statuses() == before.statuses()
    assert sim.status("x", "wf-2") == "SCHEDULING"
    assert sim.s.next_deadline() == 110  # exec timeout resumes from b's start
    # the server reports the restored attempts lost: each retries alone; wf-1 was submitted
    # before wf-2, so its retries are placed before x
    emitted = sim.send(AttemptLost("wf-1:b:0", "server restarted"))
    emitted += sim.send(AttemptLost("wf-1:c:0", "server restarted"))
    assert sim.of(PrepareAttempt, emitted) == ["b", "c"]
    assert (sim.task("b").retry, sim.task("b").lost_retries) == (1, 1)
    play(sim, "run c; run b")
    assert sim.statuses() == parse_statuses("a=COMPLETED b=COMPLETED c=COMPLETED "
                                            "d=INITIALIZING")
    assert sim.status("x", "wf-2") == "INITIALIZING"
    play(sim, "run d")
    play(sim, "run x", wid="wf-2")
    assert (sim.wf(), sim.wf("wf-2")) == ("COMPLETED", "COMPLETED")
    assert sim.s.used("n1").cpu == 0


def test_restore_of_a_gang_waiting_for_placement_and_a_terminal_workflow() -> None:
    sizes = {"default": ResourceSpec(cpu=1)}
    spec = workflow(group("g", task("p", lead=True), task("q")), resources=sizes,
                    queue_timeout=50)
    sim = Sim(node(cpu=1))
    sim.submit(workflow(task("t")), wid="wf-0")
    play(sim, "run t", wid="wf-0")
    sim.submit(spec)  # needs 2 cpus at once: waits
    restored = sim.restored({"wf-0": workflow(task("t")), "wf-1": spec}, node(cpu=2))
    assert restored.wf("wf-0") == "COMPLETED"
    assert restored.of(PrepareAttempt, restored.commands) == ["p", "q"]
    restored.s.forget("wf-0")
    with pytest.raises(KeyError):
        restored.s.workflow("wf-0")
    with pytest.raises(ValueError, match="not terminal"):
        restored.s.forget("wf-1")


def test_restore_rejects_tasks_that_do_not_match_the_spec() -> None:
    sim = mid_run()
    tasks = [TaskState.from_dict(t) for k, t in sim.stored_tasks.items() if k[1] != "d"]
    with pytest.raises(ValueError, match="do not match"):
        Scheduler().restore({"wf-1": SPEC}, [WorkflowState.from_dict(
            sim.stored_workflows["wf-1"])], tasks)
