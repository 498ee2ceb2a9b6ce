"""What one turn of the engine's loop accumulates, and its commit in one transaction.

The engine fills a :class:`Batch` while it handles a turn's events and requests: the
scheduler's commands, the rows to write beside the scheduler's changes, and the answers to
give once they are stored. :meth:`Batch.commit` writes it all atomically, before any command
of the batch is executed (``osmo.server.engine``). Engine thread only.
"""

from __future__ import annotations

from concurrent.futures import Future
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from osmo.scheduler import Scheduler
from osmo.scheduler.types import AttemptPrepared, AttemptStarted, Changes, Command, PrepareAttempt
from osmo.server.recovery import attempt_row
from osmo.store.sqlite import AttemptRow, DatasetRow, LineageRow, NewWorkflowRow, Store, TagRow

__all__ = ["HOLD_STARTS", "Batch", "HeldStarts"]

HOLD_STARTS = 0.01
"""Seconds start reports may wait, uncommitted, for the next commit (``HeldStarts``)."""
_HOLD_MOST = 256  # start reports held at once, at the most


@dataclass
class Batch:
    """One turn's commands, rows and answers.

    Attributes:
        commands: the scheduler's commands, executed after the commit.
        workflows, attempts, lineage, datasets, tags: rows to write with the changes.
        workflow_tags: workflow id → its whole new tag list (``osmo workflow tag``).
        pids: ``(attempt id, pid, its start time)`` of attempts started as local processes.
        replies: answers to requests, given after the commit.
        ended: attempts whose final report was applied (provenance forgets them).
    """

    commands: list[Command] = field(default_factory=list)
    workflows: list[NewWorkflowRow] = field(default_factory=list)
    attempts: list[AttemptRow] = field(default_factory=list)
    lineage: list[LineageRow] = field(default_factory=list)
    datasets: list[DatasetRow] = field(default_factory=list)
    tags: list[TagRow] = field(default_factory=list)
    workflow_tags: dict[str, list[str]] = field(default_factory=dict)
    pids: list[tuple[str, int, float | None]] = field(default_factory=list)
    replies: list[tuple[Future[Any], Any]] = field(default_factory=list)
    ended: list[str] = field(default_factory=list)

    def commit(self, store: Store, scheduler: Scheduler,
               home: Path) -> tuple[Changes, list[PrepareAttempt]]:
        """Take the scheduler's changes and write them with this batch's rows.

        An attempt row is added for each placement. Returns the changes and the placements.

        Raises:
            InfrastructureError: the store refused the transaction (nothing was written).
        """
        changes = scheduler.take_changes()
        placed = [c for c in self.commands if isinstance(c, PrepareAttempt)]
        self.attempts += [attempt_row(home, p.attempt_id, p.node_id) for p in placed]
        if (changes or self.workflows or self.attempts or self.lineage or self.datasets
                or self.tags or self.pids or self.workflow_tags):
            store.commit(changes, new_workflows=self.workflows, attempts=self.attempts,
                         lineage=self.lineage, datasets=self.datasets, tags=self.tags,
                         pids=self.pids, workflow_tags=self.workflow_tags)
        return changes, placed


class HeldStarts:
    """A turn of start reports kept in hand until the next commit (engine thread).

    A turn that applied nothing but ``AttemptPrepared``/``AttemptStarted`` reports and made no
    command needs no commit before anything (``osmo.server.engine``): its batch (the pids)
    is kept, the next turn goes on filling it, and its commit stores both. It is committed
    :data:`HOLD_STARTS` seconds later at the latest (the engine's wait ends then).

    Args:
        seconds: how long a held turn may wait (0: never hold).
    """

    def __init__(self, seconds: float = HOLD_STARTS) -> None:
        self._seconds = seconds
        self._batch: Batch | None = None
        self._items: list[Any] = []
        self._until = 0.0

    def batch(self) -> Batch:
        """The held batch, to go on filling, or a new one."""
        return self._batch if self._batch is not None else Batch()

    def hold(self, items: list[Any], batch: Batch, now: float) -> bool:
        """Keep ``batch`` uncommitted if this turn (``items``) may wait; True if kept."""
        if (self._seconds <= 0 or not items or batch.commands
                or len(self._items) + len(items) > _HOLD_MOST
                or not all(isinstance(i, (AttemptPrepared, AttemptStarted)) for i in items)):
            return False
        if self._batch is None:
            self._until = now + self._seconds
        self._batch = batch
        self._items += items
        return True

    def release(self) -> list[Any]:
        """Forget the held turn (it is being committed, or lost); returns its reports."""
        items, self._batch, self._items = self._items, None, []
        return items

    def deadline(self, other: float | None) -> float | None:
        """The earlier of ``other`` and when the held turn must be committed."""
        if self._batch is None:
            return other
        return self._until if other is None else min(other, self._until)
