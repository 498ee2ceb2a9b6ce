"""The engine's executor: each command goes to the local pool or to the remote-worker hub."""

from __future__ import annotations

from osmo.scheduler.types import LOCAL_NODE, KillAttempt, PrepareAttempt, RunAttempt
from osmo.server.workers import WorkerHub
from osmo.spec.model import TaskSpec
from osmo.worker.pool import LocalPool

__all__ = ["Dispatcher"]


class Dispatcher:
    """The engine's executor: the local pool for node ``local``, the hub for the rest."""

    def __init__(self, pool: LocalPool | None, hub: WorkerHub) -> None:
        self._pool, self._hub = pool, hub

    def prepare(self, cmd: PrepareAttempt, task: TaskSpec, *,
                max_output_bytes: int | None = None) -> None:
        """Route a placement by its node."""
        if self._pool is not None and cmd.node_id == LOCAL_NODE:
            self._pool.prepare(cmd, task, max_output_bytes=max_output_bytes)
        else:
            self._hub.prepare(cmd, task, max_output_bytes=max_output_bytes)

    def run(self, cmd: RunAttempt) -> None:
        """Route by the attempt's node."""
        if cmd.node_id == LOCAL_NODE and self._pool is not None:
            self._pool.run(cmd.attempt_id)
        else:
            self._hub.run(cmd.node_id, cmd.attempt_id)

    def kill(self, cmd: KillAttempt) -> None:
        """Route by the attempt's node."""
        if cmd.node_id == LOCAL_NODE and self._pool is not None:
            self._pool.kill(cmd.attempt_id, cmd.reason)
        else:
            self._hub.kill(cmd.node_id, cmd.attempt_id, cmd.reason)
