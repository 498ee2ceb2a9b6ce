"""What a Kubernetes node (osmo's in-cluster worker) offers: the nodes its pool may use.

:func:`cluster_capacity` sums the ``allocatable`` cpu, memory and ``nvidia.com/gpu`` of the
Ready, schedulable nodes the pool's node selector picks; :func:`platform_capacity` does the
same per platform of the pool (its node selector added to the pool's, its taints tolerated)
and names only the platforms some such node carries; :func:`quantity` reads Kubernetes
quantities (``3800m``, ``16318480Ki``, ``8Gi``, ``1e3``).
"""

from __future__ import annotations

import re
from collections.abc import Iterable, Mapping
from decimal import Decimal, InvalidOperation
from typing import Any

from osmo.runtime.kubernetes.config import KubePool
from osmo.runtime.kubernetes.kube import Kube

__all__ = ["Capacity", "cluster_capacity", "platform_capacity", "quantity"]

Capacity = tuple[float, int, int]
"""``(cpus, gpus, memory bytes)``."""

_SUFFIXES = {"n": Decimal("1e-9"), "u": Decimal("1e-6"), "m": Decimal("1e-3"), "": Decimal(1),
             "k": Decimal("1e3"), "M": Decimal("1e6"), "G": Decimal("1e9"),
             "T": Decimal("1e12"), "P": Decimal("1e15"), "E": Decimal("1e18"),
             "Ki": Decimal(2 ** 10), "Mi": Decimal(2 ** 20), "Gi": Decimal(2 ** 30),
             "Ti": Decimal(2 ** 40), "Pi": Decimal(2 ** 50), "Ei": Decimal(2 ** 60)}
_QUANTITY = re.compile(r"([+-]?[0-9.]+(?:[eE][+-]?[0-9]+)?)(Ki|Mi|Gi|Ti|Pi|Ei|[numkMGTPE]?)")


def quantity(text: str) -> Decimal:
    """A Kubernetes quantity as a number.

    Raises:
        ValueError: it is not one.
    """
    match = _QUANTITY.fullmatch(text.strip())
    if match is None:
        raise ValueError(f"not a Kubernetes quantity: {text!r}")
    try:
        return Decimal(match[1]) * _SUFFIXES[match[2]]
    except InvalidOperation:
        raise ValueError(f"not a Kubernetes quantity: {text!r}") from None


def _usable(node: Mapping[str, Any]) -> bool:
    if (node.get("spec") or {}).get("unschedulable"):
        return False
    for entry in (node.get("status") or {}).get("conditions") or []:
        if entry.get("type") == "Ready":
            return bool(entry.get("status") == "True")
    return True  # no Ready condition reported yet: counted


def cluster_capacity(kube: Kube, pool: KubePool) -> Capacity:
    """``(cpus, gpus, memory bytes)`` the pool's nodes can allocate.

    Raises:
        KubeError: the nodes cannot be listed.
    """
    nodes = kube.nodes(_selector(pool.placement.node_selector))
    return _allocatable(n for n in nodes if _usable(n))


def platform_capacity(kube: Kube, pool: KubePool) -> dict[str, Capacity]:
    """Each platform of the pool some Ready, schedulable node takes: its nodes' allocatable.

    A platform's nodes are those both node selectors (the pool's and the platform's) pick
    and whose ``NoSchedule``/``NoExecute`` taints the pool's or the platform's tolerations
    tolerate: where its pods can go. A platform no such node has is left out.

    Raises:
        KubeError: the nodes cannot be listed.
    """
    found: dict[str, Capacity] = {}
    for name, placement in sorted(pool.platforms.items()):
        selector = {**pool.placement.node_selector, **placement.node_selector}
        tolerations = (*pool.placement.tolerations, *placement.tolerations)
        nodes = [node for node in kube.nodes(_selector(selector))
                 if _usable(node) and _tolerated(node, tolerations)]
        if nodes:
            found[name] = _allocatable(nodes)
    return found


def _selector(labels: Mapping[str, str]) -> str:
    return ",".join(f"{k}={v}" for k, v in sorted(labels.items()))


def _allocatable(nodes: Iterable[Mapping[str, Any]]) -> Capacity:
    cpus, gpus, memory = Decimal(0), Decimal(0), Decimal(0)
    for node in nodes:
        allocatable = (node.get("status") or {}).get("allocatable") or {}
        cpus += quantity(str(allocatable.get("cpu", "0")))
        gpus += quantity(str(allocatable.get("nvidia.com/gpu", "0")))
        memory += quantity(str(allocatable.get("memory", "0")))
    return float(cpus), int(gpus), int(memory)


def _tolerated(node: Mapping[str, Any], tolerations: Iterable[Mapping[str, Any]]) -> bool:
    """Whether every taint that keeps pods off ``node`` is tolerated."""
    held = list(tolerations)
    return all(any(_tolerates(t, taint) for t in held)
               for taint in (node.get("spec") or {}).get("taints") or []
               if taint.get("effect") in ("NoSchedule", "NoExecute"))


def _tolerates(toleration: Mapping[str, Any], taint: Mapping[str, Any]) -> bool:
    """Whether ``toleration`` tolerates ``taint`` (Kubernetes' rule).

    The key (empty with ``Exists``: every key), the value (``Equal``, the default operator)
    and the effect (empty: every effect) must match.
    """
    if toleration.get("effect") and toleration["effect"] != taint.get("effect"):
        return False
    key = toleration.get("key") or ""
    if toleration.get("operator") == "Exists":
        return not key or key == taint.get("key")
    return key == taint.get("key") and (toleration.get("value") or "") == (
        taint.get("value") or "")
