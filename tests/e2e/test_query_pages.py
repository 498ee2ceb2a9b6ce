"""Issue 16: ``osmo query`` of a big workflow shows a page of its tasks and the count per
status (``--limit``, ``--status``), through the real CLI and SDK; the SDK still fetches every
task when it asks for no limit.
"""

from __future__ import annotations

import json
from pathlib import Path

import osmo as sdk
from tests.conftest import Osmo, write

WIDTH = 30


def _spec(tmp_path: Path) -> Path:
    """A source, ``WIDTH`` tasks after it (one fails), in spec order w00..w29."""
    tasks = "".join(f"""
  - name: w{i:02d}
    inputs: [{{task: src}}]
    command: [sh, -c, "{'exit 3' if i == 7 else 'true'}"]
""" for i in range(WIDTH))
    return write(tmp_path / "wide.yaml", f"""
workflow:
  name: wide
  tasks:
  - name: src
    command: ["true"]{tasks}""")


def test_query_pages_a_workflow_and_counts_its_tasks(osmo: Osmo, tmp_path: Path) -> None:
    r = osmo("submit", str(_spec(tmp_path)), "--wait", timeout=180)
    assert r.code == 1, r.out + r.err
    wf = r.out.splitlines()[0].split(" - ")[1]

    page = osmo("query", wf, "--limit", "5", check=True).out
    rows = [line.split()[0] for line in page.splitlines() if line.startswith(("src", "w"))]
    assert rows == ["src", "w00", "w01", "w02", "w03"]  # spec order, the first 5
    assert ("26 more task(s) not shown (--limit N, --status S); tasks by status: "
            "COMPLETED 30, FAILED 1") in page

    failed = osmo("query", wf, "--status", "failed", check=True).out
    assert [line.split()[0] for line in failed.splitlines() if line.startswith("w")] == ["w07"]
    assert "tasks by status: COMPLETED 30, FAILED 1" in failed
    assert "not shown" not in failed

    data = json.loads(osmo("query", wf, "--format", "json", "--limit", "2", check=True).out)
    assert [t["name"] for t in data["tasks"]] == ["src", "w00"]
    assert data["counts"] == {"COMPLETED": 30, "FAILED": 1} and data["matched"] == 31

    whole = json.loads(osmo("query", wf, "--format", "json", check=True).out)
    assert len(whole["tasks"]) == WIDTH + 1 and "counts" not in whole  # as before: all of it

    table = osmo("query", wf, check=True).out  # a small workflow: the whole table, no count
    assert sum(line.startswith("w") for line in table.splitlines()) == WIDTH
    assert "tasks by status" not in table

    with sdk.Client(home=osmo.home) as client:
        info = client.get(wf, limit=3, statuses=["COMPLETED"])
        assert [t.name for t in info.tasks] == ["src", "w00", "w01"]
        assert info.not_shown == 27 and info.counts == {"COMPLETED": 30, "FAILED": 1}
        assert len(client.get(wf).tasks) == WIDTH + 1


def test_query_refuses_a_bad_status_or_limit(osmo: Osmo, tmp_path: Path) -> None:
    wf = osmo.submit(write(tmp_path / "one.yaml", """
workflow:
  name: one
  tasks:
  - name: t
    command: ["true"]
"""))
    bad = osmo("query", wf, "--status", "BOGUS")
    assert bad.code == 2 and "unknown task status 'BOGUS'" in bad.err, bad.err
    assert "Traceback" not in bad.err
    negative = osmo("query", wf, "--limit", "-1")
    assert negative.code == 2 and "--limit must be 0 or more" in negative.err, negative.err
    with sdk.Client(home=osmo.home) as client:
        try:
            client.get(wf, limit=-5)
        except sdk.OsmoError as exc:
            assert "0 or more" in str(exc)
        else:
            raise AssertionError("a negative limit was accepted")
