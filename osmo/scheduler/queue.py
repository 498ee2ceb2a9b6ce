"""The placement queue and the deadline heap.

This module owns two orderings and nothing else: which placement requests wait (FIFO by
workflow submit order, then group order, then enqueue order) and which timeouts are due.
Both drop stale entries lazily, so removing a request or a deadline is O(1).
"""

from __future__ import annotations

import bisect
import heapq
import itertools
from dataclasses import dataclass

from osmo.scheduler.runs import Group, Queued, Run

__all__ = ["Deadline", "Deadlines", "PlacementQueue"]


class PlacementQueue:
    """Requests waiting for resources.

    A placement pass only needs to revisit *old* requests when capacity grew (an attempt
    released its resources or a node joined): otherwise they failed against at least as much
    free room before, so only the requests added since the last pass are tried.
    """

    def __init__(self) -> None:
        self._items: list[Queued] = []  # sorted by key; may hold dead entries
        self._fresh: list[Queued] = []
        self._dead = 0
        self.capacity_grew = False

    def __len__(self) -> int:
        return len(self._items) - self._dead

    def push(self, request: Queued) -> None:
        """Queue ``request`` in FIFO position."""
        bisect.insort(self._items, request, key=_key)
        self._fresh.append(request)

    def take_candidates(self) -> list[Queued]:
        """The requests a placement pass should try, in FIFO order (may include stale ones)."""
        if self.capacity_grew:
            found = self._items
        else:
            found = sorted(self._fresh, key=_key) if len(self._fresh) > 1 else self._fresh
        self.capacity_grew = False
        self._fresh = []
        return found

    def done(self, request: Queued) -> None:
        """Mark ``request`` placed or stale; it is dropped at the next compaction."""
        if request.live:
            request.live = False
            self._dead += 1

    def compact(self) -> None:
        """Drop dead entries when they make up half the queue."""
        if self._dead * 2 >= len(self._items):
            self._items = [q for q in self._items if q.live]
            self._dead = 0


def _key(request: Queued) -> tuple[int, int, int]:
    return request.key


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
