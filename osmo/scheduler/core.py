"""The scheduler: a pure, event-driven state machine over workflows, tasks and nodes.

This module owns the public facade (:class:`Scheduler`), event dispatch, submit and restore.
It performs no I/O, starts no threads, never sleeps and never reads the clock: ``now`` comes
with every event. Each ``handle()`` does only the work that event enables — it fires due
timeouts, applies the event, places what now fits, cascades and aggregates — in time
proportional to what it touches (tasks are indexed by attempt id, groups keep counters,
placement scans only the queue of waiting requests).

Order inside one ``handle(event, now)``: due timeouts fire first (a deadline at or before
``now`` wins over a report arriving at the same time), then the event, then placement, then
workflow statuses are re-derived. ``handle`` raises only for a malformed submit, and does so
before changing anything.

Reuse (``WorkflowSubmitted.reused``) is per group: a group completes at once, its tasks
COMPLETED with ``reused=True`` and the given output refs, only when *every* task of it has
an entry; otherwise the whole group runs (a gang is never half reused).
"""

from __future__ import annotations

from collections import defaultdict
from collections.abc import Collection

from osmo.scheduler import attempts, groups
from osmo.scheduler.fit import check_fit
from osmo.scheduler.placement import enqueue, place_pending, placement_of
from osmo.scheduler.runs import Run, group_outcome
from osmo.scheduler.state import TaskState, WorkflowState
from osmo.scheduler.types import (
    DEFAULT_MAX_RETRIES,
    DEFAULT_NO_WORKER_TIMEOUT,
    PRIORITIES,
    AttemptExited,
    AttemptLost,
    AttemptPrepared,
    AttemptStarted,
    AttemptStartFailed,
    AttemptWaiting,
    CancelWorkflow,
    Capacity,
    Changes,
    Command,
    Event,
    Node,
    NodeDown,
    NodeUp,
    PrepareAttempt,
    Tick,
    Waiting,
    WorkflowSubmitted,
)
from osmo.scheduler.waiting import waiting
from osmo.scheduler.world import World
from osmo.spec.model import WorkflowSpec
from osmo.status import TaskStatus

__all__ = ["Scheduler"]

_REPORTS = (AttemptPrepared, AttemptStarted, AttemptExited, AttemptStartFailed, AttemptLost,
            AttemptWaiting)


