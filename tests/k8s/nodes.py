"""An osmo cluster whose worker runs its image tasks as pods of the API stand-in.

:class:`KubeCluster` is one server (``tests/e2e/cluster.py``) plus ``osmo worker --runtime
kubernetes`` processes, each given a kubeconfig for the stand-in on loopback and a pool
configuration (``osmo.runtime.kubernetes.config``). The stand-in (API server and kubelet)
runs in the test process; its pods run under ``podman kube play``.
"""

from __future__ import annotations

import json
from collections.abc import Iterator
from pathlib import Path
from typing import Any

from tests.e2e.cluster import Cluster
from tests.k8s import store as st
from tests.k8s.apiserver import ApiServer
from tests.k8s.kubelet import Kubelet

NAMESPACE = "osmo-tasks"


def kubeconfig(url: str, folder: Path) -> Path:
    """A kubeconfig file for the stand-in at ``url`` (no authentication: it has none)."""
    path = folder / "kubeconfig.json"
    path.write_text(json.dumps({
        "apiVersion": "v1", "kind": "Config", "current-context": "standin",
        "clusters": [{"name": "standin", "cluster": {"server": url}}],
        "users": [{"name": "standin", "user": {}}],
        "contexts": [{"name": "standin", "context": {"cluster": "standin", "user": "standin"}}]}))
    return path


def pool_config(folder: Path, kube: Path, **extra: Any) -> Path:
    """A pool configuration file using ``kube`` and ``NAMESPACE`` (``extra``: more keys)."""
    path = folder / "pool.json"
    path.write_text(json.dumps({"namespace": NAMESPACE, "kubeconfig": str(kube), **extra}))
    return path


class KubeCluster:
    """The stand-in, an osmo server, and Kubernetes workers (stop with :meth:`stop`)."""

    def __init__(self, root: Path, podman_env: dict[str, str], **cluster: Any) -> None:
        """``cluster``: :class:`tests.e2e.cluster.Cluster`'s keywords (a router of its own,
        ``server_args``)."""
        root.mkdir(parents=True, exist_ok=True)
        self.root = root
        self.server = ApiServer().start()
        self.kubelet = Kubelet(self.server, podman_env, root / "kubelet")
        self.kubelet.add_node("node-1", cpu="8", memory="16Gi", gpus=1)
        self.kubeconfig = kubeconfig(self.server.url, root)
        self.osmo_cluster = Cluster(root / "osmo", env={"CONTAINERS_CONF":
                                                        podman_env["CONTAINERS_CONF"]}, **cluster)
        self.osmo_cluster.root.mkdir(parents=True, exist_ok=True)
        self.osmo_cluster.start_server()
        self.osmo = self.osmo_cluster.osmo

    def start_worker(self, name: str, *args: str, pool: str = "default",
                     env: dict[str, str] | None = None, **config: Any) -> None:
        """``osmo worker --runtime kubernetes`` named ``name`` serving ``pool`` (``config``:
        the Kubernetes pool's keys; ``env``: more of the worker's environment)."""
        folder = self.root / f"{name}-config"
        folder.mkdir(exist_ok=True)
        conf = pool_config(folder, self.kubeconfig, **config)
        self.osmo_cluster.start_worker(name, "--runtime", "kubernetes",
                                       "--kubernetes-config", str(conf), *args, pool=pool,
                                       env=env)

    def left(self) -> list[str]:
        """``kind/name`` of every pod, Secret, Service and PodGroup the stand-in holds now."""
        kinds = [k for k in st.RESOURCES if k is not st.NODES]
        return [f"{res.kind}/{obj['metadata']['name']}"
                for res, obj in self.server.store.objects(kinds)]

    def stop(self) -> tuple[list[str], list[str]]:
        """Stop everything; what podman still had (pods, containers)."""
        try:
            self.osmo_cluster.stop()
        finally:
            left = self.kubelet.close()
            self.server.stop()
        return left


def started(root: Path, podman_env: dict[str, str], **options: Any) -> Iterator[KubeCluster]:
    """A :class:`KubeCluster` for a fixture; nothing of podman may be left after it."""
    cluster = KubeCluster(root, podman_env, **options)
    try:
        yield cluster
    finally:
        left = cluster.stop()
    assert left == ([], []), f"podman still has {left}"
