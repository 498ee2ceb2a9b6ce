"""A Kubernetes node's capacity (``osmo.runtime.kubernetes.capacity``): the allocatable cpu,
memory and GPUs of the Ready, schedulable nodes its pool's selector picks, read through the
real client from the stand-in; and Kubernetes quantities."""

from __future__ import annotations

from dataclasses import replace
from decimal import Decimal
from pathlib import Path

import pytest

from osmo.config import free_port
from osmo.runtime.kubernetes.capacity import cluster_capacity, platform_capacity, quantity
from osmo.runtime.kubernetes.config import KubePool, Placement
from osmo.runtime.kubernetes.kube import Kube, KubeError, connect
from osmo.runtime.kubernetes.runtime import KubernetesRuntime
from osmo.worker.options import WorkerOptions
from osmo.worker.remote import _capacity
from tests.k8s.conftest import Cluster
from tests.k8s.nodes import kubeconfig
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


GPU_TAINT = {"key": "nvidia.com/gpu", "value": "present", "effect": "NoSchedule"}


def test_platforms_are_those_some_ready_node_takes(api: Cluster) -> None:
    """A platform is offered when a Ready, schedulable node both selectors pick carries it
    and its pods tolerate that node's taints; its capacity is those nodes' allocatable."""
    add = api.kubelet.add_node
    add("h100-1", cpu="32", memory="256Gi", gpus=8, taints=[GPU_TAINT],
        labels={"pool": "robots", "gpu": "h100"})
    add("h100-2", cpu="32", memory="256Gi", gpus=8, taints=[GPU_TAINT],
        labels={"pool": "robots", "gpu": "h100"})
    add("h100-elsewhere", cpu="32", memory="256Gi", gpus=8, labels={"gpu": "h100"})
    add("orin-1", cpu="12", memory="32Gi", gpus=1, labels={"pool": "robots", "arch": "orin"})
    add("arm-1", cpu="8", memory="16Gi", labels={"pool": "robots", "arch": "arm"},
        taints=[{"key": "dedicated", "value": "ci", "effect": "NoExecute"}])
    gpu = {"key": "nvidia.com/gpu", "operator": "Exists", "effect": "NoSchedule"}
    pool = KubePool(placement=Placement({"pool": "robots"}), platforms={
        "dgx": Placement({"gpu": "h100"}, (gpu,)),
        "dgx-untolerated": Placement({"gpu": "h100"}),  # the taint keeps its pods off
        "jetson": Placement({"arch": "orin"}),
        "arm": Placement({"arch": "arm"}),  # its only node is tainted for others
        "arm-ci": Placement({"arch": "arm"}, ({"key": "dedicated", "value": "ci"},)),
        "gb200": Placement({"gpu": "gb200"}),  # no such node
    })
    kube = Kube(api.client)
    assert platform_capacity(kube, pool) == {
        "arm-ci": (8.0, 0, 16 << 30),
        "dgx": (64.0, 16, 512 << 30),  # not h100-elsewhere: outside the pool's selector
        "jetson": (12.0, 1, 32 << 30)}

    def not_ready(obj: dict) -> None:
        obj["status"]["conditions"][0]["status"] = "False"
    api.server.store.update(NODES, None, "orin-1", not_ready)
    api.server.store.update(NODES, None, "h100-1", not_ready)
    assert platform_capacity(kube, pool) == {"arm-ci": (8.0, 0, 16 << 30),
                                             "dgx": (32.0, 8, 256 << 30)}


def test_a_worker_told_its_capacity_reads_no_node(tmp_path: Path) -> None:
    """A pool that may not read nodes (the chart's ``readNodes: false``) gives ``--cpus``,
    ``--gpus`` and ``--memory``: the worker then never asks the API (here: none listens);
    missing one of them, it asks."""
    config = kubeconfig(f"http://127.0.0.1:{free_port(0)}", tmp_path)
    runtime = KubernetesRuntime(KubePool(kubeconfig=str(config)), connect(str(config)),
                                instance="me")
    try:
        told = WorkerOptions(connect=(), cpus=4, gpus=0, memory=1 << 30)
        assert _capacity(told, runtime, None) == (4, 0, 1 << 30)
        with pytest.raises(KubeError, match="cannot be reached"):
            _capacity(replace(told, memory=None), runtime, None)
    finally:
        runtime.close()


@pytest.mark.parametrize(("text", "value"), [
    ("4", Decimal(4)), ("3800m", Decimal("3.8")), ("8Gi", Decimal(8 << 30)),
    ("16318480Ki", Decimal(16318480 * 1024)), ("1e3", Decimal(1000)), ("2M", Decimal(2_000_000)),
])
def test_quantities(text: str, value: Decimal) -> None:
    assert quantity(text) == value


def test_a_bad_quantity_is_refused() -> None:
    with pytest.raises(ValueError, match="not a Kubernetes quantity"):
        quantity("lots")