class Scheduler:
    """Owns statuses, retries, timeouts, gang placement, cascades and cancel.

    Usage: feed events with :meth:`handle`, execute the returned commands *after* persisting
    :meth:`take_changes`, and send a ``Tick`` at :meth:`next_deadline`.

    Args:
        default_max_retries: RESCHEDULE cap for restored workflows whose state has none
            (submits carry their own cap in ``WorkflowSubmitted.max_retries``).
        max_lost_retries: how many times a task is retried after lost attempts.
        no_worker_timeout: seconds a task of a workflow with no ``queue_timeout`` waits on a
            pool with no node before it fails (None: forever); see ``groups``.
    """

    def __init__(self, *, default_max_retries: int = DEFAULT_MAX_RETRIES,
                 max_lost_retries: int = 5,
                 no_worker_timeout: float | None = DEFAULT_NO_WORKER_TIMEOUT) -> None:
        self._world = World(default_max_retries=default_max_retries,
                            max_lost_retries=max_lost_retries,
                            no_worker_timeout=no_worker_timeout)

    # ------------------------------------------------------------------ events

    def handle(self, event: Event, now: float) -> list[Command]:
        """Apply ``event`` at time ``now``; return the commands to execute, in order.

        Raises:
            ValueError: a WorkflowSubmitted reuses a known workflow id.
            TypeError: a WorkflowSubmitted carries no WorkflowSpec.
        """
        world = self._world
        world.now, world.out = now, []
        submit = event if isinstance(event, WorkflowSubmitted) else None
        new_run = self._new_run(submit) if submit is not None else None
        self._fire_due()
        if isinstance(event, _REPORTS):
            attempts.on_report(world, event)
        elif submit is not None and new_run is not None:
            self._submit(new_run, submit.reused)
        elif isinstance(event, CancelWorkflow):
            run = world.runs.get(event.workflow_id)
            if run is not None:
                groups.cancel(world, run)
        elif isinstance(event, NodeUp):
            world.node_up(event.node)
        elif isinstance(event, NodeDown):
            self._node_down(event.node_id)
        else:
            assert isinstance(event, Tick), event
        place_pending(world)
        world.refresh()
        out, world.out = world.out, []
        return out

    def _fire_due(self) -> None:
        world = self._world
        while (due := world.deadlines.pop_due(world.now)) is not None:
            if due.alarm is not None:
                groups.expire_no_worker(world, due.alarm.pool)
            elif due.request is not None:
                groups.expire_queue(world, due.request)
            else:
                assert due.run is not None and due.group is not None
                groups.expire_exec(world, due.run, due.group)

    def _node_down(self, node_id: str) -> None:
        world = self._world
        lost: list[tuple[Run, TaskState]] = []
        for aid in world.node_down(node_id):
            found = world.attempts.get(aid)
            if found is None:
                continue
            run, name = found
            task = run.tasks[name]
            if task.attempt_id == aid and task.status.active:
                run.group_of(task).prepared.discard(name)  # never release it at a barrier
                lost.append((run, task))
        for run, task in lost:
            if task.status.active:  # an earlier loss may have ended its group
                attempts.lose(world, run, task, f"node '{node_id}' down")

    def _new_run(self, event: WorkflowSubmitted) -> Run:
        """Validate a submit and build its records; changes nothing (raises first)."""
        spec = event.spec
        if not isinstance(spec, WorkflowSpec):
            raise TypeError(f"WorkflowSubmitted.spec must be a WorkflowSpec, not "
                            f"{type(spec).__name__}")
        if event.workflow_id in self._world.runs:
            raise ValueError(f"workflow '{event.workflow_id}' is already known")
        if event.priority not in PRIORITIES:
            raise ValueError(f"priority must be one of {', '.join(PRIORITIES)}, not "
                             f"{event.priority!r}")
        state = WorkflowState(event.workflow_id, spec.name, pool=event.pool,
                              max_retries=event.max_retries, submitted_at=self._world.now,
                              priority=event.priority)
        run = Run.build(spec, state, next(self._world.seq), event.max_retries)
        for spec_task in spec.all_tasks():
            name = spec_task.name
            run.tasks[name] = TaskState(run.id, name, run.graph.group_of(name),
                                        created_at=self._world.now)
        return run

    def _submit(self, run: Run, reused: dict[str, str]) -> None:
        world = self._world
        world.runs[run.id] = run
        world.note_workflow(run)
        world.touch(run)
        world.log(run, None, run.state.status.name, "")
        for name in run.graph.topological_order():
            self._start_group(run, name, reused)

    def _start_group(self, run: Run, name: str, reused: dict[str, str]) -> None:
        """Set a new group's first status (topological order: its upstream are settled)."""
        world, group = self._world, run.groups[name]
        if all(t.name in reused for t in group.spec.tasks):
            for spec in group.spec.tasks:
                task = run.tasks[spec.name]
                task.output, task.reused, task.exit_code = reused[spec.name], True, 0
                world.set_status(run, task, TaskStatus.COMPLETED, "reused")
            group.closing, group.outcome = True, TaskStatus.COMPLETED
            run.open_groups -= 1
            for child in run.graph.children(name):
                run.groups[child].waiting_on -= 1
        elif group.waiting_on == 0:
            groups.open_group(world, run, group)
        else:
            for spec in group.spec.tasks:
                world.set_status(run, run.tasks[spec.name], TaskStatus.WAITING)

    # ------------------------------------------------------------------ queries

    def take_changes(self) -> Changes:
        """Copies of workflows and tasks changed since the last call, plus transitions."""
        return self._world.take_changes()

    def next_deadline(self) -> float | None:
        """The earliest time a ``Tick`` could change something (a timeout), or None."""
        return self._world.deadlines.earliest()

    def check_fit(self, spec: WorkflowSpec, pool: str | None) -> list[str]:
        """Reasons ``spec`` can never be placed in ``pool`` on the known nodes; [] = ok."""
        return check_fit(spec, pool, self._world.ledger.nodes())

    def workflow(self, workflow_id: str) -> WorkflowState:
        """A copy of the workflow's state. Raises KeyError if unknown."""
        return self._world.runs[workflow_id].state.copy()

    def tasks(self, workflow_id: str) -> list[TaskState]:
        """Copies of the workflow's tasks in spec order. Raises KeyError if unknown."""
        return [t.copy() for t in self._world.runs[workflow_id].tasks.values()]

    def placement(self, attempt_id: str) -> PrepareAttempt | None:
        """The command that placed ``attempt_id``, if it is a task's current active attempt.

        For a restarted server: what it must know of an attempt an earlier server placed
        (its inputs, for the attempt's lineage). Changes nothing.
        """
        found = self._world.attempts.get(attempt_id)
        if found is None:
            return None
        run, name = found
        task = run.tasks[name]
        if task.attempt_id != attempt_id or not task.status.active:
            return None
        return placement_of(self._world, run, name)

    def waiting(self, workflow_id: str,
                names: Collection[str] | None = None) -> dict[str, Waiting]:
        """Why each WAITING or SCHEDULING task of the workflow (of ``names``) waits, now.

        Unknown (or forgotten, terminal) workflows have nothing waiting.
        """
        run = self._world.runs.get(workflow_id)
        return waiting(self._world, run, names) if run is not None else {}

    def attempt(self, attempt_id: str) -> TaskState | None:
        """A copy of the task whose current attempt is ``attempt_id``, if any."""
        found = self._world.attempts.get(attempt_id)
        if found is None:
            return None
        task = found[0].tasks[found[1]]
        return task.copy() if task.attempt_id == attempt_id else None

    def nodes(self) -> list[Node]:
        """Known nodes, sorted by id."""
        return self._world.ledger.nodes()

    def attempts_on(self, node_id: str) -> list[str]:
        """Ids of the attempts placed on ``node_id`` that have not sent their final report."""
        return self._world.ledger.held_on(node_id)

    def used(self, node_id: str, platform: str | None = None) -> Capacity:
        """Resources held on ``node_id`` (of ``platform``) by unfinished attempts.

        (Those that have not sent their final report.)
        """
        return self._world.ledger.used(node_id, platform)

    def forget(self, workflow_id: str) -> None:
        """Drop a terminal workflow from memory (unknown ids are ignored).

        Reservations of its killed attempts stay until their final reports arrive.

        Raises:
            ValueError: the workflow is not terminal.
        """
        world = self._world
        run = world.runs.get(workflow_id)
        if run is None:
            return
        if not run.state.status.terminal:
            raise ValueError(f"workflow '{workflow_id}' is {run.state.status.name}, "
                             f"not terminal")
        del world.runs[workflow_id]
        for task in run.tasks.values():
            if task.attempt_id is not None:
                world.attempts.pop(task.attempt_id, None)

    # ------------------------------------------------------------------ restore

    def restore(self, spec_by_id: dict[str, WorkflowSpec], workflows: list[WorkflowState],
                tasks: list[TaskState]) -> None:
        """Rebuild memory from persisted states (call on a fresh scheduler, before events).

        Active tasks keep their attempt and re-reserve its resources on its node id, even
        if that node is not known yet: nodes may be re-announced with ``NodeUp`` before or
        after this call. The caller is expected to report every restored active attempt
        (``AttemptLost`` when its worker is gone) right after. Timeouts resume from the
        persisted times (exec: the earliest ``started_at`` in the group; queue: each
        waiting request's ``scheduling_at``).

        Raises:
            KeyError: a workflow has no spec in ``spec_by_id``.
            ValueError: a workflow is already known or its tasks do not match its spec.
        """
        by_workflow: dict[str, list[TaskState]] = defaultdict(list)
        for task in tasks:
            by_workflow[task.workflow_id].append(task)
        for state in sorted(workflows, key=lambda w: (w.submitted_at, w.id)):
            self._restore_run(spec_by_id[state.id], state, by_workflow[state.id])
        self._world.queue.capacity_grew()

    def _restore_run(self, spec: WorkflowSpec, state: WorkflowState,
                     tasks: list[TaskState]) -> None:
        world = self._world
        if state.id in world.runs:
            raise ValueError(f"workflow '{state.id}' is already known")
        cap = state.max_retries if state.max_retries is not None else world.default_max_retries
        run = Run.build(spec, state.copy(), next(world.seq), cap)
        given = {t.name: t for t in tasks}
        if given.keys() != run.task_specs.keys():
            raise ValueError(f"workflow '{state.id}': persisted tasks do not match its spec")
        for name in run.task_specs:
            run.tasks[name] = task = given[name].copy()
            self._restore_task(run, task)
        for name in run.graph.topological_order():
            self._restore_group(run, name)
        world.runs[run.id] = run
        world.touch(run)

    def _restore_task(self, run: Run, task: TaskState) -> None:
        world = self._world
        if task.status is TaskStatus.RESCHEDULED:  # never persisted by us; be lenient
            task.status = TaskStatus.SCHEDULING
        if task.attempt_id is not None:
            world.attempts[task.attempt_id] = (run, task.name)
        if task.status.active:
            run.active += 1
            run.running += task.status is TaskStatus.RUNNING
            if task.attempt_id is not None and task.node_id is not None:
                asked = run.requests[task.name]
                world.ledger.reserve(task.attempt_id, task.node_id, asked.capacity,
                                     asked.platform)

    def _restore_group(self, run: Run, name: str) -> None:
        world, group = self._world, run.groups[name]
        members = [run.tasks[t.name] for t in group.spec.tasks]
        if all(t.status.terminal for t in members):
            group.closing, group.outcome = True, group_outcome(group.spec, run.tasks)
            run.open_groups -= 1
            return
        group.waiting_on = sum(run.groups[up].outcome is not TaskStatus.COMPLETED
                               for up in run.graph.upstream(name))
        started = [t.started_at for t in members if t.started_at is not None]
        if started:
            groups.start_exec_clock_at(world, run, group, min(started))
        waiting = [t for t in members if t.status is TaskStatus.SCHEDULING]
        if len(waiting) == len(members) and all(t.retry == 0 for t in members):
            since = min(t.scheduling_at or run.state.submitted_at for t in waiting)
            enqueue(world, run, group, tuple(t.name for t in waiting), gang=True, since=since)
            return
        for task in waiting:
            enqueue(world, run, group, (task.name,), gang=False,
                    since=task.scheduling_at or run.state.submitted_at)
