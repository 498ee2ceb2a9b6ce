"""Nothing outlives its workflow when an in-cluster node never comes back: once its grace
ended, the server orders a live node of its pool to delete what it left (``wire.Sweep``,
``osmo.server.sweeps``), and the attempt runs again there. A live node's objects stay. The
server keeps what nodes label their objects with in its store: a node gone while the server
restarts is swept too.
"""

from __future__ import annotations

import os
import signal
import time
from collections.abc import Iterator
from pathlib import Path

import pytest
from kubernetes import client

from osmo.runtime.container.runtime import owner_id
from tests.conftest import wait_gone
from tests.containers.conftest import images, podman_env  # noqa: F401 - fixtures
from tests.containers.images import KINDS_OSMO, OSMO_IMAGE, ensure_images
from tests.containers.submitting import task_lines
from tests.k8s.nodes import NAMESPACE, KubeCluster, started
from tests.k8s.store import NODES, PODS, SECRETS, SERVICES

GRACE = 4.0  # for the server's restart
ADOPT_GRACE = 8.0  # for a node gone: long enough to see it listed away
SLOW = """\
workflow:
  name: never-back
  tasks:
  - name: slow
    image: alpine:3.18
    command: ["sh", "-c", "echo started; sleep 25; echo ran > {{output}}/x; echo done"]
"""


@pytest.fixture(scope="module")
def kube(tmp_path_factory: pytest.TempPathFactory, podman_env: dict[str, str],  # noqa: F811
         images: dict[str, str]) -> Iterator[KubeCluster]:  # noqa: F811
    ensure_images(podman_env, KINDS_OSMO)
    yield from started(tmp_path_factory.mktemp("k8s"), podman_env,
                       server_args=("--adopt-grace", str(ADOPT_GRACE),
                                    "--reconnect-grace", str(GRACE)))


def start(kube: KubeCluster, name: str, pool: str = "data") -> None:
    kube.start_worker(name, pool=pool, groupNetwork="host", data={"image": OSMO_IMAGE})


def service(kube: KubeCluster, name: str, instance: str) -> None:
    """A group Service of ``instance`` (as a gang's lead node makes it)."""
    with client.ApiClient(client.Configuration(host=kube.server.url)) as api:
        client.CoreV1Api(api).create_namespaced_service(NAMESPACE, {
            "metadata": {"name": name, "namespace": NAMESPACE,
                         "labels": {"osmo.dev/instance": instance,
                                    "osmo.dev/group": name}},
            "spec": {"clusterIP": "None", "selector": {"osmo.dev/group": name}}})


def names(kube: KubeCluster) -> set[str]:
    return {f"{res.kind}/{obj['metadata']['name']}"
            for res, obj in kube.server.store.objects([PODS, SECRETS, SERVICES])}


def running_slow(kube: KubeCluster, tmp_path: Path, pool: str) -> tuple[str, dict]:
    """Submit SLOW to ``pool``; its workflow id and pod once its task said it started."""
    spec = tmp_path / "slow.yaml"
    spec.write_text(SLOW)
    before = {obj["metadata"]["name"] for _, obj in kube.server.store.objects([PODS])}
    wf_id = kube.osmo.submit(spec, "--pool", pool, "--no-cache")
    deadline = time.monotonic() + 120
    while "started" not in task_lines(kube.osmo, wf_id).get("slow", []):
        assert time.monotonic() < deadline, (kube.left(), kube.osmo.query(wf_id))
        time.sleep(0.2)
    (pod,) = [obj for _, obj in kube.server.store.objects([PODS])
              if obj["metadata"]["name"] not in before]
    return wf_id, pod


