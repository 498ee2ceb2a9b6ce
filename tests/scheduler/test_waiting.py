"""Why a task waits (``Scheduler.waiting``), and the no-worker queue timeout, on a fake clock."""

from __future__ import annotations

import pytest

from osmo.scheduler import DEFAULT_NO_WORKER_TIMEOUT, NodeDown, NodeUp, Tick, Waiting
from osmo.spec.model import ResourceSpec

from .sim import GiB, Sim, group, node, play, task, workflow

SIZES = {"default": ResourceSpec(cpu=1), "gpu4": ResourceSpec(cpu=1, gpu=4),
         "gpu2": ResourceSpec(cpu=1, gpu=2), "arm": ResourceSpec(cpu=1, platform="arm"),
         "mem": ResourceSpec(cpu=1, memory=12 * GiB), "two": ResourceSpec(cpu=2)}


def _reason(sim: Sim, name: str, wid: str = "wf-1") -> Waiting:
    return sim.s.waiting(wid)[name]


@pytest.mark.parametrize(("nodes", "busy", "resource", "reason"), [
    ([node("n1", gpu=2)], None, "gpu4", "needs 4 gpu, the largest worker in any pool has 2"),
    ([node("n1", gpu=2)], "gpu2", "gpu2", "needs 2 gpu, largest free is 0"),
    ([node("n1", gpu=4), node("n2", gpu=2)], "gpu2", "gpu4", "needs 4 gpu, largest free is 2"),
    ([node("n1", platform="x86")], None, "arm", "no online worker in any pool has platform 'arm' (platforms: x86)"),
    ([node("n1", memory=16 * GiB)], "mem", "mem", "needs 12Gi memory, largest free is 4Gi"),
])
def test_a_task_that_does_not_fit_says_what_it_lacks(nodes: list, busy: str | None,
                                                     resource: str, reason: str) -> None:
    sim = Sim(*nodes)
    if busy is not None:
        sim.submit(workflow(task("hog", resource=busy), resources=SIZES), wid="hog-1")
        assert sim.status("hog", "hog-1") == "INITIALIZING"
    sim.submit(workflow(task("t", resource=resource), resources=SIZES))
    assert sim.status("t") == "SCHEDULING"
    assert _reason(sim, "t") == Waiting(reason)


def test_a_task_whose_dimensions_fit_only_on_different_workers_says_so() -> None:
    # n1 has the cpu free but not the memory, n2 the memory but not the cpu
    sim = Sim(node("n1", cpu=4, memory=8 * GiB), node("n2", cpu=1, memory=16 * GiB))
    sizes = {**SIZES, "big": ResourceSpec(cpu=2, memory=12 * GiB)}
    sim.submit(workflow(task("t", resource="big"), resources=sizes))
    assert _reason(sim, "t").reason == ("needs cpu=2, memory=12Gi on one worker; no worker "
                                        "in any pool has all of it free")


def test_a_gang_that_does_not_fit_at_once_names_its_group() -> None:
    sim = Sim(node("n1", cpu=2))
    sim.submit(workflow(task("hog"), resources=SIZES), wid="hog-1")
    sim.submit(workflow(group("g", task("a"), task("b")), resources=SIZES))
    assert sim.statuses() == {"a": "SCHEDULING", "b": "SCHEDULING"}
    expected = Waiting("its group 'g' starts all at once and needs cpu=2; that does not fit "
                       "what is free in any pool")
    assert sim.s.waiting("wf-1") == {"a": expected, "b": expected}


def test_waiting_tasks_name_their_upstream_and_running_ones_have_no_reason() -> None:
    sim = Sim()
    sim.submit(workflow(task("a"), task("b", "a"), task("c", "b")))
    assert sim.s.waiting("wf-1") == {"b": Waiting("waits for upstream 'a' to complete"),
                                     "c": Waiting("waits for upstream 'b' to complete")}
    play(sim, "run a")
    assert set(sim.s.waiting("wf-1")) == {"c"}
    assert sim.s.waiting("nope") == {}


