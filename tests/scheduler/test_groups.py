"""Groups: gang placement, barrier, lead semantics, ignoreNonleadStatus."""

from __future__ import annotations

import pytest

from osmo.scheduler import KillAttempt, PrepareAttempt, RunAttempt
from osmo.spec.model import GroupSpec, ResourceSpec
from osmo.status import ExitCode

from .sim import Sim, group, node, parse_statuses, play, task, workflow


def trio(*, barrier: bool = True, ignore: bool = True, after: str | None = None) -> GroupSpec:
    inputs = (after,) if after else ()
    return group("g", task("lead", *inputs, lead=True), task("w1"), task("w2"),
                 barrier=barrier, ignore=ignore)


def test_gang_is_prepared_together_with_peer_hosts() -> None:
    sim = Sim(node("n1", cpu=2), node("n2", cpu=2))
    sim.submit(workflow(trio()))
    prepares = [c for c in sim.last if isinstance(c, PrepareAttempt)]
    assert [(p.task, p.node_id) for p in prepares] == [
        ("lead", "n1"), ("w1", "n1"), ("w2", "n2")]
    assert all(p.hosts == {"lead": "addr-n1", "w1": "addr-n1", "w2": "addr-n2"}
               for p in prepares)


@pytest.mark.parametrize(("barrier", "runs_after"), [
    (True, [[], [], ["lead", "w1", "w2"]]),
    (False, [["lead"], ["w1"], ["w2"]]),
])
def test_barrier_releases_run_only_when_all_prepared(barrier: bool,
                                                     runs_after: list[list[str]]) -> None:
    sim = Sim()
    sim.submit(workflow(trio(barrier=barrier)))
    for name, expected in zip(["lead", "w1", "w2"], runs_after, strict=True):
        assert sim.of(RunAttempt, sim.prepare(name)) == expected


def test_barrier_does_not_wait_for_a_member_that_failed() -> None:
    sim = Sim()
    sim.submit(workflow(trio()))
    play(sim, "prepare lead; prepare w1")
    assert sim.of(RunAttempt, play(sim, "startfail w2")) == ["lead", "w1"]
    assert sim.status("w2") == "FAILED_START_ERROR"


def test_barrier_does_not_hold_a_retried_member() -> None:
    sim = Sim()
    sim.submit(workflow(trio()))
    play(sim, "prepare lead")
    emitted = play(sim, "lost w1")  # rescheduled alone, placed again at once
    assert sim.of(PrepareAttempt, emitted) == ["w1"]
    assert sim.of(RunAttempt, play(sim, "prepare w2")) == ["lead", "w2"]
    assert sim.of(RunAttempt, play(sim, "prepare w1")) == ["w1"]


@pytest.mark.parametrize(("ignore", "script", "expected"), [
    # ignoreNonleadStatus true: a failing non-lead is ignored, the others continue
    (True, "run w1=1", "lead=RUNNING w1=FAILED w2=RUNNING after=WAITING"),
    (True, "run w1=1; exit lead", "lead=COMPLETED w1=FAILED w2=COMPLETED after=INITIALIZING"),
    # false: any failure fails the group; the rest is stopped as FAILED
    (False, "run w1=1", "lead=FAILED w1=FAILED w2=FAILED after=FAILED_UPSTREAM"),
    (False, "run w1; exit lead", "lead=COMPLETED w1=COMPLETED w2=COMPLETED after=INITIALIZING"),
    # the lead decides in both modes
    (True, "exit lead=3", "lead=FAILED w1=FAILED w2=FAILED after=FAILED_UPSTREAM"),
    (False, "exit lead=3", "lead=FAILED w1=FAILED w2=FAILED after=FAILED_UPSTREAM"),
])
def test_ignore_nonlead_status(ignore: bool, script: str, expected: str) -> None:
    sim = Sim()
    sim.submit(workflow(trio(ignore=ignore), task("after", "lead")))
    play(sim, "prepare lead; prepare w1; prepare w2; start lead; start w1; start w2")
    play(sim, script)
    assert sim.statuses() == parse_statuses(expected)
    failed = "FAILED_UPSTREAM" in expected
    assert sim.wf() == ("FAILED" if failed else "RUNNING")


