"""The scheduler's mutable world and the few primitives every rule goes through.

This module owns the containers (runs, the attempt index, the node ledger, the queue, the
deadlines), the outgoing commands of the event being handled, the change journal, and the
single choke point for status changes (:meth:`World.set_status`), which keeps the per-run
counters, the transition log and the barrier membership consistent. Rules live in
``placement``, ``groups`` and ``attempts``; they call into this module, never the reverse.
"""

from __future__ import annotations

import itertools

from osmo.scheduler.queue import Deadline, Deadlines, PlacementQueue, PoolAlarm
from osmo.scheduler.resources import Ledger
from osmo.scheduler.runs import Group, Run, workflow_outcome
from osmo.scheduler.state import TaskState, WorkflowState
from osmo.scheduler.types import Changes, Command, KillAttempt, Node, RunAttempt, Transition
from osmo.status import TaskStatus, WorkflowStatus

__all__ = ["World"]


class World:
    """State shared by the scheduler's rules while they handle one event at ``now``."""

    def __init__(self, *, default_max_retries: int, max_lost_retries: int,
                 no_worker_timeout: float | None = None) -> None:
        self.default_max_retries = default_max_retries
        self.max_lost_retries = max_lost_retries
        self.no_worker_timeout = no_worker_timeout
        # pool (None: any pool) → since when it has had no node; first noticed, if never had
        self.empty_since: dict[str | None, float] = {}
        self.alarms: set[str | None] = set()  # pools with a PoolAlarm deadline pending
        self.runs: dict[str, Run] = {}
        self.attempts: dict[str, tuple[Run, str]] = {}  # current attempt id → (run, task)
        self.ledger = Ledger()
        self.queue = PlacementQueue()
        self.deadlines = Deadlines()
        self.seq = itertools.count()
        self.now = 0.0
        self.out: list[Command] = []
        self._dirty: dict[str, Run] = {}  # runs whose workflow status may change
        self._tasks: dict[tuple[str, str], TaskState] = {}
        self._workflows: dict[str, WorkflowState] = {}
        self._transitions: list[Transition] = []

    # ------------------------------------------------------------------ nodes

    def node_up(self, node: Node) -> None:
        """Add or replace ``node``: its pool, and the cluster, are no longer empty."""
        self.ledger.up(node)
        self.empty_since.pop(node.pool, None)
        self.empty_since.pop(None, None)
        self.queue.capacity_grew()

    def node_down(self, node_id: str) -> list[str]:
        """Remove a node; return the attempts it held. Its pool may become empty now."""
        node = self.ledger.node(node_id)
        held = self.ledger.down(node_id)
        if node is not None and not self.ledger.candidates(node.pool):
            self.empty_since[node.pool] = self.now
            self.arm_alarm(node.pool)
        if not self.ledger.candidates(None):
            self.empty_since.setdefault(None, self.now)
            self.arm_alarm(None)
        return held

    def pool_empty_since(self, pool: str | None) -> float | None:
        """Since when ``pool`` (None: the cluster) has had no node; None while it has one."""
        if self.ledger.candidates(pool):
            return None
        return self.empty_since.setdefault(pool, self.now)

    def arm_alarm(self, pool: str | None, at: float | None = None) -> None:
        """Make sure a ``PoolAlarm`` checks the requests waiting on empty ``pool``.

        Due at ``at``, by default when the pool has been empty for the no-worker timeout.
        """
        if self.no_worker_timeout is None or pool in self.alarms:
            return
        since = self.pool_empty_since(pool)
        if since is None:
            return
        self.alarms.add(pool)
        due = since + self.no_worker_timeout if at is None else at
        self.deadlines.push(Deadline(due, alarm=PoolAlarm(pool)))

    # ------------------------------------------------------------------ journal

    def take_changes(self) -> Changes:
        """Copies of what changed since the last call, and the transitions logged."""
        changes = Changes(
            workflows=[w.copy() for w in self._workflows.values()],
            tasks=[t.copy() for t in self._tasks.values()],
            transitions=self._transitions,
        )
        self._tasks, self._workflows, self._transitions = {}, {}, []
        return changes

    def touch(self, run: Run) -> None:
        """Record that ``run``'s workflow status may need a refresh at the end of the event."""
        self._dirty[run.id] = run

    def note_workflow(self, run: Run) -> None:
        """Record that ``run``'s workflow state changed (it goes into the next Changes)."""
        self._workflows[run.id] = run.state

    def log(self, run: Run, task: TaskState | None, status: str, message: str) -> None:
        """Append a transition of ``task`` (None: of the workflow) at ``now``."""
        self._transitions.append(Transition(
            at=self.now, workflow_id=run.id, task=task.name if task else None,
            retry=task.retry if task else None, status=status, message=message))

    # ------------------------------------------------------------------ task primitives

    def note_task(self, run: Run, task: TaskState) -> None:
        """Record that ``task`` changed without a status change (it goes into the next Changes)."""
        self._tasks[(run.id, task.name)] = task

    def set_status(self, run: Run, task: TaskState, status: TaskStatus,
                   message: str | None = None) -> None:
        """Change ``task``'s status, keeping counters, the log and barrier batches right."""
        old = task.status
        run.running += (status is TaskStatus.RUNNING) - (old is TaskStatus.RUNNING)
        run.active += status.active - old.active
        task.status = status
        if message is not None:
            task.message = message
        if not status.active:  # what its node said of an attempt it no longer has
            task.node_wait, task.node_wait_since = "", None
        if status.terminal:
            task.ended_at = self.now
        if status is TaskStatus.RUNNING and run.state.started_at is None:
            run.state.started_at = self.now
            self.note_workflow(run)
        self.log(run, task, status.name, task.message)
        self._tasks[(run.id, task.name)] = task
        self.touch(run)
        if old.active and not status.active:
            self._leave_batch(run, run.group_of(task), task.name)

    def end_task(self, run: Run, task: TaskState, status: TaskStatus, exit_code: int | None,
                 message: str, kill: str | None = None) -> None:
        """Make ``task`` terminal; with ``kill``, stop its attempt first if one is active.

        The attempt's resources stay reserved until its final report arrives.
        """
        if kill is not None and task.status.active and task.attempt_id is not None:
            assert task.node_id is not None  # an active attempt is placed
            self.out.append(KillAttempt(task.attempt_id, task.node_id, kill))
        task.exit_code = exit_code
        self.set_status(run, task, status, message)

    # ------------------------------------------------------------------ barrier

    def release_barrier(self, run: Run, group: Group) -> None:
        """Emit RunAttempt for the batch once every remaining member is prepared."""
        batch = group.batch
        if batch is None or batch.released or group.closing:
            return
        if not batch.members or not group.prepared.issuperset(batch.members):
            return
        batch.released = True
        for name in batch.members:
            task = run.tasks[name]
            assert task.attempt_id is not None and task.node_id is not None
            self.out.append(RunAttempt(task.attempt_id, task.node_id))

    def _leave_batch(self, run: Run, group: Group, name: str) -> None:
        group.prepared.discard(name)
        batch = group.batch
        if batch is not None and not batch.released and name in batch.members:
            batch.members.remove(name)
            self.release_barrier(run, group)

    # ------------------------------------------------------------------ workflow status

    def refresh(self) -> None:
        """Re-derive the status of every workflow touched by this event."""
        for run in self._dirty.values():
            self._refresh(run)
        self._dirty.clear()

    def _refresh(self, run: Run) -> None:
        state = run.state
        if state.status.terminal:
            return
        if run.open_groups == 0:
            self._finish(run)
            return
        if run.running:
            status = WorkflowStatus.RUNNING
        elif state.started_at is not None and not run.active:
            status = WorkflowStatus.WAITING
        else:
            return
        if status is not state.status:
            state.status = status
            self.note_workflow(run)
            self.log(run, None, status.name, state.message)

    def _finish(self, run: Run) -> None:
        state = run.state
        state.status = workflow_outcome(g.outcome for g in run.groups.values()
                                        if g.outcome is not None)
        state.ended_at = self.now
        failed = [g for g in run.groups.values() if g.outcome is not TaskStatus.COMPLETED]
        if failed:
            shown = ", ".join(f"{g.name} ({g.outcome.name if g.outcome else '?'})"
                              for g in failed[:5])
            more = f" and {len(failed) - 5} more" if len(failed) > 5 else ""
            state.message = f"groups not completed: {shown}{more}"
        self.note_workflow(run)
        self.log(run, None, state.status.name, state.message)
