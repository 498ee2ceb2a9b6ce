"""The server's orders to a worker: typed on both sides, one JSON form between them."""

from __future__ import annotations

from typing import Any

import pytest

from osmo.errors import UsageError
from osmo.scheduler.types import AttemptLost, AttemptWaiting, Capacity, Node, PrepareAttempt
from osmo.spec import Workflow, spec_to_dict
from osmo.spec.stored import StoredSpec
from osmo.transport.wire import (
    Ack,
    Hello,
    Kill,
    OpenSession,
    Prepare,
    Run,
    Sweep,
    event_from_dict,
    event_to_dict,
    order_from_dict,
    order_to_dict,
    warm_runners,
)

CMD = PrepareAttempt(attempt_id="w-1:a:0", workflow_id="w-1", task="a", retry=0, node_id="n1",
                     inputs={"up": "/runs/w-1/up/0/output"}, hosts={"a": "10.0.0.1"}, run=True)
SPEC = StoredSpec(spec_to_dict(Workflow("w").task("a", ["true"]).build()), "wf.yaml", {})

ORDERS = [
    Prepare(CMD, manifests={"/runs/w-1/up/0/output": '{"entries": []}'}, secrets=True,
            max_output_bytes=1 << 20, spec=SPEC, exec_timeout=90.5, priority="LOW"),
    Prepare(CMD, manifests={}),
    Run("w-1:a:0"),
    Kill("w-1:a:0", "cancelled"),
    Ack("w-1:a:0"),
    OpenSession("f" * 32),
    Sweep("0123456789abcdef0123"),
]


@pytest.mark.parametrize("order", ORDERS, ids=lambda o: type(o).__name__)
def test_every_order_round_trips(order: Any) -> None:
    assert order_from_dict(order_to_dict(order)) == order


def test_the_json_form_is_the_one_workers_already_read() -> None:
    """Servers and workers of the version before typed orders speak the same messages."""
    assert order_to_dict(Kill("w-1:a:0", "why")) == {"op": "kill", "attempt_id": "w-1:a:0",
                                                      "reason": "why"}
    assert order_to_dict(OpenSession("t")) == {"op": "session", "ticket": "t"}
    sent = order_to_dict(ORDERS[0])
    assert sent["op"] == "prepare" and sent["attempt_id"] == "w-1:a:0"
    assert sent["spec"] == {"spec": SPEC.data, "filename": "wf.yaml", "types": {}}
    assert sent["secrets"] is True and sent["max_output_bytes"] == 1 << 20
    assert "spec" not in order_to_dict(ORDERS[1])  # sent only the first time


def test_an_order_from_a_server_before_time_limits_and_priorities_has_none() -> None:
    old = {k: v for k, v in order_to_dict(ORDERS[0]).items()
           if k not in ("exec_timeout", "priority")}
    got = order_from_dict(old)
    assert isinstance(got, Prepare)
    assert (got.exec_timeout, got.priority) == (None, None)


@pytest.mark.parametrize("data", [
    {"op": "reboot", "attempt_id": "x"},  # an order this worker does not know
    {"attempt_id": "x"},
    {"op": "run"},
    {"op": "run", "attempt_id": 7},
    {"op": "kill", "attempt_id": "x", "reason": ["no"]},
    {"op": "session", "ticket": None},
    {"op": "prepare", "attempt_id": "x"},
    {"op": "prepare", "cmd": {"attempt_id": "x"}, "manifests": {}},
    {"op": "prepare", "cmd": order_to_dict(ORDERS[1])["cmd"], "manifests": []},
    {"op": "prepare", "cmd": order_to_dict(ORDERS[1])["cmd"], "manifests": {"a": 1}},
    {"op": "prepare", "cmd": order_to_dict(ORDERS[1])["cmd"], "manifests": {},
     "spec": "wf.yaml"},
    {"op": "prepare", "cmd": order_to_dict(ORDERS[1])["cmd"], "manifests": {},
     "max_output_bytes": "lots"},
    {"op": "prepare", "cmd": order_to_dict(ORDERS[1])["cmd"], "manifests": {},
     "exec_timeout": -1},
    {"op": "prepare", "cmd": order_to_dict(ORDERS[1])["cmd"], "manifests": {},
     "exec_timeout": "1h"},
    {"op": "prepare", "cmd": order_to_dict(ORDERS[1])["cmd"], "manifests": {},
     "priority": "URGENT"},
    {"op": "sweep"},
    {"op": "sweep", "instance": "x" * 64},
    [],
])
def test_a_malformed_order_is_a_value_error(data: Any) -> None:
    with pytest.raises(ValueError):
        order_from_dict(data)


