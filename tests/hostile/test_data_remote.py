"""The same guarantees on a remote worker (it runs tasks with the same LocalPool): a deep
output fails clearly and frees its slot, byte names round-trip through the worker and the
server, and a task writing to its input changes nobody else's (issue 11, items 1, 2, 5)."""

from __future__ import annotations

import json
import os
from collections.abc import Iterator
from pathlib import Path

import pytest

from osmo.artifacts.fsops import remove_tree
from osmo.status import ExitCode
from tests.conftest import write
from tests.e2e.cluster import Cluster
from tests.hostile.datarun import finished, tasks

SPEC = r"""
workflow:
  name: remote
  resources:
    default: {cpu: 1}
  tasks:
  - name: deep
    command: [python3, -c, "import os\nos.chdir(os.environ['OSMO_OUTPUT'])\nfor _ in range(2100):\n  os.mkdir('d'); os.chdir('d')"]
  - name: names
    command: [python3, -c, "import os\nopen(os.environb[b'OSMO_OUTPUT'] + b'/caf\\xe9.csv', 'wb').write(b'x')"]
  - name: tamper
    inputs: [{task: names}]
    command: [sh, -c, "echo more >> {{input:0}}/caf*; echo ok > {{output}}/ok"]
  - name: read
    inputs: [{task: tamper}, {task: names}]
    command: [sh, -c, "cat {{input:names}}/caf* > {{output}}/seen"]
"""


@pytest.fixture
def cluster(tmp_path: Path) -> Iterator[Cluster]:
    c = Cluster(tmp_path)
    c.start_server()
    yield c
    c.stop()
    for child in tmp_path.iterdir():  # the deep tree: pytest's own cleanup would recurse
        remove_tree(child, ignore_errors=True)


def test_a_remote_worker_keeps_the_same_guarantees(cluster: Cluster, tmp_path: Path) -> None:
    cluster.start_worker("w1", "--cpus", "2", host="other-host")  # blobs travel by zenoh
    wf = finished(cluster.osmo, write(tmp_path / "r.yaml", SPEC), code=1)
    by_name = tasks(cluster.osmo, wf)
    deep = by_name["deep"]
    assert deep["status"] == "FAILED" and deep["exit_code"] == ExitCode.OUTPUT_ERROR, deep
    assert "nested too deep" in deep["message"]
    assert [t["status"] for n, t in by_name.items() if n != "deep"] == ["COMPLETED"] * 3
    got = tmp_path / "got"
    cluster.osmo("artifacts", "get", f"{wf}:read", "-o", str(got), check=True)
    assert (got / "seen").read_bytes() == b"x"  # the original, not the tampered copy
    cluster.osmo("artifacts", "get", f"{wf}:names", "-o", str(got / "n"), check=True)
    assert os.listdir(os.fsencode(got / "n")) == [b"caf\xe9.csv"]
    nodes = json.loads(cluster.osmo("resource", "list", "--format", "json", check=True).out)
    assert [n["used"]["cpu"] for n in nodes] == [0]
