"""Resource requests, the node ledger and first-fit gang placement.

This module owns *where things fit*: what a task asks for, which nodes exist, what each
attempt holds on which node, and the packing rule. It knows nothing of statuses or events.

Rules (documented behaviour):
    - A task's request is its resource spec with ``cpu`` defaulting to 1 and ``gpu``,
      ``memory``, ``storage`` to 0 when unset.
    - A node is eligible when it is in the target pool (``None`` = any pool), serves the
      requested ``platform`` (if any: ``Node.offers``) and is not in ``nodesExcluded``.
    - Room (:func:`room`, the one fit check): a task fits what its node has free, and a
      task with a platform also what that platform of the node has free (its capacity
      less what the node's attempts of that platform hold): a cluster node's gpu nodes
      and cpu nodes fill up apart.
    - Packing is *first-fit decreasing*: the tasks of a gang are taken largest first
      (gpu, cpu, memory, storage), each onto the first eligible node (by id) with room.
      There is no backtracking, so a packing that exists may be missed; ``check_fit`` uses
      the same rule on empty nodes, so a group it accepts always fits an idle cluster.
    - Reservations are kept per attempt and per node *id*, also for nodes not (yet) known,
      so state restored before its nodes are re-announced stays accounted for.
"""

from __future__ import annotations

import functools
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass

from osmo.scheduler.types import Capacity, Node
from osmo.spec.model import ResourceSpec, TaskSpec, WorkflowSpec

__all__ = ["ZERO", "Ledger", "Request", "Used", "first_fit", "request_for", "requests_of",
           "room", "total"]

ZERO = Capacity()

Used = Mapping[tuple[str, str | None], Capacity]
"""What attempts hold: ``(node id, None)`` on the node, ``(node id, platform)`` of a platform."""


@dataclass(frozen=True)
class Request:
    """What one task needs from a node."""

    capacity: Capacity
    platform: str | None = None
    excluded: frozenset[str] = frozenset()

    def allows(self, node: Node) -> bool:
        """True if ``node``'s platform and id are acceptable (capacity not checked)."""
        return node.id not in self.excluded and node.offers(self.platform) is not None


def request_for(spec: WorkflowSpec, task: TaskSpec) -> Request:
    """The request of ``task``: its resource spec with the documented defaults."""
    return _request(spec.resource_for(task))


def requests_of(spec: WorkflowSpec) -> dict[str, Request]:
    """Task name → :func:`request_for` it, for every task of ``spec``.

    A request depends only on the task's ``resource`` and its resolved type, which the tasks
    of a big fan-out share: each such pair is looked up once.
    """
    seen: dict[tuple[str, int], Request] = {}
    out: dict[str, Request] = {}
    for task in spec.all_tasks():
        key = (task.resource, id(task.resolved))  # the tasks outlive this call: ids hold
        found = seen.get(key)
        if found is None:
            found = seen[key] = request_for(spec, task)
        out[task.name] = found
    return out


@functools.lru_cache(maxsize=4096)
def _request(res: ResourceSpec) -> Request:
    """A resource spec's request (cached: the tasks of a workflow share a few specs)."""
    capacity = Capacity(
        cpu=float(res.cpu if res.cpu is not None else 1),
        gpu=res.gpu or 0,
        memory=res.memory or 0,
        storage=res.storage or 0,
    )
    return Request(capacity, res.platform, frozenset(res.nodes_excluded))


def _size(item: tuple[str, Request]) -> tuple[float, ...]:
    cap = item[1].capacity
    return (cap.gpu, cap.cpu, cap.memory, cap.storage)


def room(node: Node, req: Request, used: Used, extra: Used | None = None) -> Capacity | None:
    """What ``node`` has free for ``req`` now (None: it cannot take it at all).

    The node's capacity less what it holds; for a request with a platform, also no more
    than that platform's capacity less what the node's attempts of that platform hold.
    ``extra``: more held, not reserved yet (a gang being packed).
    """
    offered = node.offers(req.platform)
    if offered is None or node.id in req.excluded:
        return None
    key: tuple[str, str | None] = (node.id, None)
    free = node.capacity - used.get(key, ZERO)
    if extra:
        free = free - extra.get(key, ZERO)
    if req.platform is None:
        return free
    key = (node.id, req.platform)
    own = offered - used.get(key, ZERO)
    if extra:
        own = own - extra.get(key, ZERO)
    return Capacity(min(free.cpu, own.cpu), min(free.gpu, own.gpu),
                    min(free.memory, own.memory), min(free.storage, own.storage))


