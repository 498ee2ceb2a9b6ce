"""The placement queue and the deadline heap.

This module owns two orderings and nothing else: which placement requests wait (by their
``Queued.key``: priority with ageing, then workflow submit order, group order and enqueue
order) and which timeouts are due.
Both drop stale entries lazily, so removing a request or a deadline is O(1).
"""

from __future__ import annotations

import heapq
import itertools
from collections.abc import Hashable, Iterator
from dataclasses import dataclass

from osmo.scheduler.runs import Group, Queued, Run

__all__ = ["Deadline", "Deadlines", "PlacementQueue"]


class PlacementQueue:
    """Requests waiting for resources, kept per *shape* (pool + per-task requests).

    Requests of one shape fit or fail alike, and placements only consume room, so once a
    shape fails it is *blocked* until capacity grows (an attempt released its resources or a
    node joined). A pass therefore visits only the head of each unblocked shape, in global
    FIFO order: O(shapes + placements), however long the queue is.
    """

    def __init__(self) -> None:
        self._by_shape: dict[Hashable, list[tuple[tuple[float, int, int, int], Queued]]] = {}
        self._blocked: set[Hashable] = set()

    def push(self, request: Queued) -> None:
        """Queue ``request`` in its ``key``'s position."""
        heapq.heappush(self._by_shape.setdefault(request.shape, []), (request.key, request))

    def capacity_grew(self) -> None:
        """Room was freed or added: every shape may fit again."""
        self._blocked.clear()

    def block(self, shape: Hashable) -> None:
        """``shape`` does not fit now; skip it until capacity grows."""
        self._blocked.add(shape)

    def done(self, request: Queued) -> None:
        """Mark ``request`` placed or stale; it leaves the queue lazily."""
        request.live = False

    def pending(self) -> Iterator[Queued]:
        """Heads of unblocked shapes in FIFO order, until every shape is blocked or empty.

        For each request yielded, the caller must call :meth:`done` (placed or stale) or
        :meth:`block` with its shape before asking for the next one.
        """
        heads = [(h[0][0], i, shape) for i, shape in enumerate(list(self._by_shape))
                 if shape not in self._blocked and (h := self._head(shape))]
        heapq.heapify(heads)
        while heads:
            _, i, shape = heapq.heappop(heads)
            items = self._by_shape[shape]
            request = items[0][1]
            yield request
            if shape in self._blocked:
                continue
            assert not request.live, "pending(): request neither done nor blocked"
            head = self._head(shape)
            if head:
                heapq.heappush(heads, (head[0][0], i, shape))

    def _head(self, shape: Hashable) -> list[tuple[tuple[float, int, int, int], Queued]]:
        """The shape's heap with dead heads dropped (emptied shapes are forgotten)."""
        items = self._by_shape[shape]
        while items and not items[0][1].live:
            heapq.heappop(items)
        if not items:
            del self._by_shape[shape]
            self._blocked.discard(shape)
        return items


@dataclass(frozen=True, eq=False)
class Deadline:
    """A timeout due at ``at``: a queued request's queue timeout or a group's exec timeout."""

    at: float
    request: Queued | None = None
    run: Run | None = None
    group: Group | None = None

    def pending(self) -> bool:
        """True while firing it would still change something."""
        if self.request is not None:
            return self.request.valid()
        assert self.group is not None
        return not self.group.closing and self.group.exec_deadline == self.at


class Deadlines:
    """A min-heap of deadlines with lazy removal of those no longer pending."""

    def __init__(self) -> None:
        self._heap: list[tuple[float, int, Deadline]] = []
        self._seq = itertools.count()
        self._limit = 64  # rebuild without stale entries when the heap outgrows this

    def push(self, deadline: Deadline) -> None:
        """Add ``deadline``."""
        heapq.heappush(self._heap, (deadline.at, next(self._seq), deadline))
        if len(self._heap) > self._limit:  # amortised O(1): the limit doubles
            self._heap = [e for e in self._heap if e[2].pending()]
            heapq.heapify(self._heap)
            self._limit = 2 * len(self._heap) + 64

    def earliest(self) -> float | None:
        """The earliest pending deadline, dropping stale ones on the way."""
        while self._heap and not self._heap[0][2].pending():
            heapq.heappop(self._heap)
        return self._heap[0][0] if self._heap else None

    def pop_due(self, now: float) -> Deadline | None:
        """The next pending deadline at or before ``now``, removed; None when none is due."""
        while self._heap and self._heap[0][0] <= now:
            deadline = heapq.heappop(self._heap)[2]
            if deadline.pending():
                return deadline
        return None
