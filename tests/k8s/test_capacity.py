"""A Kubernetes node's capacity (``osmo.runtime.kubernetes.capacity``): the allocatable cpu,
memory and GPUs of the Ready, schedulable nodes its pool's selector picks, read through the
real client from the stand-in; and Kubernetes quantities."""

from __future__ import annotations

from decimal import Decimal

import pytest

from osmo.runtime.kubernetes.capacity import cluster_capacity, quantity
from osmo.runtime.kubernetes.config import KubePool, Placement
from osmo.runtime.kubernetes.kube import Kube
from tests.k8s.conftest import Cluster
from tests.k8s.store import NODES


def test_capacity_is_the_selected_nodes_allocatable(api: Cluster) -> None:
    api.kubelet.add_node("gpu-1", cpu="16", memory="64Gi", gpus=4, labels={"pool": "robots"})
    api.kubelet.add_node("gpu-2", cpu="3800m", memory="16318480Ki", gpus=2,
                         labels={"pool": "robots"})
    api.kubelet.add_node("cpu-1", cpu="4", memory="8Gi", labels={"pool": "other"})
    kube = Kube(api.client)
    robots = KubePool(placement=Placement({"pool": "robots"}))
    assert cluster_capacity(kube, robots) == (19.8, 6, (64 << 30) + 16318480 * 1024)
    everything = cluster_capacity(kube, KubePool())  # node-1 (4, 1 GPU, 8Gi) too
    assert everything[:2] == (27.8, 7)

    def cordon(obj: dict) -> None:
        obj["spec"]["unschedulable"] = True
    api.server.store.update(NODES, None, "gpu-1", cordon)
    assert cluster_capacity(kube, robots)[:2] == (3.8, 2)


@pytest.mark.parametrize(("text", "value"), [
    ("4", Decimal(4)), ("3800m", Decimal("3.8")), ("8Gi", Decimal(8 << 30)),
    ("16318480Ki", Decimal(16318480 * 1024)), ("1e3", Decimal(1000)), ("2M", Decimal(2_000_000)),
])
def test_quantities(text: str, value: Decimal) -> None:
    assert quantity(text) == value


def test_a_bad_quantity_is_refused() -> None:
    with pytest.raises(ValueError, match="not a Kubernetes quantity"):
        quantity("lots")
