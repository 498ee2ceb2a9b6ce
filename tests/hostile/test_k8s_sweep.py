"""A sweep (``wire.Sweep``) deletes only the named instance's objects, never the node's own,
and a value that is no label value (a selector smuggled in) is refused."""

from __future__ import annotations

from pathlib import Path

import pytest

from osmo.errors import OsmoError
from osmo.runtime.kubernetes.config import KubePool
from osmo.runtime.kubernetes.kube import Kube
from osmo.runtime.kubernetes.runtime import KubernetesRuntime
from tests.k8s.conftest import Cluster, api, podman_env  # noqa: F401 - fixtures
from tests.k8s.nodes import kubeconfig
from tests.k8s.store import SECRETS, SERVICES

NS = "default"


def _objects(api: Cluster, instance: str) -> None:  # noqa: F811
    labels = {"osmo.dev/instance": instance}
    api.core.create_namespaced_secret(NS, {"metadata": {"name": f"s-{instance}",
                                                        "labels": labels},
                                           "stringData": {"k": "v"}})
    api.core.create_namespaced_service(NS, {"metadata": {"name": f"svc-{instance}",
                                                         "labels": labels},
                                            "spec": {"clusterIP": "None"}})


def _left(api: Cluster) -> set[str]:  # noqa: F811
    return {obj["metadata"]["name"] for _, obj in api.server.store.objects([SECRETS, SERVICES])}


@pytest.mark.parametrize("instance", ["me", "", "gone,osmo.dev/instance!=x", "gone x",
                                      "a" * 64])
def test_a_sweep_of_its_own_or_of_no_label_value_is_refused(
        api: Cluster, tmp_path: Path, instance: str) -> None:  # noqa: F811
    runtime = KubernetesRuntime(KubePool(kubeconfig=str(kubeconfig(api.server.url, tmp_path))),
                                Kube(api.client), instance="me")
    for owner in ("me", "gone", "x"):
        _objects(api, owner)
    with pytest.raises(OsmoError, match="refused to sweep"):
        runtime.sweep(instance)
    assert len(_left(api)) == 6
    assert sorted(runtime.sweep("gone")) == ["secret/s-gone", "service/svc-gone"]
    assert _left(api) == {"s-me", "svc-me", "s-x", "svc-x"}
    runtime.close()
    for owner in ("me", "x"):
        api.server.store.delete(SECRETS, NS, f"s-{owner}")
        api.server.store.delete(SERVICES, NS, f"svc-{owner}")
