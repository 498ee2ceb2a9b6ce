"""Exec and queue timeouts (fake clock), next_deadline, cancel."""

from __future__ import annotations

import pytest

from osmo.scheduler import CancelWorkflow, KillAttempt, PrepareAttempt, Tick
from osmo.spec.model import ResourceSpec, WorkflowSpec
from osmo.status import ExitCode

from .sim import Sim, group, node, parse_statuses, play, task, workflow


def pair_then_c(exec_timeout: float | None = None) -> WorkflowSpec:
    return workflow(group("g", task("a", lead=True), task("b")), task("c", "a"),
                    exec_timeout=exec_timeout)


def test_exec_timeout_runs_from_the_groups_first_running() -> None:
    sim = Sim()
    sim.submit(pair_then_c(exec_timeout=10))
    assert sim.s.next_deadline() is None  # nothing is running yet
    sim.now = 5
    play(sim, "prepare a; prepare b; start a")
    assert sim.s.next_deadline() == 15
    sim.now = 8
    play(sim, "start b")
    assert sim.s.next_deadline() == 15  # per group, not per task
    assert sim.send(Tick(), at=14.9) == []
    emitted = sim.send(Tick(), at=15)
    assert emitted == [KillAttempt("wf-1:a:0", "n1", "exec timeout"),
                       KillAttempt("wf-1:b:0", "n1", "exec timeout")]
    assert sim.statuses() == parse_statuses(
        "a=FAILED_EXEC_TIMEOUT b=FAILED_EXEC_TIMEOUT c=FAILED_UPSTREAM")
    a = sim.task("a")
    assert (a.exit_code, a.message) == (ExitCode.EXEC_TIMEOUT, "exec timeout (10s) exceeded")
    assert sim.wf() == "FAILED_EXEC_TIMEOUT"
    assert sim.s.next_deadline() is None
    assert sim.s.used("n1").cpu == 2  # until the killed attempts report
    play(sim, "exit a=137; exit b=137")
    assert sim.s.used("n1").cpu == 0
    assert sim.task("a").status.name == "FAILED_EXEC_TIMEOUT"


def test_exec_timeout_fires_before_a_report_arriving_after_the_deadline() -> None:
    sim = Sim()
    sim.submit(workflow(task("t"), exec_timeout=10))
    play(sim, "prepare t; start t")
    sim.now = 11
    play(sim, "exit t")
    assert sim.status("t") == "FAILED_EXEC_TIMEOUT"


def test_exec_timeout_cleared_when_group_finishes_in_time() -> None:
    sim = Sim()
    sim.submit(workflow(task("t"), task("u", "t"), exec_timeout=10))
    play(sim, "run t")
    assert sim.s.next_deadline() is None  # t's group ended in time: its deadline is dropped
    play(sim, "prepare u")
    sim.now = 4
    play(sim, "start u")
    assert sim.s.next_deadline() == 14


@pytest.mark.parametrize(("ignore", "expected", "wf_status"), [
    (True, "lead=FAILED_QUEUE_TIMEOUT w=FAILED_QUEUE_TIMEOUT", "FAILED_QUEUE_TIMEOUT"),
    (False, "lead=FAILED_QUEUE_TIMEOUT w=FAILED_QUEUE_TIMEOUT", "FAILED_QUEUE_TIMEOUT"),
])
def test_queue_timeout_of_a_group_that_never_fits(ignore: bool, expected: str,
                                                  wf_status: str) -> None:
    sim = Sim(node(cpu=1))
    sim.submit(workflow(group("g", task("lead"), task("w"), ignore=ignore), queue_timeout=30))
    assert sim.s.next_deadline() == 30
    sim.send(Tick(), at=30)
    assert sim.statuses() == parse_statuses(expected)
    assert sim.task("w").exit_code == ExitCode.QUEUE_TIMEOUT
    assert sim.wf() == wf_status


def test_queue_timeout_counts_from_entering_scheduling_until_placed() -> None:
    two = {"default": ResourceSpec(cpu=1), "two": ResourceSpec(cpu=2)}
    sim = Sim(node(cpu=2))
    sim.submit(workflow(task("a"), task("b", "a"), resources=two, queue_timeout=5))
    sim.submit(workflow(task("big", resource="two"), resources=two, queue_timeout=5),
               wid="wf-2")
    assert sim.s.next_deadline() == 5  # wf-2's big waits; a was placed at once
    sim.now = 3
    play(sim, "prepare a; start a; exit a")  # frees the cpu: big fits, b follows it
    assert sim.status("big", "wf-2") == "SCHEDULING"  # FIFO: wf-1's b goes first, fits
    assert sim.status("b") == "INITIALIZING"
    sim.send(Tick(), at=5)
    assert sim.status("big", "wf-2") == "FAILED_QUEUE_TIMEOUT"
    assert sim.wf() == "RUNNING"


@pytest.mark.parametrize(("script", "expected", "kills"), [
    ("", "a=FAILED_CANCELED b=FAILED_CANCELED c=FAILED_CANCELED", ["a", "b"]),
    ("prepare a; prepare b; start a; exit b", "a=FAILED_CANCELED b=COMPLETED c=FAILED_CANCELED",
     ["a"]),
])
def test_cancel(script: str, expected: str, kills: list[str]) -> None:
    sim = Sim()
    sim.submit(pair_then_c())
    play(sim, script)
    emitted = play(sim, "cancel")
    assert sim.of(KillAttempt, emitted) == kills
    assert sim.statuses() == parse_statuses(expected)
    assert sim.task("c").exit_code == ExitCode.CANCELED
    assert sim.wf() == "FAILED_CANCELED"
    assert sim.s.workflow("wf-1").ended_at == sim.now


def test_cancel_of_terminal_or_unknown_workflow_is_a_no_op() -> None:
    sim = Sim()
    sim.submit(workflow(task("t")))
    play(sim, "run t")
    assert play(sim, "cancel") == []
    assert not sim.changes
    assert sim.send(CancelWorkflow("nope")) == []
    assert sim.wf() == "COMPLETED"


def test_canceled_queued_request_is_never_placed() -> None:
    sim = Sim(node(cpu=1))
    sim.submit(workflow(task("a")))
    sim.submit(workflow(task("b")), wid="wf-2")
    play(sim, "cancel", wid="wf-2")
    assert sim.of(PrepareAttempt, play(sim, "run a")) == []
    assert sim.status("b", "wf-2") == "FAILED_CANCELED"
    assert sim.s.used("n1").cpu == 0


def test_an_attempt_a_cluster_s_time_limit_ended_is_failed_exec_timeout() -> None:
    """A Slurm job's TIMEOUT (its --time, or its partition's limit) reaches the scheduler as
    exit code ExitCode.EXEC_TIMEOUT: the task is FAILED_EXEC_TIMEOUT, not retried."""
    sim = Sim()
    sim.submit(workflow(task("t", rules=[("RESCHEDULE", [(0, 255)])])))
    play(sim, f"run t={ExitCode.EXEC_TIMEOUT}")
    t = sim.task("t")
    assert (t.status.name, t.retry, t.exit_code) == ("FAILED_EXEC_TIMEOUT", 0,
                                                     ExitCode.EXEC_TIMEOUT)
    assert "time limit" in t.message
    assert sim.wf() == "FAILED_EXEC_TIMEOUT"
