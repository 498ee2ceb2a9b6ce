"""A beat's offer (what a cluster node's cluster has now) is checked like a registration.

A fake worker (a valid worker token) registers with room for one cpu-1 task, then beats
with offers: a malformed one is refused whole (the worker's capacity unchanged, no
traceback); a good one changes what ``osmo resource list`` shows and what the scheduler
places there, while the attempt it already holds keeps its reservation.
"""

from __future__ import annotations

from pathlib import Path

import pytest

from osmo.errors import UsageError
from tests.conftest import write
from tests.e2e.cluster import Cluster

FAKE = {"id": "fake", "pool": "default", "address": "127.0.0.1",
        "capacity": {"cpu": 1, "memory": 8 << 30, "storage": 100 << 30}}
BAD = [
    "junk",
    {"capacity": {"cpu": -1}},
    {"capacity": {"cpu": "many"}},
    {"capacity": {"gpu": 2**70}},
    {"capacity": {"cpu": 4}, "platforms": {"a b": {"cpu": 1}}},
    {"capacity": {"cpu": 4}, "platforms": {f"p{i}": {"cpu": 1} for i in range(10_000)}},
    {"capacity": {"cpu": 4}, "platforms": {"gpu": "all"}},
]


def _spec(tmp: Path) -> Path:
    return write(tmp / "w.yaml", """
workflow:
  name: w
  resources:
    default: {cpu: 1}
  tasks:
  - name: a
    command: [sh, -c, "true"]
  - name: b
    command: [sh, -c, "true"]
""")


def test_an_offer_is_checked_and_changes_what_the_node_has_room_for(tmp_path: Path) -> None:
    c = Cluster(tmp_path)
    c.start_server()
    try:
        with c.fake_worker(FAKE) as fake:
            wf = c.osmo.submit(_spec(tmp_path))
            info = c.osmo.wait_for(wf, lambda i: any(t["status"] == "INITIALIZING"
                                                     for t in i["tasks"]))
            assert sorted(t["status"] for t in info["tasks"]) == ["INITIALIZING", "SCHEDULING"]
            for offer in BAD:
                with pytest.raises(UsageError):
                    fake.call("worker_beat", {"id": "fake", "offer": offer})
            assert c.nodes()["fake"]["total"]["cpu"] == 1
            fake.call("worker_beat", {"id": "fake", "offer": {
                "capacity": {"cpu": 2, "memory": 8 << 30, "storage": 100 << 30},
                "platforms": {"big": {"cpu": 2}}}})
            c.osmo.wait_for(wf, lambda i: all(t["status"] == "INITIALIZING"
                                              for t in i["tasks"]))
            node = c.nodes()["fake"]  # the held attempt kept its cpu; the second got the new
            assert (node["total"]["cpu"], node["used"]["cpu"]) == (2, 2), node
            assert node["platforms"]["big"]["total"]["cpu"] == 2, node
        assert "Traceback" not in (c.osmo.home / "server.log").read_text()
    finally:
        c.stop()
