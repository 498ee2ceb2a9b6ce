"""A sweep is held for the node it was ordered to until that node says it is done.

A cluster node (``instance``, ``outlives``) that is down for good leaves objects; the server
orders a live node of its pool to delete them (``wire.Sweep``). Fake workers play the nodes:
one that is ordered to sweep and leaves without saying it swept (it died mid-sweep) must not
take the order with it: the next node of the pool gets it. A node may only confirm what was
ordered to it: a confirmation of another's order, of an unknown instance, or one that comes
after its order went to another node is refused, and the order stays.
"""

from __future__ import annotations

import json
import queue
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import pytest

from osmo.errors import NotAllowed, UsageError
from osmo.transport.rpc import ApiClient
from osmo.transport.seal import Purpose
from osmo.transport.wire import Sweep, order_from_dict
from osmo.transport.zenoh_link import Link, Subscription
from tests.e2e.cluster import Cluster

GRACE = 1.0  # --adopt-grace: how long a gone cluster node is away before it is down


def _hello(name: str) -> dict[str, object]:
    return {"id": name, "pool": "default", "address": "127.0.0.1", "instance": f"inst-{name}",
            "outlives": True, "capacity": {"cpu": 1, "memory": 8 << 30, "storage": 100 << 30}}


@contextmanager
def _node(c: Cluster, name: str) -> Iterator[tuple[ApiClient, queue.Queue[str], Subscription]]:
    """A fake cluster node, the instances the server orders it to sweep, and its liveliness
    token (closed: the node leaves, while its link may still speak)."""
    ordered: queue.Queue[str] = queue.Queue()
    rel = f"to-worker/{name}"
    link = Link.client([c.endpoint], "local")
    fake = ApiClient(link, timeout=10, token=c.token(name))

    def on_order(_key: str, data: bytes, attachment: bytes | None) -> None:
        opened = fake.opened(Purpose.PUSH, rel, attachment, data)
        if opened is not None and isinstance(order := order_from_dict(
                json.loads(opened[2])), Sweep):
            ordered.put(order.instance)

    try:
        sub = link.subscribe_raw(link.key(rel), on_order)
        fake.call("worker_register", _hello(name))
        alive = link.token(link.key("alive", "worker", name))
        try:
            yield fake, ordered, alive
        finally:
            alive.close()
            sub.close()
    finally:
        link.close()


def _ordered_until(ordered: queue.Queue[str], instance: str, timeout: float = 30) -> list[str]:
    """The sweeps ordered, until ``instance`` was (AssertionError: never)."""
    seen: list[str] = []
    deadline = time.monotonic() + timeout
    while instance not in seen:
        try:
            seen.append(ordered.get(timeout=max(0.0, deadline - time.monotonic())))
        except queue.Empty:
            raise AssertionError(f"{instance} was never ordered swept (seen: {seen})") from None
    return seen


def _until_gone(c: Cluster, name: str) -> None:
    deadline = time.monotonic() + GRACE + 30
    while name in c.nodes():
        assert time.monotonic() < deadline, c.nodes()
        time.sleep(0.1)


def test_a_sweep_its_live_node_did_not_confirm_is_ordered_again(tmp_path: Path) -> None:
    """A node whose sweep failed (the API server refused it) says nothing: while it lives,
    the order comes again each adopt grace, until it confirms."""
    c = Cluster(tmp_path, server_args=("--adopt-grace", str(GRACE)))
    c.start_server()
    try:
        with _node(c, "gone"):
            pass
        _until_gone(c, "gone")
        with _node(c, "tries") as (tries, ordered, _):
            _ordered_until(ordered, "inst-gone")
            started = time.monotonic()
            again = _ordered_until(ordered, "inst-gone", timeout=GRACE + 10)
            assert again == ["inst-gone"] and time.monotonic() - started >= GRACE * 0.5, again
            tries.call("worker_swept", {"id": "tries", "instance": "inst-gone"})
            with pytest.raises(queue.Empty):  # confirmed: not again
                ordered.get(timeout=GRACE * 3)
    finally:
        c.stop()


def test_a_sweep_its_node_did_not_confirm_goes_to_the_next_node(tmp_path: Path) -> None:
    c = Cluster(tmp_path, server_args=("--adopt-grace", str(GRACE)))
    c.start_server()
    try:
        with _node(c, "gone"):
            pass  # it leaves: away, then down for good; its pool has no live node yet
        _until_gone(c, "gone")
        with _node(c, "dies") as (dies, ordered, alive):
            _ordered_until(ordered, "inst-gone")
            alive.close()  # it leaves without confirming (killed mid-sweep): not done
            deadline = time.monotonic() + 30
            while c.nodes().get("dies", {}).get("status") == "online":
                assert time.monotonic() < deadline, c.nodes()
                time.sleep(0.1)
            with pytest.raises(NotAllowed):  # and a late word from it counts no more
                dies.call("worker_swept", {"id": "dies", "instance": "inst-gone"})
        with _node(c, "next") as (nxt, ordered, _):
            _ordered_until(ordered, "inst-gone")  # the unconfirmed sweep was not lost
            for bad in ("inst-nobody", "inst-next", "inst-*", "**", "\x1b[2J" + "A" * 100_000):
                # never ordered to it: no name, wildcard or hostile text, matches one
                with pytest.raises(NotAllowed):
                    nxt.call("worker_swept", {"id": "next", "instance": bad})
            for bad in ("", None, 7):
                with pytest.raises(UsageError):
                    nxt.call("worker_swept", {"id": "next", "instance": bad})
            with pytest.raises(NotAllowed):  # it speaks only for itself
                nxt.call("worker_swept", {"id": "dies", "instance": "inst-gone"})
            nxt.call("worker_swept", {"id": "next", "instance": "inst-gone"})
            with pytest.raises(NotAllowed):  # done: once
                nxt.call("worker_swept", {"id": "next", "instance": "inst-gone"})
        with _node(c, "last") as (_, ordered, _):  # confirmed: nobody is ordered it again
            swept = [ordered.get(timeout=GRACE + 30)]  # "dies" and "next" are down now
            deadline = time.monotonic() + 2
            while time.monotonic() < deadline:
                try:
                    swept.append(ordered.get(timeout=0.2))
                except queue.Empty:
                    pass
            assert "inst-gone" not in swept and set(swept) <= {"inst-dies", "inst-next"}, swept
    finally:
        c.stop()