def first_fit(tasks: Sequence[tuple[str, Request]], nodes: Sequence[Node],
              used: Used) -> dict[str, str] | None:
    """Place every task at once (first-fit decreasing), or return None.

    Args:
        tasks: (task name, request) pairs of one gang.
        nodes: eligible-pool nodes, sorted by id.
        used: what is already reserved (:data:`Used`).

    Returns:
        task name → node id for every task, or None when the gang does not fit.
    """
    extra: dict[tuple[str, str | None], Capacity] = {}
    plan: dict[str, str] = {}
    for name, req in sorted(tasks, key=_size, reverse=True):  # sorted() is stable
        for node in nodes:
            free = room(node, req, used, extra)
            if free is not None and req.capacity.fits_in(free):
                plan[name] = node.id
                for key in {(node.id, None), (node.id, req.platform)}:
                    extra[key] = extra.get(key, ZERO) + req.capacity
                break
        else:
            return None
    return plan


class Ledger:
    """Known nodes and what each attempt holds on which node."""

    def __init__(self) -> None:
        self._nodes: dict[str, Node] = {}
        self._used: dict[tuple[str, str | None], Capacity] = {}  # see Used
        self._held: dict[str, tuple[str, str | None, Capacity]] = {}  # attempt → where, amount
        self._on_node: dict[str, set[str]] = {}  # node id → attempt ids held there
        self._by_pool: dict[str | None, list[Node]] = {}  # cache, reset on node changes

    def nodes(self) -> list[Node]:
        """Known nodes, sorted by id."""
        return [self._nodes[k] for k in sorted(self._nodes)]

    def node(self, node_id: str) -> Node | None:
        """The node called ``node_id``, if known."""
        return self._nodes.get(node_id)

    def used(self, node_id: str, platform: str | None = None) -> Capacity:
        """What attempts hold on ``node_id`` (of ``platform``; zero when nothing)."""
        return self._used.get((node_id, platform), ZERO)

    def usage(self) -> Used:
        """What attempts hold, by node and platform (read only)."""
        return self._used

    def held_on(self, node_id: str) -> list[str]:
        """Ids of the attempts holding resources on ``node_id``."""
        return sorted(self._on_node.get(node_id, ()))

    def up(self, node: Node) -> None:
        """Add or replace a node (its reservations are kept)."""
        self._nodes[node.id] = node
        self._by_pool.clear()

    def down(self, node_id: str) -> list[str]:
        """Remove a node and drop its reservations; return the attempt ids it held."""
        self._nodes.pop(node_id, None)
        self._by_pool.clear()
        held = sorted(self._on_node.pop(node_id, ()))
        platforms: set[str | None] = {None}
        for aid in held:
            platforms.add(self._held.pop(aid)[1])
        for platform in platforms:
            self._used.pop((node_id, platform), None)
        return held

    def reserve(self, attempt: str, node_id: str, amount: Capacity,
                platform: str | None = None) -> None:
        """Hold ``amount`` on ``node_id`` (of ``platform``) for ``attempt`` (once per attempt)."""
        if attempt in self._held:
            return
        self._held[attempt] = (node_id, platform, amount)
        self._on_node.setdefault(node_id, set()).add(attempt)
        for key in {(node_id, None), (node_id, platform)}:
            self._used[key] = self._used.get(key, ZERO) + amount

    def release(self, attempt: str) -> bool:
        """Free what ``attempt`` holds; False when it held nothing."""
        found = self._held.pop(attempt, None)
        if found is None:
            return False
        node_id, platform, amount = found
        self._on_node[node_id].discard(attempt)
        for key in {(node_id, None), (node_id, platform)}:
            self._used[key] = self._used[key] - amount
        return True

    def candidates(self, pool: str | None) -> list[Node]:
        """Nodes of ``pool`` (any pool when None), sorted by id."""
        found = self._by_pool.get(pool)
        if found is None:
            found = [n for n in self.nodes() if pool is None or n.pool == pool]
            self._by_pool[pool] = found
        return found

    def place(self, tasks: Sequence[tuple[str, Request]],
              pool: str | None) -> dict[str, str] | None:
        """First-fit the gang ``tasks`` into what is free now (nothing is reserved)."""
        return first_fit(tasks, self.candidates(pool), self._used)  # Used: read only there


def total(amounts: Iterable[Capacity]) -> Capacity:
    """The sum of ``amounts``."""
    result = ZERO
    for amount in amounts:
        result = result + amount
    return result
