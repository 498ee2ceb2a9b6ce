"""Pods that fetch their own data, through a router that authenticates (issue #28).

The router is the chart's: ``router.json5`` rendered with ``auth.enabled``, ``router.enabled``
and a kubernetes pool without ``workClaim``, run as a real zenoh router on loopback with the
rendered password dictionary. The server joins it as ``auth.serverUser``, the worker as
``auth.user``, and the pods' data containers as ``auth.podUser``, from the client config the
worker hands them in each attempt's Secret (``data.zenohConfig``). The pods run under
``podman kube play`` through the API stand-in.
"""

from __future__ import annotations

import json
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

from tests.containers.conftest import images, podman_env  # noqa: F401 - fixtures
from tests.containers.images import KINDS_OSMO, OSMO_IMAGE, ensure_images
from tests.containers.submitting import check_serial_tutorial, submitted_id, task_lines, tasks
from tests.helm.chart import auth_secret, local_router_config, router_config
from tests.k8s.nodes import KubeCluster, pool_config, started
from tests.k8s.store import PODS

TUTORIALS = Path(__file__).parent.parent / "containers" / "osmo_tutorials"
VALUES = {"router": {"enabled": True}, "auth": {"enabled": True, "password": "pw"},
          "pools": [{"name": "data", "replicas": 1, "kind": "kubernetes", "kubernetes": {}}]}
# what a task container runs to look for the pods' router user: its environment, and every
# file it can read (the user name is spelt backwards in the spec, so the spec is not a hit)
LOOKS = """\
workflow:
  name: looks
  tasks:
  - name: look
    image: alpine:3.18
    command: ["sh", "-c", "env; user=$(echo dop-omso | rev); env | grep -c \\"$user\\";
      grep -rlsF \\"$user\\" / --exclude-dir=proc --exclude-dir=sys --exclude-dir=dev;
      echo looked > {{output}}/looked.txt"]
"""


def _client(path: Path, user: str, password: str, dictionary: bool = False) -> Path:
    """A zenoh config logging in as ``user`` (``dictionary``: and accepting only that user
    on the server's own local socket, which its CLI dials with the same config)."""
    usrpwd = {"user": user, "password": password}
    if dictionary:
        (path.parent / f"{path.stem}.dictionary").write_text(f"{user}:{password}\n")
        usrpwd["dictionary_file"] = str(path.parent / f"{path.stem}.dictionary")
    path.write_text(json.dumps({"transport": {"auth": {"usrpwd": usrpwd}}}))
    return path


@pytest.fixture(scope="module")
def kube(tmp_path_factory: pytest.TempPathFactory, podman_env: dict[str, str],  # noqa: F811
         images: dict[str, str]) -> Iterator[tuple[KubeCluster, dict[str, str]]]:  # noqa: F811
    ensure_images(podman_env, KINDS_OSMO)
    root = tmp_path_factory.mktemp("k8s-auth")
    secret = auth_secret(VALUES)
    config, _ = local_router_config(router_config(VALUES), secret["dictionary"], root)
    (root / "router.json5").write_text(json.dumps(config))
    server = _client(root / "server.json5", secret["server-user"], secret["server-password"],
                     dictionary=True)
    for cluster in started(root / "cluster", podman_env, router_config=root / "router.json5",
                           server_args=("--zenoh-config", str(server))):
        worker = _client(root / "worker.json5", secret["user"], secret["password"])
        pods = _client(root / "pod.json5", secret["pod-user"], secret["pod-password"])
        cluster.start_worker("kube-data", pool="data", groupNetwork="host",
                             env={"OSMO_ZENOH_CONFIG": str(worker)},
                             data={"image": OSMO_IMAGE, "zenohConfig": str(pods)})
        yield cluster, secret


def _made(cluster: KubeCluster) -> list[dict[str, Any]]:
    made: list[dict[str, Any]] = []
    cluster.server.store.listen(lambda e: made.append(e.obj) if (
        e.res == PODS and e.type == "ADDED") else None)
    return made


def test_the_serial_tutorial_runs_with_the_routers_auth_on(
        kube: tuple[KubeCluster, dict[str, str]]) -> None:
    cluster, secret = kube
    made = _made(cluster)
    r = cluster.osmo("submit", str(TUTORIALS / "serial_workflow.yaml"), "--pool", "data",
                     "--no-cache", "--wait", timeout=300)
    wf_id = submitted_id(r.out)
    lines, rows = task_lines(cluster.osmo, wf_id), tasks(cluster.osmo, wf_id)
    assert r.code == 0, f"{r.out}{r.err}{lines}{rows}\n" + cluster.osmo_cluster.worker_log(
        "kube-data")
    check_serial_tutorial(lines, rows)
    assert len(made) == 3
    for pod in made:
        fetch = pod["spec"]["initContainers"][0]
        assert "--zenoh-config" in fetch["command"]
        assert secret["pod-password"] not in json.dumps(pod)  # in its Secret, never the pod


def test_the_task_container_holds_no_router_credentials(
        kube: tuple[KubeCluster, dict[str, str]], tmp_path: Path) -> None:
    cluster, secret = kube
    spec = tmp_path / "looks.yaml"
    spec.write_text(LOOKS)
    r = cluster.osmo("submit", str(spec), "--pool", "data", "--no-cache", "--wait",
                     timeout=300)
    wf_id = submitted_id(r.out)
    lines = task_lines(cluster.osmo, wf_id)["look"]
    assert r.code == 0, f"{r.out}{r.err}{lines}"
    text = "\n".join(lines)
    # the look ran (its output came back through the collector, with the pod user), and
    # found the user in no variable ("0") and in no file it can read
    assert "PATH=" in text and "0" in lines, text
    assert [line for line in lines if line.startswith("/")] == [], text
    assert secret["pod-password"] not in text and "osmo-pod" not in text


def test_a_worker_whose_pods_could_not_log_in_refuses_to_start(
        kube: tuple[KubeCluster, dict[str, str]]) -> None:
    """No ``data.zenohConfig`` while its own router authenticates: every pod would fail to
    connect; the worker says so at start (exit 2) instead."""
    cluster, _ = kube
    folder = cluster.root / "kube-bare-config"
    folder.mkdir(exist_ok=True)
    conf = pool_config(folder, cluster.kubeconfig, groupNetwork="host",
                       data={"image": OSMO_IMAGE})
    proc = cluster.osmo_cluster.start_worker(
        "kube-bare", "--runtime", "kubernetes", "--kubernetes-config", str(conf), pool="data",
        env={"OSMO_ZENOH_CONFIG": str(cluster.root.parent / "worker.json5")}, wait=False)
    assert proc.wait(timeout=120) == 2, cluster.osmo_cluster.worker_log("kube-bare")
    log = cluster.osmo_cluster.worker_log("kube-bare")
    assert "give the pool's data a zenohConfig" in log and "Traceback" not in log, log
