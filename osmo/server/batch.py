"""What one turn of the engine's loop accumulates, and its commit in one transaction.

The engine fills a :class:`Batch` while it handles a turn's events and requests: the
scheduler's commands, the rows to write beside the scheduler's changes, and the answers to
give once they are stored. :meth:`Batch.commit` writes it all atomically, before any command
of the batch is executed (``osmo.server.engine``). Engine thread only.
"""

from __future__ import annotations

from concurrent.futures import Future
from dataclasses import dataclass, field
from typing import Any

from osmo.layout import Home
from osmo.scheduler import Scheduler
from osmo.scheduler.types import Changes, Command, PrepareAttempt
from osmo.server.recovery import attempt_row
from osmo.store.sqlite import AttemptRow, DatasetRow, LineageRow, NewWorkflowRow, Store, TagRow

__all__ = ["Batch"]


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
               home: Home) -> tuple[Changes, list[PrepareAttempt]]:
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
