"""The engine's executor: each command goes to the local pool or to the remote-worker hub."""

from __future__ import annotations

import collections
from collections.abc import Callable

from osmo.scheduler.types import PrepareAttempt
from osmo.server.workers import WorkerHub
from osmo.spec.model import TaskSpec
from osmo.worker.pool import LocalPool

__all__ = ["Dispatcher"]

_REMEMBER = 100_000


class Dispatcher:
    """The engine's executor: the local pool for node ``local``, the hub for the rest."""

    def __init__(self, pool: LocalPool | None, hub: WorkerHub,
                 node_of: Callable[[str], str | None] = lambda _aid: None) -> None:
        self._pool, self._hub = pool, hub
        self._lookup = node_of  # restored attempts: their node, asked of the scheduler
        self._node_of: collections.OrderedDict[str, str] = collections.OrderedDict()

    def _node(self, attempt_id: str) -> str:
        return self._node_of.get(attempt_id) or self._lookup(attempt_id) or "local"

    def prepare(self, cmd: PrepareAttempt, task: TaskSpec, *,
                max_output_bytes: int | None = None) -> None:
        """Route a placement by its node."""
        self._node_of[cmd.attempt_id] = cmd.node_id
        while len(self._node_of) > _REMEMBER:
            self._node_of.popitem(last=False)
        if self._pool is not None and cmd.node_id == "local":
            self._pool.prepare(cmd, task, max_output_bytes=max_output_bytes)
        else:
            self._hub.prepare(cmd, task, max_output_bytes=max_output_bytes)

    def run(self, attempt_id: str) -> None:
        """Route by the attempt's node."""
        node = self._node(attempt_id)
        if node == "local" and self._pool is not None:
            self._pool.run(attempt_id)
        else:
            self._hub.run(node, attempt_id)

    def kill(self, attempt_id: str, reason: str) -> None:
        """Route by the attempt's node (restored attempts: found from their id's node)."""
        node = self._node(attempt_id)
        if node == "local" and self._pool is not None:
            self._pool.kill(attempt_id, reason)
        else:
            self._hub.kill(node, attempt_id, reason)

    def running(self) -> dict[str, int]:
        """Pids of the local pool's running attempts (remote ones have no local pid)."""
        return self._pool.running() if self._pool is not None else {}
