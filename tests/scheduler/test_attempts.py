"""Attempt reports: exit actions and retry caps, lost attempts, fencing."""

from __future__ import annotations

import pytest

from osmo.scheduler import (
    AttemptExited,
    AttemptLost,
    AttemptPrepared,
    AttemptStarted,
    AttemptWaiting,
    NodeUp,
    PrepareAttempt,
)
from osmo.status import ExitCode

from .sim import Sim, node, play, task, workflow

RETRY_ON_3 = [("RESCHEDULE", [(3, 3)]), ("COMPLETE", [(0, 0), (10, 10)])]


@pytest.mark.parametrize(("codes", "max_retries", "status", "retry", "exit_code", "message"), [
    ([0], 3, "COMPLETED", 0, 0, ""),
    ([10], 3, "COMPLETED", 0, 10, ""),  # a COMPLETE rule on a non-zero code
    ([1], 3, "FAILED", 0, 1, "exit code 1"),
    ([3, 0], 3, "COMPLETED", 1, 0, ""),
    ([3, 3, 3, 0], 3, "COMPLETED", 3, 0, ""),
    ([3, 3, 3, 3], 3, "FAILED", 3, 3, "exit code 3: retry cap 3 reached"),
    ([3], 0, "FAILED", 0, 3, "exit code 3: retry cap 0 reached"),
    ([3, 1], 3, "FAILED", 1, 1, "exit code 1"),
])
def test_exit_actions_and_retry_cap(codes: list[int], max_retries: int, status: str,
                                    retry: int, exit_code: int, message: str) -> None:
    sim = Sim()
    sim.submit(workflow(task("t", rules=RETRY_ON_3)), max_retries=max_retries)
    for code in codes:
        play(sim, f"run t={code}")
    t = sim.task("t")
    assert (t.status.name, t.retry, t.exit_code, t.message) == (
        status, retry, exit_code, message)
    assert t.user_retries == retry and t.lost_retries == 0
    assert sim.wf() == status


def test_reschedule_logs_both_retries_and_uses_a_new_attempt_id() -> None:
    sim = Sim()
    sim.submit(workflow(task("t", rules=RETRY_ON_3)))
    emitted = play(sim, "run t=3")
    assert [(t.status, t.retry) for t in sim.transitions if t.task == "t"][-3:] == [
        ("RESCHEDULED", 0), ("SCHEDULING", 1), ("INITIALIZING", 1)]
    [prepare] = [c for c in emitted if isinstance(c, PrepareAttempt)]
    assert (prepare.attempt_id, prepare.retry) == ("wf-1:t:1", 1)


def test_complete_without_output_is_an_output_error() -> None:
    sim = Sim()
    sim.submit(workflow(task("t")))
    play(sim, "prepare t; start t")
    sim.send(AttemptExited(sim.aid("t"), 0, None, "disk full"))
    t = sim.task("t")
    assert (t.status.name, t.exit_code, t.message) == ("FAILED", ExitCode.OUTPUT_ERROR,
                                                       "disk full")


def test_start_failure() -> None:
    sim = Sim()
    sim.submit(workflow(task("t"), task("u", "t")))
    play(sim, "startfail t")
    t = sim.task("t")
    assert (t.status.name, t.exit_code, t.message) == (
        "FAILED_START_ERROR", ExitCode.START_ERROR, "boom")
    assert sim.status("u") == "FAILED_UPSTREAM"
    assert sim.s.used("n1").cpu == 0


@pytest.mark.parametrize(("losses", "cap", "status", "retry"), [
    (1, 5, "INITIALIZING", 1),
    (2, 2, "INITIALIZING", 2),
    (3, 2, "FAILED_SERVER_ERROR", 2),
])
def test_lost_attempts_retry_without_using_user_retries(losses: int, cap: int, status: str,
                                                       retry: int) -> None:
    sim = Sim(max_lost_retries=cap)
    sim.submit(workflow(task("t")), max_retries=0)
    for _ in range(losses):
        play(sim, "prepare t; start t; lost t")
    t = sim.task("t")
    assert (t.status.name, t.retry, t.user_retries, t.lost_retries) == (
        status, retry, 0, min(losses, cap))
    if status == "FAILED_SERVER_ERROR":
        assert t.exit_code == ExitCode.LOST and "cap 2 reached" in t.message
        assert sim.wf() == "FAILED_SERVER_ERROR"


@pytest.mark.parametrize(("steps", "counted"), [
    ("", 0),  # placed (INITIALIZING) when the server died: not the task's fault
    ("prepare t", 0),  # prepared, its command not started yet
    ("prepare t; start t", 1),  # RUNNING when the server died: counted like any loss
])
def test_a_server_restart_counts_only_attempts_that_were_running(steps: str,
                                                                 counted: int) -> None:
    sim = Sim(max_lost_retries=2)
    sim.submit(workflow(task("t")), max_retries=0)
    for _ in range(10):  # a crash loop of the server, each time at the same point
        play(sim, steps)
        sim.send(AttemptLost(sim.aid("t"), "server restarted; attempt lost",
                             server_restart=True))
        if sim.task("t").status.terminal:
            break
    t = sim.task("t")
    if counted:
        assert (t.status.name, t.lost_retries) == ("FAILED_SERVER_ERROR", 2)
    else:
        assert (t.status.name, t.retry, t.lost_retries) == ("INITIALIZING", 10, 0)
        assert "not counted against the lost-attempt cap" in sim.transitions[-2].message


