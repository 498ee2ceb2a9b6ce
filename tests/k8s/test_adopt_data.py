"""A node whose pods fetch and send back their own data (the pool's ``data``) is killed and
restarted: its pods are adopted (their collectors wait for the node, then send the output
once, whole), and a pod whose journaled tickets were tampered with is deleted and run again.
The chaos run: a workflow of serial and parallel tasks, the node killed while two pods run.

Each test SIGKILLs the in-cluster node mid-run and starts it again on the same home (the
chart's emptyDir home survives a worker container's restart).
"""

from __future__ import annotations

import json
import signal
import time
from collections.abc import Iterator
from pathlib import Path

import pytest

from tests.containers.conftest import images, podman_env  # noqa: F401 - fixtures
from tests.containers.images import KINDS_OSMO, OSMO_IMAGE, ensure_images
from tests.containers.submitting import osmo_lines, task_lines
from tests.k8s.nodes import KubeCluster, started
from tests.k8s.store import PODS

NODE = "kube-data"
SLOW = """\
workflow:
  name: slow-data
  tasks:
  - name: slow
    image: alpine:3.18
    command: ["sh", "-c", "echo started; sleep 15; mkdir -p {{output}}/d; \
echo survived > {{output}}/d/x; echo done"]
"""


@pytest.fixture(scope="module")
def kube(tmp_path_factory: pytest.TempPathFactory, podman_env: dict[str, str],  # noqa: F811
         images: dict[str, str]) -> Iterator[KubeCluster]:  # noqa: F811
    ensure_images(podman_env, KINDS_OSMO)
    for cluster in started(tmp_path_factory.mktemp("k8s"), podman_env):
        start(cluster)
        yield cluster


def start(kube: KubeCluster) -> None:
    """The data pool's node (again, on the same home)."""
    kube.start_worker(NODE, pool="data", groupNetwork="host", data={"image": OSMO_IMAGE})


def nothing_left(kube: KubeCluster, timeout: float = 20) -> list[str]:
    deadline = time.monotonic() + timeout
    while (left := kube.left()) and time.monotonic() < deadline:
        time.sleep(0.2)
    return left


def kill_while_running(kube: KubeCluster, tmp_path: Path) -> tuple[str, dict]:
    """Submit SLOW, SIGKILL the node once its task started; the workflow id and its pod."""
    spec = tmp_path / "slow.yaml"
    spec.write_text(SLOW)
    wf_id = kube.osmo.submit(spec, "--pool", "data", "--no-cache")
    deadline = time.monotonic() + 120
    while "started" not in task_lines(kube.osmo, wf_id).get("slow", []):
        said = osmo_lines(kube.osmo, wf_id, "slow")
        assert time.monotonic() < deadline and not any("FAILED" in s for s in said), said
        time.sleep(0.2)
    (pod,) = [obj for _, obj in kube.server.store.objects([PODS])]
    kube.osmo_cluster.signal(NODE, signal.SIGKILL)
    kube.osmo_cluster.workers[NODE].wait(30)
    return wf_id, pod


def test_a_killed_node_adopts_its_data_pod_which_sends_its_output_once(
        kube: KubeCluster, tmp_path: Path) -> None:
    """Killed while the collector waits for the task's end: the restarted node adopts the
    pod (never created again), the collector reaches it and sends the output whole."""
    created = kube.server.writes[("create", "pods")]
    wf_id, pod = kill_while_running(kube, tmp_path)
    start(kube)
    info = kube.osmo.wait_for(wf_id, lambda i: i["status"] in ("COMPLETED", "FAILED"),
                              timeout=180)
    log = kube.osmo_cluster.worker_log(NODE)
    assert info["status"] == "COMPLETED", (info, log)
    row = info["tasks"][0]
    assert row["retry"] == 0, row
    assert (Path(row["output"]) / "d" / "x").read_text() == "survived\n"
    assert sorted(p.name for p in Path(row["output"]).rglob("*")) == ["d", "x"]
    assert kube.server.writes[("create", "pods")] == created + 1, "one pod, never made again"
    assert task_lines(kube.osmo, wf_id)["slow"] == ["started", "done"]
    said = osmo_lines(kube.osmo, wf_id, "slow")
    assert any(f"adopted by node {NODE} after its restart" in line for line in said), said
    assert f"cancelled pod/{pod['metadata']['name']}" not in log, log
    assert nothing_left(kube) == []