def test_a_pool_with_no_worker_says_since_when_and_fails_after_the_default() -> None:
    limit = DEFAULT_NO_WORKER_TIMEOUT
    sim = Sim(node("g1", cpu=1, pool="gpu"))
    sim.submit(workflow(task("a"), task("b")), pool="gpu")
    assert _reason(sim, "b") == Waiting("needs 1 cpu, largest free is 0")
    sim.send(NodeDown("g1"), at=100)  # a is lost and waits again, with b
    expected = Waiting("pool 'gpu' has no online worker", since=100, fails_at=100 + limit)
    assert sim.s.waiting("wf-1") == {"a": expected, "b": expected}
    assert sim.s.next_deadline() == 100 + limit
    sim.send(Tick(), at=100 + limit - 1)
    assert sim.statuses() == {"a": "SCHEDULING", "b": "SCHEDULING"}
    sim.send(Tick(), at=100 + limit)
    assert sim.statuses() == {"a": "FAILED_QUEUE_TIMEOUT", "b": "FAILED_QUEUE_TIMEOUT"}
    assert sim.task("a").message == (f"pool 'gpu' has had no online worker for {limit:g}s (the "
                                     "queue timeout of a pool with no worker; set "
                                     "timeout.queue_timeout to wait longer)")
    assert sim.wf() == "FAILED_QUEUE_TIMEOUT"


def test_a_worker_joining_in_time_stops_the_no_worker_clock() -> None:
    sim = Sim(node("g1", pool="gpu"))
    sim.submit(workflow(task("a")), pool="gpu")
    sim.send(NodeDown("g1"), at=10)
    sim.send(NodeUp(node("g2", pool="gpu")), at=20)
    assert sim.status("a") == "INITIALIZING"
    play(sim, "run a")
    sim.send(Tick(), at=10 + DEFAULT_NO_WORKER_TIMEOUT)
    assert sim.wf() == "COMPLETED"


def test_the_no_worker_clock_counts_from_the_later_of_the_pool_and_the_task() -> None:
    limit = 100.0
    sim = Sim(node("g1", cpu=1, pool="gpu"), no_worker_timeout=limit)  # type: ignore[arg-type]
    sim.submit(workflow(task("a"), task("b", "a")), pool="gpu")
    sim.send(NodeDown("g1"), at=0)  # a waits from 0
    sim.send(NodeUp(node("g1", cpu=1, pool="gpu")), at=50)
    play(sim, "prepare a; start a")
    sim.send(NodeDown("g1"), at=60)  # the pool is empty again from 60; a is lost at 60
    assert _reason(sim, "a") == Waiting("pool 'gpu' has no online worker", 60, 160)
    sim.send(Tick(), at=159)
    assert sim.status("a") == "SCHEDULING"
    sim.send(Tick(), at=160)
    assert sim.status("a") == "FAILED_QUEUE_TIMEOUT"


def test_a_workflow_queue_timeout_replaces_the_no_worker_default() -> None:
    sim = Sim(node("g1", pool="gpu"))
    sim.submit(workflow(task("a"), queue_timeout=5000), pool="gpu")
    sim.send(NodeDown("g1"), at=0)
    assert _reason(sim, "a").fails_at is None
    sim.send(Tick(), at=DEFAULT_NO_WORKER_TIMEOUT + 1)
    assert sim.status("a") == "SCHEDULING"
    sim.send(Tick(), at=5000)
    assert sim.status("a") == "FAILED_QUEUE_TIMEOUT"
    assert sim.task("a").message == "queue timeout (5000s) exceeded"


def test_with_no_node_at_all_any_pool_waits_for_one() -> None:
    sim = Sim(node("n1"))
    sim.submit(workflow(task("a")))
    sim.send(NodeDown("n1"), at=7)
    assert _reason(sim, "a") == Waiting("no worker is online", 7,
                                        7 + DEFAULT_NO_WORKER_TIMEOUT)
