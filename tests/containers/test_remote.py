"""A remote ``osmo worker --runtime container`` runs image tasks through the same pool code;
after a ``kill -9`` of the worker, the restarted worker removes what its containers left.

The task is quiet until it ends: a container that writes after its worker died gets SIGPIPE
through the engine CLI's signal proxy and ends by itself; a quiet one outlives the worker,
which is the case the restart must clean up.
"""

from __future__ import annotations

import json
import signal
import time
from collections.abc import Iterator
from pathlib import Path

import pytest

from osmo.runtime.container import ContainerEngine
from osmo.worker.containers import owner_id
from tests.conftest import ended, write
from tests.containers.submitting import leftovers, task_lines, tasks
from tests.e2e.cluster import Cluster

SPEC = """
workflow:
  name: remote-box
  tasks:
  - name: boxed
    image: alpine:3.18
    command: [sh, -c, "sleep 4; echo in $(hostname); echo $OSMO_NODE > {{output}}/node"]
"""


@pytest.fixture
def cluster(podman_env: dict[str, str], images: dict[str, str], engine: ContainerEngine,
            tmp_path: Path) -> Iterator[Cluster]:
    c = Cluster(tmp_path, env={"CONTAINERS_CONF": podman_env["CONTAINERS_CONF"]})
    c.start_server()
    yield c
    c.stop()
    labels = {"osmo.owner": owner_id(tmp_path / "w1" / "worker")}
    assert leftovers(engine, labels) == ([], [])


def test_a_remote_worker_runs_a_container_and_cleans_up_after_a_kill_9(
        cluster: Cluster, engine: ContainerEngine, tmp_path: Path) -> None:
    cluster.start_worker("w1", "--runtime", "container", "--cpus", "2")
    node = cluster.nodes()["w1"]
    assert node["runtime"].startswith("container (podman ")
    wf = cluster.osmo.submit(write(tmp_path / "wf.yaml", SPEC))
    labels = {"osmo.owner": owner_id(tmp_path / "w1" / "worker"), "osmo.workflow": wf}
    deadline = time.monotonic() + 60
    while not engine.running(labels):
        assert time.monotonic() < deadline, cluster.worker_log("w1")
        time.sleep(0.1)
    cluster.signal("w1", signal.SIGKILL)
    cluster.workers["w1"].wait(timeout=30)
    time.sleep(0.5)
    assert engine.containers(labels), "its container outlives the worker (nothing else kills)"
    cluster.start_worker("w1", "--runtime", "container", "--cpus", "2")
    deadline = time.monotonic() + 60
    while not (running := engine.running(labels)):
        assert time.monotonic() < deadline, cluster.worker_log("w1")
        time.sleep(0.1)
    ident = running[0]
    info = cluster.osmo.wait_for(wf, ended, timeout=120)
    assert info["status"] == "COMPLETED", json.dumps(info)
    boxed = tasks(cluster.osmo, wf)["boxed"]
    assert boxed["retry"] == 1
    assert Path(boxed["output"], "node").read_text().strip() == "w1"
    assert task_lines(cluster.osmo, wf)["boxed"] == [f"in {ident[:12]}"]  # in its container
