"""Where a pod may run: resource fit on nodes, node selectors, taints, and gangs.

Pure functions over API objects (dicts); the kubelet calls them and publishes the answer.

- **Requests** — a pod's request per resource is the larger of its containers' sum and its
  largest init container, as the real scheduler counts it; a container without requests
  requests its limits. ``cpu``, ``memory``, ``ephemeral-storage``, ``nvidia.com/gpu`` and any
  other named resource are compared against a node's ``status.allocatable`` minus what the
  pods bound to it (and not finished) request.
- **Nodes** — :func:`node` builds a Node object (allocatable, labels, taints, Ready).
  ``nodeSelector`` must match the labels; a ``NoSchedule``/``NoExecute`` taint needs a
  toleration. Affinity, topology spread and preemption are not modelled.
- **Gangs** — a pod names its gang the way its scheduler reads it (:data:`GANG_KEYS`): KAI's
  ``pod-group-name`` annotation, Volcano's ``scheduling.k8s.io/group-name`` annotation,
  coscheduling's ``scheduling.x-k8s.io/pod-group`` label (each with its PodGroup object's
  ``spec.minMember``), or Kueue's ``kueue.x-k8s.io/pod-group-name`` label with the
  ``kueue.x-k8s.io/pod-group-total-count`` annotation (no object). Its members bind together
  once ``minMember`` of them exist and all of them fit; until then each stays Pending with
  PodScheduled False, reason Unschedulable, and the reason in the message.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass
from decimal import Decimal
from typing import Any

from kubernetes.utils.quantity import parse_quantity

from tests.k8s import store as st

__all__ = ["GANG_KEYS", "Gang", "gang_of", "node", "place", "requests"]

Obj = dict[str, Any]


@dataclass(frozen=True)
class GangKey:
    """How pods name a gang for one scheduler, and where its PodGroup lives (None: Kueue)."""

    where: str  # "annotations" or "labels"
    key: str
    podgroup: st.Resource | None


GANG_KEYS = (
    GangKey("annotations", "pod-group-name", st.KAI),
    GangKey("annotations", "scheduling.k8s.io/group-name", st.VOLCANO),
    GangKey("labels", "scheduling.x-k8s.io/pod-group", st.COSCHEDULING),
    GangKey("labels", "kueue.x-k8s.io/pod-group-name", None),
)
KUEUE_COUNT = "kueue.x-k8s.io/pod-group-total-count"


@dataclass(frozen=True)
class Gang:
    """A pod's gang: the scheduler's key, the namespace and the group's name."""

    key: GangKey
    namespace: str
    name: str


def gang_of(pod: Obj) -> Gang | None:
    """The gang ``pod`` belongs to (None: it is scheduled alone)."""
    meta = pod["metadata"]
    for key in GANG_KEYS:
        name = (meta.get(key.where) or {}).get(key.key)
        if name:
            return Gang(key, meta.get("namespace") or "default", name)
    return None


def min_member(gang: Gang, store: st.Store, members: Sequence[Obj]) -> tuple[int | None, str]:
    """How many members ``gang`` needs, or None and why it cannot be known yet."""
    if gang.key.podgroup is None:
        counts = {(m["metadata"].get("annotations") or {}).get(KUEUE_COUNT) for m in members}
        counts.discard(None)
        if len(counts) != 1:
            return None, f"pod group {gang.name!r}: {KUEUE_COUNT} is missing or differs"
        try:
            return int(str(counts.pop())), ""
        except ValueError:
            return None, f"pod group {gang.name!r}: {KUEUE_COUNT} is not a number"
    group = store.find(gang.key.podgroup, gang.namespace, gang.name)
    if group is None:
        return None, f'{gang.key.podgroup.qualified} "{gang.name}" not found'
    return int((group.get("spec") or {}).get("minMember") or 1), ""


