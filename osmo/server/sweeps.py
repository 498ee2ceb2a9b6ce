"""What nodes down for good left in their cluster, until a node of their pool deletes it.

A Kubernetes node labels every object it makes with its instance (``osmo.dev/instance``;
its hello's ``instance``). Alive, or away within its grace, its objects are its own: it
adopts or deletes them itself when it comes back. Once its grace ended (its attempts were
lost and rescheduled: the server no longer holds them), nothing of it is wanted any more,
and the server orders one live node of the same pool (the same namespace) to delete them
(``wire.Sweep``), at once or when such a node next registers.

The server decides, never a node: a node cannot name another's instance to have it swept,
and an instance that a registered or away node holds is never swept.
A node that comes back under a swept-to-be instance cleans up after itself instead.

This module keeps that bookkeeping; ``osmo.server.workers`` sends the orders. Each node's
instance and what is still to be swept are written through to the store
(``osmo.store.instances``), so a restarted server knows them: the nodes of its previous
life that do not come back within its grace are down for good then
(:meth:`Sweeps.restored`). An instance is ordered to one node at a time and stays to be
swept until that node says it swept it (``worker_swept``, :meth:`Sweeps.swept`): if that node
leaves (or registers again) first, or the server restarts, it is ordered again, to the next
live node of its pool. An order its node has not confirmed within the retry period (the
server's ``--adopt-grace``) is sent to it again (:meth:`Sweeps.overdue`): a sweep that failed
(the API server refused it, say) is tried again while its node lives. Sweeping twice does no
harm (what is gone is not found again).
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable

from osmo.errors import OsmoError
from osmo.store.instances import InstanceRows

__all__ = ["Sweeps"]

log = logging.getLogger("osmo.server.workers")


class Sweeps:
    """Instances of nodes, and those of nodes down for good still to be swept, per pool.

    Args:
        rows: where they are kept across restarts (None: memory only); read once here.
    """

    def __init__(self, rows: InstanceRows | None = None) -> None:
        self._lock = threading.Lock()
        self._rows = rows
        self._instances: dict[str, tuple[str, str]] = {}  # node id -> (pool, instance)
        self._pending: dict[str, set[str]] = {}  # pool -> instances to sweep
        # (pool, instance) -> (node, when last sent: monotonic s), until that node swept it
        self._ordered: dict[tuple[str, str], tuple[str, float]] = {}
        if rows is not None:
            self._instances = rows.node_instances()
            self._pending = rows.pending_sweeps()
        self._restored = frozenset(self._instances)

    def restored(self) -> frozenset[str]:
        """The nodes the store knew when this server started (its previous life's)."""
        return self._restored

    def registered(self, node: str, pool: str, instance: str | None) -> None:
        """Node ``node`` of ``pool`` registered, labelling its objects ``instance``."""
        now = None if instance is None else (pool, instance)
        with self._lock:
            if self._instances.get(node) == now:
                return
            if now is None:
                del self._instances[node]
            else:
                self._instances[node] = now
            self._write(lambda rows: rows.set_node_instance(node, pool, instance))

    def down(self, node: str) -> None:
        """Node ``node`` is down for good: its instance is to be swept (unless held)."""
        with self._lock:
            found = self._instances.pop(node, None)
            if found is not None:
                pool, instance = found
                self._pending.setdefault(pool, set()).add(instance)
                self._write(lambda rows: rows.node_down(node, pool, instance))

    def sweeper(self, node: str) -> bool:
        """Whether ``node`` can sweep (it labels objects of its own)."""
        with self._lock:
            return node in self._instances

    def due(self, pool: str, node: str) -> list[str]:
        """The instances ``node`` (of ``pool``) is to sweep now; each is ordered to it.

        An instance ordered to a node stays its own until that node says it is swept
        (:meth:`swept`) or leaves (:meth:`release`). An instance a known node holds is
        dropped (that node cleans up after itself).
        """
        with self._lock:
            held = {instance for _pool, instance in self._instances.values()}
            pending = self._pending.get(pool, set())
            for instance in sorted(pending & held):
                self._drop(pool, instance)
            out = sorted(i for i in pending if (pool, i) not in self._ordered)
            now = time.monotonic()
            for instance in out:
                self._ordered[(pool, instance)] = (node, now)
            return out

    def overdue(self, after: float) -> list[tuple[str, str]]:
        """The unconfirmed orders last sent ``after`` seconds ago or more, to send again.

        ``(node, instance)`` each; they count as sent now.
        """
        now = time.monotonic()
        with self._lock:
            late = [(key, node) for key, (node, sent) in self._ordered.items()
                    if now - sent >= after]
            for key, node in late:
                self._ordered[key] = (node, now)
            return sorted((node, instance) for (_pool, instance), node in late)

    def swept(self, node: str, instance: str) -> bool:
        """``node`` says it swept ``instance``: done, if that was ordered to it."""
        with self._lock:
            found = next((pool for (pool, i), (n, _) in self._ordered.items()
                          if i == instance and n == node), None)
            if found is not None:
                self._drop(found, instance)
            return found is not None

    def release(self, node: str) -> list[str]:
        """``node`` left, or registered again: what it did not sweep is due again.

        The pools of what it was ordered, to order it again.
        """
        with self._lock:
            mine = [key for key, (n, _) in self._ordered.items() if n == node]
            for key in mine:
                del self._ordered[key]
            return sorted({pool for pool, _ in mine})

    def _drop(self, pool: str, instance: str) -> None:
        """Nothing of ``instance`` is to be swept any more (the lock held)."""
        self._ordered.pop((pool, instance), None)
        pending = self._pending.get(pool)
        if pending is not None:
            pending.discard(instance)
            if not pending:
                del self._pending[pool]
        self._write(lambda rows: rows.drop_sweep(pool, instance))

    def _write(self, change: Callable[[InstanceRows], None]) -> None:
        """Apply ``change(rows)`` to the store; a store that fails leaves it in memory only."""
        if self._rows is None:
            return
        try:
            change(self._rows)
        except OsmoError as exc:
            log.warning("could not keep node instances in the store (kept in memory): %s",
                        exc)