def test_lead_completion_stops_nonleads_with_kill() -> None:
    sim = Sim()
    sim.submit(workflow(trio()))
    play(sim, "prepare lead; prepare w1; prepare w2; start lead; start w1")
    emitted = play(sim, "exit lead")
    assert emitted == [KillAttempt("wf-1:w1:0", "n1", "stopped: lead finished"),
                       KillAttempt("wf-1:w2:0", "n1", "stopped: lead finished")]
    w1 = sim.task("w1")
    assert (w1.status.name, w1.exit_code, w1.message) == (
        "COMPLETED", ExitCode.STOPPED, "stopped: lead finished")
    assert sim.wf() == "COMPLETED"


def test_group_failure_names_the_failed_task() -> None:
    sim = Sim()
    sim.submit(workflow(trio(ignore=False)))
    play(sim, "prepare lead; prepare w1; prepare w2; start lead")
    emitted = play(sim, "startfail w2")
    assert sim.of(KillAttempt, emitted) == ["lead", "w1"]
    lead = sim.task("lead")
    assert (lead.status.name, lead.message) == ("FAILED", "stopped: task 'w2' FAILED_START_ERROR")
    assert sim.wf() == "FAILED"


def test_killed_attempt_keeps_resources_until_its_final_report() -> None:
    sizes = {"default": ResourceSpec(cpu=1), "two": ResourceSpec(cpu=2)}
    sim = Sim(node(cpu=3))
    sim.submit(workflow(trio(), task("next", "lead", resource="two"), resources=sizes))
    play(sim, "prepare lead; prepare w1; prepare w2; start lead; start w1; start w2")
    play(sim, "exit lead")
    assert sim.status("next") == "SCHEDULING"  # w1 and w2 are killed but hold 2 cpus
    assert sim.s.used("n1").cpu == 2
    play(sim, "exit w1=137")  # final report of a killed attempt: it only releases
    w1 = sim.task("w1")
    assert (w1.status.name, w1.exit_code) == ("COMPLETED", ExitCode.STOPPED)
    assert sim.status("next") == "INITIALIZING"
    assert sim.s.used("n1").cpu == 3
    play(sim, "exit w1=137")  # a duplicate releases nothing more
    assert sim.s.used("n1").cpu == 3


@pytest.mark.parametrize(("cpus", "placed", "after_one_exit"), [
    (1, ["a"], ["b"]),
    (2, ["a", "b"], ["c"]),
    (3, ["a", "b", "c"], []),
])
def test_placement_never_over_commits(cpus: int, placed: list[str],
                                      after_one_exit: list[str]) -> None:
    sim = Sim(node(cpu=cpus))
    sim.submit(workflow(task("a"), task("b"), task("c")))
    assert sim.of(PrepareAttempt) == placed
    assert sim.s.used("n1").cpu == len(placed)
    assert sim.of(PrepareAttempt, play(sim, "run a")) == after_one_exit
    assert sim.s.used("n1").cpu == min(cpus, 2)


def test_group_that_does_not_fit_waits_without_blocking_smaller_ones() -> None:
    sim = Sim(node(cpu=2))
    sim.submit(workflow(task("solo")))
    sim.submit(workflow(trio()), wid="wf-2")  # needs 3 cpus at once: never partially placed
    sim.submit(workflow(task("small")), wid="wf-3")
    assert sim.status("solo") == "INITIALIZING"
    assert set(sim.statuses("wf-2").values()) == {"SCHEDULING"}
    assert sim.status("small", "wf-3") == "INITIALIZING"
    assert sim.s.used("n1").cpu == 2


@pytest.mark.parametrize(("barrier", "held"), [(True, True), (False, False)])
def test_only_barrier_members_wait_for_run_attempt(barrier: bool, held: bool) -> None:
    sim = Sim()
    sim.submit(workflow(trio(barrier=barrier)))
    prepares = [c for c in sim.last if isinstance(c, PrepareAttempt)]
    assert len(prepares) == 3
    assert all(c.run is not held for c in prepares)
