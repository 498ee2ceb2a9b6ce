"""docs/reference/spec.md, Spec decisions → Why a task waits: "`osmo query` shows why each waiting task waits"
and "a task waits at most 30 minutes on a pool with no online worker".

A real server with one remote worker of one cpu in pool 'gpu': the second task waits for a
free cpu; after the worker is SIGKILLed, both wait for a worker, since the moment it left,
and say when they will fail.
"""

from __future__ import annotations

import signal
import time
from pathlib import Path

import pytest

from osmo.scheduler import DEFAULT_NO_WORKER_TIMEOUT
from tests.conftest import write
from tests.e2e.cluster import Cluster


def test_query_says_why_each_task_waits(tmp_path: Path) -> None:
    cluster = Cluster(tmp_path, env={"OSMO_HOST_ID": "shared-host"})
    go = tmp_path / "go"  # the tasks end once it exists (also one left by its killed worker)
    try:
        cluster.start_server()
        cluster.start_worker("w1", "--cpus", "1", pool="gpu")
        _check_reasons(cluster, tmp_path, go)
    finally:
        go.touch()
        cluster.stop()


def _check_reasons(cluster: Cluster, tmp_path: Path, go: Path) -> None:
    wait = f"while [ ! -e {go} ]; do sleep 0.05; done"
    spec = write(tmp_path / "wf.yaml", f"""
workflow:
  name: stuck
  tasks:
  - name: a
    command: [sh, -c, "{wait}"]
  - name: b
    command: [sh, -c, "{wait}"]
  - name: c
    command: ["true"]
    inputs: [{{task: a}}]
""")
    wf = cluster.osmo.submit(spec, "--pool", "gpu")
    info = cluster.osmo.wait_for(wf, lambda i: "RUNNING" in _statuses(i).values())
    waiting = {t["name"]: t.get("waiting") for t in info["tasks"]}
    [running] = [n for n, s in _statuses(info).items() if s == "RUNNING"]
    other = "b" if running == "a" else "a"
    assert waiting[running] is None
    assert waiting[other] == {"reason": "needs 1 cpu, largest free is 0", "since": None,
                              "fails_at": None}
    assert waiting["c"]["reason"] == "waits for upstream 'a' to complete"
    text = cluster.osmo("query", wf, check=True).out
    assert "Waiting For" in text and "needs 1 cpu, largest free is 0" in text, text

    killed_at = time.time()
    cluster.signal("w1", signal.SIGKILL)
    info = cluster.osmo.wait_for(wf, lambda i: _statuses(i)["a"] == _statuses(i)["b"]
                                 == "SCHEDULING", timeout=60)
    for name in ("a", "b"):
        got = next(t for t in info["tasks"] if t["name"] == name)["waiting"]
        assert got["reason"] == "pool 'gpu' has no online worker", got
        assert killed_at - 1 <= got["since"] <= time.time()
        assert got["fails_at"] == pytest.approx(got["since"] + DEFAULT_NO_WORKER_TIMEOUT)
    text = cluster.osmo("query", wf, check=True).out
    assert "pool 'gpu' has no online worker since " in text and "fails at " in text, text


def _statuses(info: dict) -> dict[str, str]:
    return {t["name"]: t["status"] for t in info["tasks"]}