def node(name: str, *, cpu: str = "4", memory: str = "8Gi", gpus: int = 0,
         pods: int = 110, labels: Mapping[str, str] | None = None,
         taints: Iterable[Mapping[str, str]] = ()) -> Obj:
    """A Node object that is Ready with this allocatable capacity, labels and taints."""
    allocatable = {"cpu": cpu, "memory": memory, "pods": str(pods),
                   "ephemeral-storage": "100Gi"}
    if gpus:
        allocatable["nvidia.com/gpu"] = str(gpus)
    return {
        "apiVersion": "v1", "kind": "Node",
        "metadata": {"name": name, "labels": {"kubernetes.io/hostname": name,
                                              "kubernetes.io/os": "linux", **(labels or {})}},
        "spec": {"taints": [dict(t) for t in taints]} if taints else {},
        "status": {"capacity": dict(allocatable), "allocatable": allocatable,
                   "conditions": [{"type": "Ready", "status": "True", "reason": "KubeletReady",
                                   "lastTransitionTime": st.now()}],
                   "addresses": [{"type": "InternalIP", "address": "127.0.0.1"},
                                 {"type": "Hostname", "address": name}],
                   "nodeInfo": {"machineID": name, "systemUUID": name, "bootID": name,
                                "kernelVersion": "6.1.0", "osImage": "osmo k8s stand-in",
                                "containerRuntimeVersion": "podman://4.3.1",
                                "kubeletVersion": "v1.33.0-osmo-standin",
                                "kubeProxyVersion": "", "operatingSystem": "linux",
                                "architecture": "amd64"}},
    }


def requests(pod: Obj) -> dict[str, Decimal]:
    """What ``pod`` requests of each resource."""
    spec = pod.get("spec") or {}

    def of(container: Obj) -> dict[str, Decimal]:
        res = container.get("resources") or {}
        wanted = {**(res.get("limits") or {}), **(res.get("requests") or {})}
        return {k: Decimal(parse_quantity(v)) for k, v in wanted.items()}

    total: dict[str, Decimal] = {}
    for container in spec.get("containers") or []:
        for k, v in of(container).items():
            total[k] = total.get(k, Decimal(0)) + v
    for container in spec.get("initContainers") or []:
        for k, v in of(container).items():
            total[k] = max(total.get(k, Decimal(0)), v)
    return total


def place(pods: Sequence[Obj], nodes: Sequence[Obj], bound: Sequence[Obj]
          ) -> tuple[dict[str, str], str]:
    """Nodes for all of ``pods`` together ({pod name: node name}), or ({}, why not).

    ``bound`` are the pods already on nodes (their requests are taken); a pod goes to the
    first node, in name order, where it fits.
    """
    used: dict[str, dict[str, Decimal]] = {n["metadata"]["name"]: {} for n in nodes}
    for pod in bound:
        on = used.get(pod["spec"].get("nodeName") or "")
        if on is not None:
            for k, v in requests(pod).items():
                on[k] = on.get(k, Decimal(0)) + v
    chosen: dict[str, str] = {}
    for pod in pods:
        reasons: dict[str, int] = {}
        target = None
        for candidate in sorted(nodes, key=lambda n: n["metadata"]["name"]):
            why = _misfit(pod, candidate, used[candidate["metadata"]["name"]])
            if why is None:
                target = candidate["metadata"]["name"]
                break
            reasons[why] = reasons.get(why, 0) + 1
        if target is None:
            return {}, _unschedulable(len(nodes), reasons)
        chosen[pod["metadata"]["name"]] = target
        for k, v in requests(pod).items():
            used[target][k] = used[target].get(k, Decimal(0)) + v
    return chosen, ""


def _misfit(pod: Obj, candidate: Obj, used: Mapping[str, Decimal]) -> str | None:
    spec = pod.get("spec") or {}
    labels = candidate["metadata"].get("labels") or {}
    if any(labels.get(k) != v for k, v in (spec.get("nodeSelector") or {}).items()):
        return "node(s) didn't match Pod's node affinity/selector"
    for taint in (candidate.get("spec") or {}).get("taints") or []:
        if taint.get("effect") in ("NoSchedule", "NoExecute") and not any(
                _tolerates(t, taint) for t in spec.get("tolerations") or []):
            return (f"node(s) had untolerated taint {{{taint.get('key')}: "
                    f"{taint.get('value', '')}}}")
    allocatable = (candidate.get("status") or {}).get("allocatable") or {}
    for name, amount in sorted(requests(pod).items()):
        free = Decimal(parse_quantity(allocatable.get(name, "0"))) - used.get(name, Decimal(0))
        if amount > free:
            return f"Insufficient {name}"
    return None


def _tolerates(toleration: Mapping[str, Any], taint: Mapping[str, Any]) -> bool:
    if toleration.get("effect") not in (None, "", taint.get("effect")):
        return False
    if toleration.get("operator") == "Exists":
        return toleration.get("key") in (None, "", taint.get("key"))
    return (toleration.get("key") == taint.get("key")
            and toleration.get("value", "") == taint.get("value", ""))


def _unschedulable(total: int, reasons: Mapping[str, int]) -> str:
    parts = ", ".join(f"{n} {why}" for why, n in sorted(reasons.items()))
    return (f"0/{total} nodes are available: {parts}." if total
            else "0/0 nodes are available: no nodes available to schedule pods.")
