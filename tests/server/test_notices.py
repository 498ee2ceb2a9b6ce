"""Change notices: a burst of changes is told in few notices, and the last change is told."""

from __future__ import annotations

import threading
import time
from collections.abc import Iterator

import pytest

from osmo.config import free_port
from osmo.server.notices import Notifier
from osmo.transport.zenoh_link import Link


@pytest.fixture
def links() -> Iterator[tuple[Link, Link]]:
    """A router session (the server's) and a client session subscribed through it."""
    port = free_port(0)
    server = Link.router([f"tcp/127.0.0.1:{port}"])
    client = Link.client([f"tcp/127.0.0.1:{port}"])
    yield server, client
    client.close()
    server.close()


def _subscribe(client: Link, wf_id: str) -> tuple[list[float], threading.Event]:
    got: list[float] = []
    arrived = threading.Event()

    def on_notice(message: dict[str, object]) -> None:
        assert message == {"workflow_id": wf_id}
        got.append(time.monotonic())
        arrived.set()

    client.subscribe(client.key("events", wf_id), on_notice)
    return got, arrived


def _delivered(server: Link, client: Link) -> None:
    """Wait until a publication reaches the client (the subscription is in place)."""
    got, arrived = _subscribe(client, "probe")
    deadline = time.monotonic() + 10
    while not got and time.monotonic() < deadline:
        server.publish(server.key("events", "probe"), {"workflow_id": "probe"})
        arrived.wait(0.05)
    assert got, "the subscription never received anything"


def test_a_burst_of_changes_is_told_in_few_notices(links: tuple[Link, Link]) -> None:
    server, client = links
    got, _ = _subscribe(client, "wf-1")
    _delivered(server, client)
    interval = 0.5
    notifier = Notifier(server, interval=interval)
    try:
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
    finally:
        notifier.close()


def test_a_change_held_back_is_told_one_interval_later(links: tuple[Link, Link]) -> None:
    server, client = links
    got, arrived = _subscribe(client, "wf-3")
    _delivered(server, client)
    interval = 1.0
    notifier = Notifier(server, interval=interval)
    try:
        notifier.changed({"wf-3"})  # told at once: nothing was sent before
        assert arrived.wait(10)
        arrived.clear()
        notifier.changed({"wf-3"})  # within the interval: held back, then told
        assert arrived.wait(10), "a change held back by the interval was never told"
        assert len(got) == 2
        assert got[1] - got[0] >= interval / 2, got
    finally:
        notifier.close()


def test_a_change_pending_at_close_is_sent(links: tuple[Link, Link]) -> None:
    server, client = links
    got, arrived = _subscribe(client, "wf-2")
    _delivered(server, client)
    notifier = Notifier(server, interval=30)
    notifier.changed({"wf-2"})  # sent at once: nothing was sent before
    assert arrived.wait(10)
    arrived.clear()
    notifier.changed({"wf-2"})  # held back by the interval ...
    notifier.close()  # ... and sent when the notifier closes
    assert arrived.wait(10)
    assert len(got) == 2
