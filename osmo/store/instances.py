"""What cluster nodes label their objects with, and the instances still to be swept.

The rows behind ``osmo.server.sweeps.Sweeps``: ``node_instances`` holds each registered
node's pool and instance label; ``sweeps`` the instances of nodes down for good whose
objects a live node of their pool has not yet been ordered to delete. Kept so that a
restarted server still knows them.

A mixin of ``osmo.store.sqlite.Store`` (which owns the connection and the transaction).
Must not import sqlite3.
"""

from __future__ import annotations

from contextlib import AbstractContextManager
from typing import Any

__all__ = ["InstanceRows"]


class InstanceRows:
    """Node instance and pending sweep rows; needs ``self._read`` and ``self._tx``."""

    def _read(self, sql: str, args: tuple[Any, ...] = ()) -> list[Any]:
        raise NotImplementedError

    def _tx(self) -> AbstractContextManager[Any]:
        raise NotImplementedError

    def set_node_instance(self, node: str, pool: str, instance: str | None) -> None:
        """Node ``node`` of ``pool`` labels its objects ``instance`` (None: it makes none)."""
        with self._tx() as db:
            if instance is None:
                db.execute("DELETE FROM node_instances WHERE node = ?", (node,))
            else:
                db.execute("INSERT OR REPLACE INTO node_instances VALUES (?,?,?)",
                           (node, pool, instance))

    def node_down(self, node: str, pool: str, instance: str) -> None:
        """Node ``node`` is down for good: its instance is to be swept by ``pool``."""
        with self._tx() as db:
            db.execute("DELETE FROM node_instances WHERE node = ?", (node,))
            db.execute("INSERT OR IGNORE INTO sweeps VALUES (?,?)", (pool, instance))

    def drop_sweep(self, pool: str, instance: str) -> None:
        """``instance`` is no longer to be swept by ``pool`` (swept, or held again)."""
        with self._tx() as db:
            db.execute("DELETE FROM sweeps WHERE pool = ? AND instance = ?", (pool, instance))

    def node_instances(self) -> dict[str, tuple[str, str]]:
        """Node id → (pool, instance) of every node recorded."""
        return {str(node): (str(pool), str(instance)) for node, pool, instance
                in self._read("SELECT node, pool, instance FROM node_instances")}

    def pending_sweeps(self) -> dict[str, set[str]]:
        """Pool → the instances its nodes are still to sweep."""
        out: dict[str, set[str]] = {}
        for pool, instance in self._read("SELECT pool, instance FROM sweeps"):
            out.setdefault(str(pool), set()).add(str(instance))
        return out
