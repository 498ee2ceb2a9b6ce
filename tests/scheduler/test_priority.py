"""Priority under contention, with ageing (a fake clock; one node with room for one task)."""

from __future__ import annotations

import pytest

from osmo.scheduler import PrepareAttempt
from osmo.scheduler.types import PRIORITY_AGEING

from .sim import Sim, node, task, workflow

ONE = workflow(task("t"))


def _placed(sim: Sim) -> list[str]:
    """Workflow ids in the order their task was placed."""
    return [c.attempt_id.split(":")[0] for c in sim.commands if isinstance(c, PrepareAttempt)]


def _drain(sim: Sim, order: list[str]) -> None:
    """Run whatever holds the node until every workflow in ``order`` was placed."""
    while len(_placed(sim)) < len(order):
        sim.run("t", wid=_placed(sim)[-1])


@pytest.mark.parametrize(("submits", "expected"), [
    # (workflow, priority, submit time): the node is busy with 'busy' until it ends
    ([("low", "LOW", 1), ("normal", "NORMAL", 2), ("high", "HIGH", 3)],
     ["high", "normal", "low"]),
    ([("a", "NORMAL", 1), ("b", "NORMAL", 2), ("c", "NORMAL", 3)], ["a", "b", "c"]),  # FIFO
    # ageing: a LOW request that waited more than two levels is no longer overtaken
    ([("low", "LOW", 1), ("high", "HIGH", 1 + 2 * PRIORITY_AGEING + 1)], ["low", "high"]),
    ([("low", "LOW", 1), ("high", "HIGH", 1 + 2 * PRIORITY_AGEING - 1)], ["high", "low"]),
    ([("normal", "NORMAL", 1), ("high", "HIGH", 1 + PRIORITY_AGEING + 1),
      ("low", "LOW", 2)], ["normal", "high", "low"]),
])
def test_priority_order_under_contention(submits: list[tuple[str, str, float]],
                                         expected: list[str]) -> None:
    sim = Sim(node(cpu=1))
    sim.submit(ONE, "busy-1", priority="LOW", )
    assert _placed(sim) == ["busy-1"]
    for wid, priority, at in submits:
        sim.now = at
        sim.submit(ONE, wid, priority=priority)
    assert _placed(sim) == ["busy-1"]  # all wait: the node is full
    sim.now = 10 * PRIORITY_AGEING
    _drain(sim, ["busy-1", *expected])
    assert _placed(sim) == ["busy-1", *expected]


def test_a_big_high_request_does_not_block_a_small_low_one() -> None:
    sim = Sim(node(cpu=2))
    big = workflow(task("t", resource="big"), resources={"big": _cpu(2)})
    sim.submit(ONE, "busy-1")
    sim.submit(big, "big-1", priority="HIGH")   # needs the whole node: waits
    sim.submit(ONE, "small-1", priority="LOW")  # fits the free cpu: placed now (backfill)
    assert _placed(sim) == ["busy-1", "small-1"]


def test_priority_survives_a_restart() -> None:
    sim = Sim(node(cpu=1))
    sim.submit(ONE, "busy-1")
    sim.submit(ONE, "low-1", priority="LOW")
    sim.now = 5
    sim.submit(ONE, "high-1", priority="HIGH")
    again = sim.restored({w: ONE for w in ("busy-1", "low-1", "high-1")}, node(cpu=1))
    assert again.s.workflow("high-1").priority == "HIGH"
    again.run("t", wid="busy-1")
    placed = [c.attempt_id.split(":")[0] for c in again.commands
              if isinstance(c, PrepareAttempt)]
    assert placed == ["high-1"], placed


def test_an_unknown_priority_is_refused() -> None:
    with pytest.raises(ValueError, match="priority must be one of HIGH, NORMAL, LOW"):
        Sim().submit(ONE, "x-1", priority="URGENT")


def _cpu(n: float):  # type: ignore[no-untyped-def]
    from osmo.spec.model import ResourceSpec

    return ResourceSpec(cpu=n)
