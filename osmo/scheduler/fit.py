"""Why a workflow can never fit the known nodes (the server refuses such a submit).

This module owns the reasons only: for each group, can all its tasks be placed at once on the
target pool's nodes when those nodes are empty? It uses the same first-fit rule as live
placement (``resources.first_fit``), so a workflow accepted here can always start on an idle
cluster. It never reserves anything.
"""

from __future__ import annotations

from collections.abc import Sequence

from osmo.scheduler.resources import Request, first_fit, requests_of, room, total
from osmo.scheduler.types import Capacity, Node
from osmo.spec.model import GroupSpec, WorkflowSpec

__all__ = ["DIMENSIONS", "check_fit", "format_amount", "format_capacity"]

DIMENSIONS = ("cpu", "gpu", "memory", "storage")
_BINARY_UNITS = (("Ti", 1 << 40), ("Gi", 1 << 30), ("Mi", 1 << 20), ("Ki", 1 << 10))


def format_amount(dimension: str, value: float) -> str:
    """``value`` of ``dimension`` for people: ``4``, ``0.5``, ``16Gi``, ``1536Ki``."""
    if dimension in ("memory", "storage"):
        for unit, size in _BINARY_UNITS:
            if value >= size and value % size == 0:
                return f"{int(value // size)}{unit}"
        return f"{int(value)}B" if value else "0"
    return str(int(value)) if float(value).is_integer() else f"{value:g}"


def format_capacity(cap: Capacity) -> str:
    """The non-zero dimensions of ``cap`` for people: ``cpu=2, gpu=1``."""
    parts = [f"{d}={format_amount(d, getattr(cap, d))}" for d in DIMENSIONS if getattr(cap, d)]
    return ", ".join(parts) or "nothing"


def check_fit(spec: WorkflowSpec, pool: str | None, nodes: Sequence[Node]) -> list[str]:
    """Reasons ``spec`` can never be placed in ``pool`` on ``nodes``; [] when it can.

    Args:
        spec: the validated workflow.
        pool: the target pool; None = any pool.
        nodes: the currently known nodes (their whole capacity counts, as if idle).
    """
    pools = sorted({n.pool for n in nodes})
    if pool is not None and pool not in pools:
        return [f"unknown pool '{pool}' (pools: {', '.join(pools) or 'none'})"]
    where = f"pool '{pool}'" if pool is not None else "any pool"
    members = sorted((n for n in nodes if pool is None or n.pool == pool), key=lambda n: n.id)
    if not members:
        return [f"no node is available in {where}"]
    reasons: list[str] = []
    of_task = requests_of(spec)
    # the tasks of a big workflow share few requests: each is judged once
    problems = {req: _request_problem(req, members, where) for req in set(of_task.values())}
    for group in spec.groups:
        requests = [(t.name, of_task[t.name]) for t in group.tasks]
        task_reasons = [f"task '{name}' {problems[req]}" for name, req in requests
                        if problems[req] is not None]
        reasons.extend(task_reasons)
        if not task_reasons and len(requests) > 1 and first_fit(requests, members, {}) is None:
            reasons.append(_group_reason(group, requests, members, where))
    return reasons


def _request_problem(req: Request, nodes: Sequence[Node], where: str) -> str | None:
    """Why no node can ever take a task with ``req`` (after "task 'NAME' "), or None."""
    if req.platform is not None and not any(n.offers(req.platform) for n in nodes):
        platforms = sorted({p for n in nodes for p in n.served()}) or ["none"]
        return (f"requests platform '{req.platform}' but no node in {where} has it "
                f"(platforms: {', '.join(platforms)})")
    eligible = [n for n in nodes if req.allows(n)]
    if not eligible:
        return f"excludes every eligible node in {where}"
    offered = [room(n, req, {}) or n.capacity for n in eligible]  # a platform's, if it asks
    for dim in DIMENSIONS:
        need = getattr(req.capacity, dim)
        best = max(getattr(cap, dim) for cap in offered)
        if need > best + 1e-9:
            return (f"requests {dim}={format_amount(dim, need)} but no node in {where} has "
                    f"more than {format_amount(dim, best)} {dim}")
    if not any(req.capacity.fits_in(cap) for cap in offered):
        return (f"requests {format_capacity(req.capacity)} but no single node in {where} "
                "has all of it")
    return None


def _group_reason(group: GroupSpec, requests: Sequence[tuple[str, Request]],
                  nodes: Sequence[Node], where: str) -> str:
    need = total(req.capacity for _, req in requests)
    have = total(n.capacity for n in nodes)
    for dim in DIMENSIONS:
        if getattr(need, dim) > getattr(have, dim) + 1e-9:
            return (f"group '{group.name}' needs {dim}={format_amount(dim, getattr(need, dim))} "
                    f"at once; the largest placement possible is "
                    f"{format_amount(dim, getattr(have, dim))}")
    return (f"group '{group.name}' needs {format_capacity(need)} at once but its "
            f"{len(requests)} tasks cannot be packed onto the nodes of {where}")
