"""What a Kubernetes node (osmo's in-cluster worker) offers: the nodes its pool may use.

:func:`cluster_capacity` sums the ``allocatable`` cpu, memory and ``nvidia.com/gpu`` of the
Ready, schedulable nodes the pool's node selector picks; :func:`quantity` reads Kubernetes
quantities (``3800m``, ``16318480Ki``, ``8Gi``, ``1e3``).
"""

from __future__ import annotations

import re
from collections.abc import Mapping
from decimal import Decimal, InvalidOperation
from typing import Any

from osmo.runtime.kubernetes.config import KubePool
from osmo.runtime.kubernetes.kube import Kube

__all__ = ["cluster_capacity", "quantity"]

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


def cluster_capacity(kube: Kube, pool: KubePool) -> tuple[float, int, int]:
    """``(cpus, gpus, memory bytes)`` the pool's nodes can allocate.

    Raises:
        KubeError: the nodes cannot be listed.
    """
    labels = ",".join(f"{k}={v}" for k, v in sorted(pool.placement.node_selector.items()))
    cpus, gpus, memory = Decimal(0), Decimal(0), Decimal(0)
    for node in kube.nodes(labels):
        if not _usable(node):
            continue
        allocatable = (node.get("status") or {}).get("allocatable") or {}
        cpus += quantity(str(allocatable.get("cpu", "0")))
        gpus += quantity(str(allocatable.get("nvidia.com/gpu", "0")))
        memory += quantity(str(allocatable.get("memory", "0")))
    return float(cpus), int(gpus), int(memory)
