"""A node whose attempts outlive it (a cluster's jobs, pods) is away, not down: nobody else
may claim its id, and so its attempts, meanwhile (issue 29 item 6, issue 28 item 5).

A fake node registers as one whose attempts outlive it, is placed an attempt, and goes (its
session closes: its liveliness token goes). An attacker with another worker token then tries
to register the same id and to speak for the attempt: both refused while the node is away.
The node itself comes back with the same token, says it still runs the attempt, and is told
the server still places it there.
"""

from __future__ import annotations

import time
from pathlib import Path

import pytest

from osmo.errors import NotAllowed
from osmo.transport.rpc import ApiClient
from osmo.transport.zenoh_link import Link
from tests.conftest import write
from tests.e2e.cluster import Cluster

NODE = {"id": "victim", "pool": "default", "address": "127.0.0.1",
        "capacity": {"cpu": 1}, "outlives": True}


def _node(c: Cluster, token: str, **extra: object) -> tuple[Link, ApiClient, dict]:
    link = Link.client([c.endpoint], "local")
    api = ApiClient(link, timeout=10, token=token)
    reply = api.call("worker_register", {**NODE, **extra})
    return link, api, reply


def test_an_away_node_s_id_and_attempts_cannot_be_claimed_by_another_token(
        tmp_path: Path) -> None:
    c = Cluster(tmp_path, server_args=("--adopt-grace", "120"))
    c.start_server()
    links: list[Link] = []
    try:
        link, _, _ = _node(c, c.token("victim"))
        links.append(link)
        alive = link.token(link.key("alive", "worker", "victim"))
        spec = write(tmp_path / "wf.yaml", """
workflow:
  name: held
  tasks:
  - name: t
    command: [sh, -c, "sleep 600"]
""")
        wf = c.osmo.submit(spec)
        aid = f"{wf}:t:0"
        deadline = time.monotonic() + 30
        while c.osmo.query(wf)["tasks"][0].get("node") != "victim":
            assert time.monotonic() < deadline, c.osmo.query(wf)
            time.sleep(0.1)
        before = c.osmo.query(wf)["tasks"][0]
        alive.close()
        link.close()  # the node goes, as a SIGKILLed one does
        links.remove(link)
        time.sleep(1.5)  # its token's loss is seen

        attacker_link = Link.client([c.endpoint], "local")
        links.append(attacker_link)
        attacker = ApiClient(attacker_link, timeout=10, token=c.token("attacker"))
        with pytest.raises(NotAllowed, match="registered with another token"):
            attacker.call("worker_register", NODE)
        for verb, request in (("worker_report", {"id": "victim", "report": {
                                  "op": "exited", "attempt_id": aid, "exit_code": 0}}),
                              ("worker_secrets", {"id": "victim", "attempt_id": aid})):
            with pytest.raises(NotAllowed):
                attacker.call(verb, request)
        held = c.osmo.query(wf)["tasks"][0]
        assert (held["status"], held["node"], held["retry"]) == (
            before["status"], "victim", 0), held

        back, _, reply = _node(c, c.token("victim"), active=[aid])
        links.append(back)
        assert reply.get("placed") == [aid], reply
        assert c.osmo.query(wf)["tasks"][0]["node"] == "victim"
        assert "is gone; its attempts outlive it" in (c.osmo.home / "server.log").read_text()
        c.osmo("workflow", "cancel", wf)
    finally:
        for made in links:
            made.close()
        c.stop()