def test_the_lost_attempt_cap_message_says_how_to_run_it_again() -> None:
    sim = Sim(max_lost_retries=0)
    sim.submit(workflow(task("t")))
    play(sim, "prepare t; start t; lost t")
    t = sim.task("t")
    assert t.status.name == "FAILED_SERVER_ERROR"
    assert t.message == ("worker lost; lost-attempt cap 0 reached; once the cause is fixed, "
                         "`osmo restart wf-1` runs it again")


def test_node_down_loses_its_attempts_and_they_move_to_another_node() -> None:
    sim = Sim(node("n1", cpu=1), node("n2", cpu=1))
    sim.submit(workflow(task("a"), task("b")))
    assert {sim.task("a").node_id, sim.task("b").node_id} == {"n1", "n2"}
    play(sim, "prepare a; start a; down n1")
    assert (sim.status("a"), sim.task("a").retry) == ("SCHEDULING", 1)
    assert sim.task("a").message == "retry 1 after: node 'n1' down"
    sim.send(NodeUp(node("n3", cpu=1)))
    assert (sim.status("a"), sim.task("a").node_id) == ("INITIALIZING", "n3")
    assert [n.id for n in sim.s.nodes()] == ["n2", "n3"]


@pytest.mark.parametrize("report", [
    AttemptPrepared("wf-1:t:0"),
    AttemptStarted("wf-1:t:0"),
    AttemptExited("wf-1:t:0", 0, "late-output"),
    AttemptLost("wf-1:t:0"),
    AttemptWaiting("wf-1:t:0", "Resources"),
    AttemptWaiting("wf-1:t:7", "Resources"),
    AttemptExited("wf-1:t:7", 0, "never-existed"),
    AttemptExited("nope", 0, "unknown"),
])
def test_reports_of_superseded_attempts_are_ignored(report: object) -> None:
    sim = Sim()
    sim.submit(workflow(task("t", rules=RETRY_ON_3)))
    play(sim, "run t=3; prepare t; start t")  # retry 1 is running
    before = sim.task("t")
    assert sim.send(report) == []  # type: ignore[arg-type]
    assert sim.task("t") == before
    assert not sim.changes
    assert sim.s.used("n1").cpu == 1


def test_a_terminal_task_is_never_committed_twice() -> None:
    sim = Sim()
    sim.submit(workflow(task("t")))
    play(sim, "run t")
    sim.send(AttemptExited("wf-1:t:0", 1, None))
    t = sim.task("t")
    assert (t.status.name, t.exit_code, t.output) == ("COMPLETED", 0, "out:t")
    assert sim.s.attempt("wf-1:t:0") == t
    assert sim.s.attempt("wf-1:x:0") is None


def test_a_waiting_reason_is_the_message_and_one_event_per_change() -> None:
    sim = Sim()
    sim.submit(workflow(task("t")))
    play(sim, "prepare t; start t")
    aid = sim.aid("t")
    waits = [AttemptWaiting(aid, "Priority"), AttemptWaiting(aid, "Priority"),
             AttemptWaiting(aid, "Resources")]
    for n, report in enumerate(waits):
        assert sim.send(report, at=100.0 + n) == []
    t = sim.task("t")
    assert (t.status.name, t.message, t.node_wait, t.node_wait_since) == (
        "RUNNING", "waiting: Resources", "Resources", 102.0)
    said = [(e.status, e.message) for e in sim.transitions if e.task == "t"][-2:]
    assert said == [("RUNNING", "waiting: Priority"), ("RUNNING", "waiting: Resources")]
    sim.send(AttemptWaiting(aid, ""))  # it runs now
    t = sim.task("t")
    assert (t.message, t.node_wait, t.node_wait_since) == ("", "", None)
    assert sim.transitions[-1].message == "waits no more"
    play(sim, "exit t")
    assert sim.status("t") == "COMPLETED"


def test_a_reason_said_before_the_start_is_kept_and_a_retry_starts_clean() -> None:
    sim = Sim()
    sim.submit(workflow(task("t", rules=RETRY_ON_3)))
    play(sim, "prepare t")
    sim.send(AttemptWaiting(sim.aid("t"), "0/2 nodes are available: 2 Insufficient cpu."))
    play(sim, "start t")
    t = sim.task("t")
    assert (t.status.name, t.message) == (
        "RUNNING", "waiting: 0/2 nodes are available: 2 Insufficient cpu.")
    play(sim, "exit t=3")  # RESCHEDULE: the next retry has no reason of its own yet
    t = sim.task("t")
    assert (t.retry, t.node_wait, t.node_wait_since) == (1, "", None)


@pytest.mark.parametrize(("said", "kept"), [
    ("Insufficient\x1b[31m cpu\n\rfake line\u202e", "Insufficient [31m cpu fake line"),
    ("x" * 100_000, "x" * 297 + "..."),
    ("\x00\x07\t", ""),
])
def test_a_reason_is_one_bounded_line_of_plain_text(said: str, kept: str) -> None:
    sim = Sim()
    sim.submit(workflow(task("t")))
    play(sim, "prepare t; start t")
    sim.send(AttemptWaiting(sim.aid("t"), said))
    assert sim.task("t").node_wait == kept
