"""Change notices: a burst of changes is told in few notices, and no change goes untold."""

from __future__ import annotations

import json
import threading
import time
from collections.abc import Callable, Iterator

import pytest

from osmo.server.notices import Notifier
from osmo.transport.seal import Signer, Verifier
from osmo.transport.zenoh_link import Link
from tests.transport.conftest import endpoint, links  # noqa: F401 - the fixtures

SIGNER = Signer()

Heard = tuple[list[float], threading.Event]  # arrival times, and "a notice arrived"
ENDS: list[bool] = []  # whether each notice heard told its workflow's end
Told = Callable[[str, float], tuple[Notifier, Heard]]


def _subscribe(client: Link, wf_id: str) -> Heard:
    got: list[float] = []
    arrived = threading.Event()

    verifier = Verifier(SIGNER.public)

    def on_notice(key: str, payload: bytes, signature: bytes | None) -> None:
        if wf_id == "probe":  # the test's own unsigned probe
            got.append(time.monotonic())
            arrived.set()
            return
        assert verifier.notice(key, payload, signature), "an unsigned notice"
        notice = json.loads(payload)
        assert notice in ({"workflow_id": wf_id}, {"workflow_id": wf_id, "ended": True})
        ENDS.append(notice.get("ended", False))
        got.append(time.monotonic())
        arrived.set()

    client.subscribe_raw(client.key("events", wf_id), on_notice)
    return got, arrived


def _delivered(server: Link, client: Link) -> None:
    """Wait until a publication reaches the client (the subscription is in place)."""
    got, arrived = _subscribe(client, "probe")
    deadline = time.monotonic() + 10
    while not got and time.monotonic() < deadline:
        server.put(server.key("events", "probe"), b'{"workflow_id": "probe"}')
        arrived.wait(0.05)
    assert got, "the subscription never received anything"


@pytest.fixture
def told(links: tuple[Link, Link]) -> Iterator[Told]:  # noqa: F811
    """``told(wf_id, interval)``: a real notifier on the server link and what the client hears."""
    server, client = links
    made: list[Notifier] = []

    def make(wf_id: str, interval: float) -> tuple[Notifier, Heard]:
        heard = _subscribe(client, wf_id)
        _delivered(server, client)
        made.append(Notifier(server, SIGNER, interval=interval))
        return made[-1], heard

    yield make
    for notifier in made:
        notifier.close()


def test_a_burst_of_changes_is_told_in_few_notices(told: Told) -> None:
    interval = 0.5
    notifier, (got, _) = told("wf-1", interval)
    start = time.monotonic()
    for _ in range(200):  # a busy workflow: one change per engine commit
        notifier.changed({"wf-1"})
        time.sleep(0.0005)
    last = time.monotonic()
    deadline = last + 10
    while time.monotonic() < deadline and (not got or got[-1] < last):
        time.sleep(0.01)
    time.sleep(interval * 2)  # nothing is pending any more
    # one leading notice, then at most one per interval while the burst lasted, one after
    assert 1 <= len(got) <= 2 + (last - start) / interval, got


def test_a_change_held_back_is_told_one_interval_later(told: Told) -> None:
    interval = 1.0
    notifier, (got, arrived) = told("wf-3", interval)
    notifier.changed({"wf-3"})  # told at once: nothing was sent before
    assert arrived.wait(10)
    arrived.clear()
    notifier.changed({"wf-3"})  # within the interval: held back, then told
    assert arrived.wait(10), "a change held back by the interval was never told"
    assert len(got) == 2
    assert got[1] - got[0] >= interval / 2, got


def test_a_workflow_s_end_is_told_at_once_within_the_interval(told: Told) -> None:
    notifier, (got, arrived) = told("wf-4", 30)
    notifier.changed({"wf-4"})  # told at once: nothing was sent before
    assert arrived.wait(10)
    arrived.clear()
    notifier.changed({"wf-4"}, ended={"wf-4"})  # within the interval, but its end
    assert arrived.wait(10), "a workflow's end waited out the interval"
    assert len(got) == 2 and got[1] - got[0] < 10, got
    assert ENDS[-2:] == [False, True]  # the notice says so, signed


def test_a_change_pending_at_close_is_sent(told: Told) -> None:
    notifier, (got, arrived) = told("wf-2", 30)
    notifier.changed({"wf-2"})  # sent at once: nothing was sent before
    assert arrived.wait(10)
    arrived.clear()
    notifier.changed({"wf-2"})  # held back by the interval ...
    notifier.close()  # ... and sent when the notifier closes
    assert arrived.wait(10)
    assert len(got) == 2
