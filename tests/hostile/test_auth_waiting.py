"""A worker's waiting reason is hostile text, about its own attempts only (issues #28, #29).

A fake worker (a valid worker token, registered with room for one task) is given an
attempt. It reports why the attempt waits: a reason of 100,000 characters full of terminal
escapes, line breaks and bidirectional overrides is kept as one short line of plain text
in ``osmo query`` and ``osmo events``; a reason for an attempt not placed on it (another
retry, an attempt of nobody) is refused and logged; the same reason again is not a new
event; an empty reason (it runs) clears it.
"""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from osmo.errors import NotAllowed
from osmo.transport.rpc import ApiClient
from tests.conftest import write
from tests.e2e.cluster import Cluster

FAKE = {"id": "fake", "pool": "default", "address": "127.0.0.1",
        "capacity": {"cpu": 4, "memory": 8 << 30, "storage": 100 << 30}}
EVIL = ("Insufficient cpu\x1b]0;pwned\x07\x1b[2J\r\nERROR forged line\u202e" + "A" * 100_000)


def _spec(tmp: Path) -> Path:
    return write(tmp / "w.yaml", """
workflow:
  name: w
  tasks:
  - name: t
    command: [sh, -c, "true"]
""")


def _wait(fake: ApiClient, aid: str, reason: str) -> None:
    fake.call("worker_beat", {"id": "fake"})  # within the lease, however slow the test
    fake.call("worker_report", {"id": "fake", "report": {"op": "waiting", "attempt_id": aid,
                                                         "reason": reason}})


def test_a_hostile_reason_is_one_bounded_line_and_only_for_its_own_attempt(
        tmp_path: Path) -> None:
    c = Cluster(tmp_path)
    c.start_server()
    try:
        with c.fake_worker(FAKE) as fake:  # its liveliness token held: placed on
            _waiting_is_one_line_of_its_own(c, fake, tmp_path)
    finally:
        c.stop()


def _waiting_is_one_line_of_its_own(c: Cluster, fake: ApiClient, tmp_path: Path) -> None:
    wf = c.osmo.submit(_spec(tmp_path))
    c.osmo.wait_for(wf, lambda i: i["tasks"][0]["status"] == "INITIALIZING")
    aid = f"{wf}:t:0"
    for other in (f"{wf}:t:1", "nobody:t:0"):
        with pytest.raises(NotAllowed, match="is not placed on worker fake"):
            _wait(fake, other, "Priority")
    fake.call("worker_report", {"id": "fake", "report": {"op": "started",
                                                         "attempt_id": aid}})
    _wait(fake, aid, EVIL)
    _wait(fake, aid, EVIL)  # the same again: no new event
    info = c.osmo.wait_for(wf, lambda i: i["tasks"][0].get("waiting") is not None,
                           timeout=30)
    task = info["tasks"][0]
    shown = task["waiting"]["reason"]
    assert shown.startswith("Insufficient cpu ]0;pwned [2J ERROR forged line AAA"), shown
    assert shown.endswith("...") and len(shown) == 300
    assert task["status"] == "RUNNING" and task["message"] == f"waiting: {shown}"
    events = json.loads(c.osmo("events", wf, "--format", "json", check=True).out)
    said = [e["message"] for e in events if e["task"] == "t"
            and e["message"].startswith("waiting:")]
    assert said == [f"waiting: {shown}"]
    for args in (("query", wf), ("events", wf), ("query", wf, "-v")):
        out = c.osmo(*args, check=True).out
        assert "Insufficient cpu" in out, out
        assert not any(ch in out for ch in "\x1b\x07\r\u202e"), repr(out)
        assert "\nERROR forged line" not in out
    _wait(fake, aid, "")  # it runs now
    info = c.osmo.wait_for(wf, lambda i: i["tasks"][0].get("waiting") is None, timeout=30)
    assert info["tasks"][0]["message"] == ""
    assert "waits no more" in c.osmo("events", wf, check=True).out
    refused = (c.osmo.home / "server.log").read_text()
    assert refused.count("refused 'worker_report' from fake (worker)") == 2
