"""Which turns of the engine may wait for the next report before their commit."""

from __future__ import annotations

import pytest

from osmo.scheduler.types import AttemptExited, AttemptPrepared, AttemptStarted, Tick
from osmo.server.engine import _starts_only

A, B = "wf-1:a:0", "wf-1:b:0"


@pytest.mark.parametrize(("items", "rides"), [
    ([AttemptPrepared(A), AttemptStarted(A, 12, 1.0)], True),  # started by its worker at once
    ([AttemptStarted(B, 13, 1.0)], True),  # a group member started after its barrier
    ([AttemptPrepared(A), AttemptStarted(A, 12, 1.0), AttemptStarted(B, 13, 1.0)], True),
    ([AttemptPrepared(A)], False),  # may release its group's barrier: RunAttempt to send
    ([AttemptPrepared(A), AttemptStarted(B, 13, 1.0)], False),  # A waits at a barrier
    ([AttemptPrepared(A), AttemptStarted(A, 12, 1.0), AttemptExited(B, 0)], False),
    ([Tick()], False),
    ([], False),
])
def test_only_start_reports_of_attempts_already_running_wait_for_the_next_turn(
        items: list[object], rides: bool) -> None:
    assert _starts_only(items) is rides
