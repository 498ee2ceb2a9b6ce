"""docs/concepts/durability.md, Retries: "the default cap is 3 RESCHEDULE retries per task" and "an
attempt lost to a crashed server or worker is rescheduled separately (up to 5 times)".

Both caps are checked at a real server that was given neither value: the workflow names no
``maxRetries``, and the server runs with its defaults.
"""

from __future__ import annotations

import contextlib
import os
import signal
from collections.abc import Iterator
from pathlib import Path

import pytest

from tests.conftest import Osmo, ended, host_pid, write
from tests.e2e.cluster import Cluster


def test_reschedule_retries_default_to_three(osmo: Osmo, tmp_path: Path) -> None:
    runs = tmp_path / "runs"
    spec = write(tmp_path / "wf.yaml", f"""
workflow:
  name: flaky-forever
  tasks:
  - name: flaky
    command: [sh, -c, "echo x >> {runs}; exit 42"]
    exitActions:
      RESCHEDULE: 42
""")
    r = osmo("submit", str(spec), "--wait")
    assert r.code == 1, r.out + r.err
    task = osmo.query(r.out.splitlines()[0].split(" - ")[1])["tasks"][0]
    assert (task["status"], task["retry"], task["exit_code"]) == ("FAILED", 3, 42), task
    assert "retry cap 3 reached" in task["message"]
    assert runs.read_text().count("x") == 4  # the first run and three retries


@pytest.fixture
def cluster(tmp_path: Path) -> Iterator[Cluster]:
    c = Cluster(tmp_path, env={"OSMO_HOST_ID": "shared-host"})
    c.start_server()
    yield c
    c.stop()


def test_lost_attempts_are_capped_at_five(cluster: Cluster, tmp_path: Path) -> None:
    """Six workers; the task's worker is SIGKILLed each time the task runs. Five losses are
    rescheduled; the sixth fails the task (FAILED_SERVER_ERROR, exit code 3006)."""
    workers = [f"w{i}" for i in range(6)]
    for name in workers:
        cluster.start_worker(name, "--cpus", "1", wait=False)
    for name in workers:
        cluster.wait_online(name)
    spec = write(tmp_path / "wf.yaml", f"""
workflow:
  name: unlucky
  tasks:
  - name: t
    command: [sh, -c, "echo $$ >> {tmp_path}/pids; exec sleep 600"]
""")
    wf = cluster.osmo.submit(spec)
    try:
        for retry in range(6):
            info = cluster.osmo.wait_for(wf, lambda i, r=retry: ended(i) or (
                i["tasks"][0]["retry"] == r and i["tasks"][0]["status"] == "RUNNING"))
            if ended(info):
                break  # ended too early: the assertions below say how
            cluster.signal(info["tasks"][0]["node"], signal.SIGKILL)
        info = cluster.osmo.wait_for(wf, ended)
    finally:
        _kill_orphans(tmp_path / "pids")
    task = info["tasks"][0]
    assert info["status"] == "FAILED_SERVER_ERROR", info
    assert (task["status"], task["retry"], task["exit_code"]) == (
        "FAILED_SERVER_ERROR", 5, 3006), task
    assert "lost-attempt cap 5 reached" in task["message"]


def _kill_orphans(pids: Path) -> None:
    """A task outlives a SIGKILLed worker (see the report of issue 19): kill what the test
    started, by the pids the tasks wrote."""
    if not pids.exists():
        return
    for line in pids.read_text().split():
        pid = host_pid(int(line), str(pids.parent))  # a sandboxed task's $$ is its own
        if pid is not None:
            with contextlib.suppress(ProcessLookupError):
                os.kill(pid, signal.SIGKILL)