def test_a_node_that_never_comes_back_leaves_nothing_after_its_grace(
        kube: KubeCluster, tmp_path: Path) -> None:
    start(kube, "kube-gone")
    wf_id, pod = running_slow(kube, tmp_path, "data")
    gone = pod["metadata"]["labels"]["osmo.dev/instance"]
    service(kube, "osmo-wf-gone-gang", gone)
    left = names(kube)
    assert len(left) == 3 and {k.split("/")[0] for k in left} == {"Pod", "Secret", "Service"}
    kube.osmo_cluster.signal("kube-gone", signal.SIGKILL)  # never started again
    kube.osmo_cluster.workers["kube-gone"].wait(30)
    statuses = []  # osmo resource list shows it away (no capacity) until its grace ends
    deadline = time.monotonic() + ADOPT_GRACE + 30
    while "kube-gone" in (listed := kube.osmo_cluster.nodes()):
        assert time.monotonic() < deadline, statuses
        statuses.append((listed["kube-gone"]["status"], listed["kube-gone"]["total"]["cpu"]))
        time.sleep(0.2)
    assert ("away", 0) in statuses, statuses
    start(kube, "kube-live")  # within the grace or after it: it sweeps (ordered by the server)
    mine = owner_id(kube.osmo_cluster.root / "kube-live")  # the live node's instance label
    service(kube, "osmo-wf-live-gang", mine)
    info = kube.osmo.wait_for(wf_id, lambda i: i["status"] in ("COMPLETED", "FAILED"),
                              timeout=180)
    log = kube.osmo_cluster.worker_log("kube-live")
    assert info["status"] == "COMPLETED", (info, log)
    row = info["tasks"][0]
    assert row["node"] == "kube-live", row  # lost with its node, run again on the live one
    assert (Path(row["output"]) / "x").read_text() == "ran\n"
    deadline = time.monotonic() + 30
    while left & names(kube):
        assert time.monotonic() < deadline, (names(kube), log)
        time.sleep(0.2)
    assert f"deleted pod/{pod['metadata']['name']} that node instance {gone} left" in \
        kube.osmo_cluster.worker_log("kube-live")
    assert kube.server.writes[("create", "pods")] == 2
    assert names(kube) == {"Service/osmo-wf-live-gang"}  # a live node's object stays
    kube.server.store.delete(SERVICES, NAMESPACE, "osmo-wf-live-gang")


def test_a_node_gone_while_the_server_restarts_is_swept_by_the_new_server(
        kube: KubeCluster, tmp_path: Path) -> None:
    """The node and the server are killed together (kill -9): the new server knows the
    node's instance from its store, and once the node's grace ended it has a live node of
    its pool delete the pod still running there, while the attempt runs again."""
    start(kube, "kube-gone-2", pool="data2")
    wf_id, pod = running_slow(kube, tmp_path, "data2")
    gone = pod["metadata"]["labels"]["osmo.dev/instance"]
    kube.osmo_cluster.signal("kube-gone-2", signal.SIGKILL)  # never started again
    kube.osmo_cluster.workers["kube-gone-2"].wait(30)
    server = kube.osmo.server_pid()
    assert server is not None
    os.kill(server, signal.SIGKILL)
    wait_gone(server)
    kube.osmo_cluster.start_server()
    start(kube, "kube-live-2", pool="data2")
    deadline = time.monotonic() + 60
    name = pod["metadata"]["name"]
    while name in {obj["metadata"]["name"] for _, obj in kube.server.store.objects([PODS])}:
        assert time.monotonic() < deadline, (kube.left(), kube.osmo_cluster.worker_log(
            "kube-live-2"))
        time.sleep(0.2)
    said = f"deleted pod/{name} that node instance {gone} left"
    while said not in kube.osmo_cluster.worker_log("kube-live-2"):  # logged after the deletes
        assert time.monotonic() < deadline, kube.osmo_cluster.worker_log("kube-live-2")
        time.sleep(0.2)
    info = kube.osmo.wait_for(wf_id, lambda i: i["tasks"][0].get("node") == "kube-live-2",
                              timeout=60)  # lost with its node, run again on the live one
    assert info["status"] == "RUNNING", info
    kube.osmo("cancel", wf_id, check=True)
    kube.osmo.wait_for(wf_id, lambda i: i["status"] != "RUNNING", timeout=60)
    deadline = time.monotonic() + 30
    while any(k.startswith("Pod/") for k in kube.left()):
        assert time.monotonic() < deadline, kube.left()
        time.sleep(0.2)


def test_a_node_offers_what_its_cluster_has_now(kube: KubeCluster) -> None:
    """A Kubernetes node added after the worker registered (or removed) changes what the
    worker offers, and its platforms, within ``--capacity-every``: shown by osmo resource
    list, used by the scheduler."""
    kube.start_worker("kube-grow", "--capacity-every", "0.5", pool="grow",
                      groupNetwork="host", data={"image": OSMO_IMAGE},
                      platforms={"big": {"nodeSelector": {"osmo.dev/test-kind": "big"}}})

    def offered() -> tuple[float, dict[str, float]]:
        node = kube.osmo_cluster.nodes()["kube-grow"]
        return node["total"]["cpu"], {name: p["total"]["cpu"]
                                      for name, p in node["platforms"].items()}

    def until(expected: tuple[float, dict[str, float]]) -> None:
        deadline = time.monotonic() + 30
        while (now := offered()) != expected:
            assert time.monotonic() < deadline, (now, kube.osmo_cluster.worker_log("kube-grow"))
            time.sleep(0.2)

    assert offered() == (8, {})  # node-1 only
    kube.kubelet.add_node("node-big", cpu="4", memory="8Gi",
                          labels={"osmo.dev/test-kind": "big"})
    until((12, {"big": 4}))
    kube.server.store.delete(NODES, None, "node-big")
    until((8, {}))
