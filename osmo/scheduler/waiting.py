"""Why a task waits: the reason ``osmo query`` shows for each WAITING or SCHEDULING task.

This module owns the reasons only, computed when asked (a query), never during placement,
so they cost placement nothing. Each reason is the first that holds, in this order:

- WAITING: the upstream groups not COMPLETED yet.
- SCHEDULING, in the target pool (or any pool):
    1. no node at all: ``pool 'gpu' has no online worker`` (``since`` it lost its last one,
       or since the scheduler first noticed; ``fails_at`` under the no-worker timeout);
    2. no node its platform and ``nodesExcluded`` allow;
    3. a dimension it needs more of than any eligible node has in total (``needs 4 gpu,
       the largest worker in pool 'gpu' has 2``) or has free (``needs 4 gpu, largest free
       is 2``);
    4. no eligible node has all of its request free at once;
    5. its group is placed all at once and the whole group does not fit what is free;
    6. otherwise it fits now and is placed in this very pass (a query raced placement).

Tasks with the same request, pool and gang share one computation, so a query over 10,000
waiting tasks costs O(distinct shapes x nodes).
"""

from __future__ import annotations

from collections.abc import Collection

from osmo.scheduler.fit import DIMENSIONS, format_amount, format_capacity
from osmo.scheduler.resources import ZERO, Request, first_fit, room, total
from osmo.scheduler.runs import Group, Run
from osmo.scheduler.state import TaskState
from osmo.scheduler.types import Capacity, Node, Waiting
from osmo.scheduler.world import World
from osmo.status import TaskStatus

__all__ = ["waiting"]


def waiting(world: World, run: Run,
            names: Collection[str] | None = None) -> dict[str, Waiting]:
    """Task name → why it waits, for every WAITING or SCHEDULING task of ``run``.

    ``names``: only for these tasks (a query that shows a few of 100,000).
    """
    out: dict[str, Waiting] = {}
    memo: dict[tuple[Request, str | None], Waiting] = {}
    tasks = (run.tasks.values() if names is None else
             [run.tasks[n] for n in names if n in run.tasks])
    for task in tasks:
        if task.status is TaskStatus.WAITING:
            out[task.name] = _upstream(run, task)
        elif task.status is TaskStatus.SCHEDULING:
            group = run.group_of(task)
            gang = group.name if _in_gang(run, group) else None
            key = (run.requests[task.name], gang)
            if key not in memo:
                memo[key] = _unplaced(world, run, task, group if gang else None)
            out[task.name] = memo[key]
    return out


def _upstream(run: Run, task: TaskState) -> Waiting:
    names = [up for up in sorted(run.graph.upstream(task.group), key=run.graph.index)
             if run.groups[up].outcome is not TaskStatus.COMPLETED]
    shown = ", ".join(f"'{n}'" for n in names[:5]) + (" ..." if len(names) > 5 else "")
    return Waiting(f"waits for upstream {shown} to complete")


def _in_gang(run: Run, group: Group) -> bool:
    """True while ``group`` waits to be placed as a whole (its first placement)."""
    members = [run.tasks[t.name] for t in group.spec.tasks]
    return len(members) > 1 and all(
        t.status is TaskStatus.SCHEDULING and t.retry == 0 for t in members)


def _unplaced(world: World, run: Run, task: TaskState, gang: Group | None) -> Waiting:
    pool = run.state.pool
    where = f"pool '{pool}'" if pool is not None else "any pool"
    nodes = world.ledger.candidates(pool)
    if not nodes:
        return _no_worker(world, run, pool, where)
    req = run.requests[task.name]
    eligible = [n for n in nodes if req.allows(n)]
    if not eligible:
        if req.platform is not None and not any(n.offers(req.platform) for n in nodes):
            served = sorted({p for n in nodes for p in n.served()})
            return Waiting(f"no online worker in {where} has platform '{req.platform}' "
                           f"(platforms: {', '.join(served) or 'none'})")
        return Waiting(f"every online worker in {where} is in its nodesExcluded")
    used = world.ledger.usage()
    free = {n.id: room(n, req, used) or ZERO for n in eligible}
    short = _short(req.capacity, eligible, free, where, req.platform)
    if short is not None:
        return Waiting(short)
    if not any(req.capacity.fits_in(free[n.id]) for n in eligible):
        return Waiting(f"needs {format_capacity(req.capacity)} on one worker; no worker in "
                       f"{where} has all of it free")
    if gang is not None:
        members = [(t.name, run.requests[t.name]) for t in gang.spec.tasks]
        if first_fit(members, nodes, used) is None:
            need = total(r.capacity for _, r in members)
            return Waiting(f"its group '{gang.name}' starts all at once and needs "
                           f"{format_capacity(need)}; that does not fit what is free in "
                           f"{where}")
    return Waiting("fits now; being placed")


def _short(need: Capacity, nodes: list[Node], free: dict[str, Capacity],
           where: str, platform: str | None = None) -> str | None:
    """The first dimension ``need`` exceeds on every node: in total, or free now."""
    of = f" for platform '{platform}'" if platform is not None else ""
    for dim in DIMENSIONS:
        amount = getattr(need, dim)
        if not amount:
            continue
        largest = max(getattr(n.offers(platform) or n.capacity, dim) for n in nodes)
        if amount > largest + 1e-9:
            return (f"needs {format_amount(dim, amount)} {dim}, the largest worker in {where} "
                    f"has {format_amount(dim, largest)}{of}")
        largest_free = max(getattr(free[n.id], dim) for n in nodes)
        if amount > largest_free + 1e-9:
            return (f"needs {format_amount(dim, amount)} {dim}, largest free is "
                    f"{format_amount(dim, max(largest_free, 0))}")
    return None


def _no_worker(world: World, run: Run, pool: str | None, where: str) -> Waiting:
    since = world.pool_empty_since(pool)
    timeout = run.spec.timeout.queue_timeout
    fails_at = None
    if timeout is None and world.no_worker_timeout is not None and since is not None:
        fails_at = since + world.no_worker_timeout  # at the earliest (see expire_no_worker)
    text = f"{where} has no online worker" if pool is not None else "no worker is online"
    return Waiting(text, since=since, fails_at=fails_at)