def test_a_handed_back_attempt_is_reported_through_the_wire_form() -> None:
    lost = AttemptLost("w-1:a:0", "worker w drained; attempt handed back")
    assert event_from_dict(event_to_dict(lost)) == lost


def test_a_waiting_report_round_trips_and_is_cleaned_on_arrival() -> None:
    said = AttemptWaiting("w-1:a:0", "0/2 nodes are available: 2 Insufficient cpu.")
    assert event_from_dict(event_to_dict(said)) == said
    hostile = {"op": "waiting", "attempt_id": "w-1:a:0", "reason": "a\x1b[2J\nb" * 1000}
    reason = event_from_dict(hostile).reason  # type: ignore[union-attr]
    assert reason.startswith("a [2J ba [2J b") and len(reason) == 300
    assert event_from_dict({"op": "waiting", "attempt_id": "x", "reason": None}) == (
        AttemptWaiting("x", ""))


GPU = Capacity(4, 2, 16 << 30, 0)
NODE = Node("k1", "default", Capacity(16, 2, 64 << 30, 0), address="10.0.0.2",
            platforms={"gpu": GPU, "cpu": Capacity(12, 0, 48 << 30, 0)})


def test_a_hello_carries_every_platform_with_its_capacity() -> None:
    assert Hello.from_dict(Hello(NODE).to_dict()).node == NODE
    hello = Hello(NODE, outlives=True, instance="0123456789abcdef0123")
    assert Hello.from_dict(hello.to_dict()) == hello
    old = Hello(Node("w", "default", Capacity(2), platform="x86")).to_dict()
    del old["platforms"]  # a worker from before platforms: its one platform, whole
    node = Hello.from_dict(old).node
    assert (node.platforms, node.offers("x86"), node.served()) == ({}, Capacity(2), ["x86"])


@pytest.mark.parametrize(("platforms", "words"), [
    ({f"p{n}": {} for n in range(257)}, "at most 256"),
    ({"a b": {}}, "no spaces"),
    ({"\x1b[31m": {}}, "printable"),
    ({"x" * 254: {}}, "1 to 253"),
    ({"gpu": 3}, "must be a capacity"),
    ({"gpu": {"cpu": -1}}, "must be a number from 0"),
    ([], "platforms"),
])
def test_a_malformed_platform_list_is_refused(platforms: Any, words: str) -> None:
    hello = {**Hello(NODE).to_dict(), "platforms": platforms}
    with pytest.raises(UsageError, match=words):
        Hello.from_dict(hello)


_RUNNER = {"type": "sim.rollout@2", "pid": 7, "rss": 1 << 20, "started": 3, "running": 1}


@pytest.mark.parametrize(("warm", "message"), [
    ("many", "'warm' must be a list"),
    ([1], "a list of runners"),
    ([{**_RUNNER, "pid": "7"}], "'warm.pid' must be"),
    ([{**_RUNNER, "rss": -1}], "numbers are from 0"),
    ([{**_RUNNER, "type": "x" * 201}], "'warm.type' is too long"),
    ([dict(_RUNNER)] * 257, "at most 256"),
])
def test_a_beats_warm_runners_are_checked(warm: Any, message: str) -> None:
    with pytest.raises(UsageError, match=message):
        warm_runners({"id": "w1", "warm": warm})


def test_a_beats_warm_runners_round_trip() -> None:
    assert warm_runners({"id": "w1", "warm": [_RUNNER]}) == [_RUNNER]
    assert warm_runners({"id": "w1"}) == []  # a worker from before the field