def test_a_tampered_ticket_record_is_refused_and_its_pod_runs_again(
        kube: KubeCluster, tmp_path: Path) -> None:
    """Hostile: the journaled ticket of the pod (its digest) altered while the node was
    down: the node does not adopt it; the pod is deleted and the attempt runs again."""
    created = kube.server.writes[("create", "pods")]
    wf_id, pod = kill_while_running(kube, tmp_path)
    records = list((kube.osmo_cluster.root / NODE).rglob("pod.json"))
    assert len(records) == 1, records
    record = json.loads(records[0].read_text())
    digest = record["data"]["collect"]
    record["data"]["collect"] = ("0" if digest[0] != "0" else "1") + digest[1:]
    records[0].write_text(json.dumps(record))
    start(kube)
    info = kube.osmo.wait_for(wf_id, lambda i: i["status"] in ("COMPLETED", "FAILED"),
                              timeout=240)
    log = kube.osmo_cluster.worker_log(NODE)
    assert info["status"] == "COMPLETED", (info, log)
    row = info["tasks"][0]
    assert (Path(row["output"]) / "d" / "x").read_text() == "survived\n"
    assert kube.server.writes[("create", "pods")] == created + 2, "deleted and made again"
    assert f"cancelled pod/{pod['metadata']['name']}" in log, log
    assert "tickets" in log and "could not adopt" in log, log
    assert nothing_left(kube) == []


MIXED = """\
workflow:
  name: mixed
  tasks:
  - name: first
    image: alpine:3.18
    command: ["sh", "-c", "echo one > {{output}}/one.txt"]
  - name: left
    image: alpine:3.18
    command: ["sh", "-c", "echo started; sleep 20; sed s/one/left/ {{input:0}}/one.txt \
> {{output}}/l.txt"]
    inputs:
    - task: first
  - name: right
    image: alpine:3.18
    command: ["sh", "-c", "echo started; sleep 20; sed s/one/right/ {{input:0}}/one.txt \
> {{output}}/r.txt"]
    inputs:
    - task: first
  - name: last
    image: alpine:3.18
    command: ["sh", "-c", "cat {{input:0}}/l.txt {{input:1}}/r.txt"]
    inputs:
    - task: left
    - task: right
"""


def test_chaos_a_node_killed_mid_run_leaves_nothing_and_loses_nothing(
        kube: KubeCluster, tmp_path: Path) -> None:
    """Chaos (#28): kill -9 of the in-cluster node while two parallel pods run (after a
    serial one), restarted: every pod is adopted or deleted, every task's output and log is
    whole, and no pod or Secret is left behind."""
    created = kube.server.writes[("create", "pods")]
    spec = tmp_path / "mixed.yaml"
    spec.write_text(MIXED)
    wf_id = kube.osmo.submit(spec, "--pool", "data", "--no-cache")
    deadline = time.monotonic() + 120
    while not all("started" in task_lines(kube.osmo, wf_id).get(t, []) for t in ("left",
                                                                                 "right")):
        assert time.monotonic() < deadline, kube.osmo.query(wf_id)
        time.sleep(0.2)
    kube.osmo_cluster.signal(NODE, signal.SIGKILL)
    kube.osmo_cluster.workers[NODE].wait(30)
    start(kube)
    info = kube.osmo.wait_for(wf_id, lambda i: i["status"] in ("COMPLETED", "FAILED"),
                              timeout=180)
    assert info["status"] == "COMPLETED", (info, kube.osmo_cluster.worker_log(NODE))
    rows = {row["name"]: row for row in info["tasks"]}
    assert {name: row["retry"] for name, row in rows.items()} == dict.fromkeys(
        ("first", "left", "right", "last"), 0)
    assert kube.server.writes[("create", "pods")] == created + 4, "each pod made once"
    lines = task_lines(kube.osmo, wf_id)
    assert lines["last"] == ["left", "right"], lines
    assert lines["left"] == lines["right"] == ["started"], lines
    for name in ("left", "right"):
        said = osmo_lines(kube.osmo, wf_id, name)
        assert any("adopted by node" in line for line in said), said
    assert nothing_left(kube) == []
