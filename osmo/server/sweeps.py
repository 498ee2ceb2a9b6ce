"""What nodes down for good left in their cluster, until a node of their pool deletes it.

A Kubernetes node labels every object it makes with its instance (``osmo.dev/instance``;
its hello's ``instance``). Alive, or away within its grace, its objects are its own: it
adopts or deletes them itself when it comes back. Once its grace ended (its attempts were
lost and rescheduled: the server no longer holds them), nothing of it is wanted any more,
and the server orders one live node of the same pool (the same namespace) to delete them
(``wire.Sweep``), at once or when such a node next registers.

The server decides, never a node: a node cannot name another's instance to have it swept,
and an instance that a registered or away node holds (whatever its pool) is never swept.
A node that comes back under a swept-to-be instance cleans up after itself instead.

This module keeps that bookkeeping (pure, no I/O: ``osmo.server.workers`` sends the
orders). What is pending is held in memory: a server restarted meanwhile forgets it, and
the objects stay until their own node's instance comes back (documented in the chart's
README).
"""

from __future__ import annotations

import threading

__all__ = ["Sweeps"]


class Sweeps:
    """Instances of nodes, and those of nodes down for good still to be swept, per pool."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._instances: dict[str, tuple[str, str]] = {}  # node id -> (pool, instance)
        self._pending: dict[str, set[str]] = {}  # pool -> instances to sweep

    def registered(self, node: str, pool: str, instance: str | None) -> None:
        """Node ``node`` of ``pool`` registered, labelling its objects ``instance``."""
        with self._lock:
            if instance is None:
                self._instances.pop(node, None)
            else:
                self._instances[node] = (pool, instance)

    def down(self, node: str) -> None:
        """Node ``node`` is down for good: its instance is to be swept (unless held)."""
        with self._lock:
            found = self._instances.pop(node, None)
            if found is not None:
                self._pending.setdefault(found[0], set()).add(found[1])

    def sweeper(self, node: str) -> bool:
        """Whether ``node`` can sweep (it labels objects of its own)."""
        with self._lock:
            return node in self._instances

    def due(self, pool: str) -> list[str]:
        """The instances a node of ``pool`` is to sweep now (taken: each is ordered once).

        An instance a known node holds is not swept (that node cleans up after itself).
        """
        with self._lock:
            held = {instance for _pool, instance in self._instances.values()}
            return sorted(self._pending.pop(pool, set()) - held)
