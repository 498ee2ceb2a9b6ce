"""Group rules: opening, ending, downstream cascade, timeouts and cancel.

This module owns what happens to a group as a unit (documented behaviour):

- A group opens (all tasks SCHEDULING, one gang request) when every upstream group is
  COMPLETED. If an upstream group fails, every group downstream of it, transitively, ends
  with its tasks FAILED_UPSTREAM (exit code ``ExitCode.UPSTREAM_FAILED``).
- A group ends when its lead is terminal, or (``ignoreNonleadStatus: false``) when any task
  fails. Still-running or not-yet-started tasks are then stopped: COMPLETED with exit code
  ``ExitCode.STOPPED`` and "stopped: lead finished" if the lead completed; otherwise FAILED
  with ``ExitCode.STOPPED`` and a message naming the task that failed the group. Active
  ones get a KillAttempt.
- ``exec_timeout`` counts from the group's first RUNNING task (not reset by retries); when
  it expires every non-terminal task becomes FAILED_EXEC_TIMEOUT. ``queue_timeout`` counts
  from each request entering the queue (the group's gang, or one retried task) until it is
  placed; on expiry its tasks become FAILED_QUEUE_TIMEOUT and the group rules apply.
- No worker: a request whose workflow names no ``queue_timeout`` and whose pool has no node
  at all fails the same way once both it has waited and the pool has been empty for the
  scheduler's ``no_worker_timeout`` (``DEFAULT_NO_WORKER_TIMEOUT``); a node joining the pool
  in time stops that clock.
- Cancel ends every open group with its non-terminal tasks FAILED_CANCELED.
"""

from __future__ import annotations

from osmo.scheduler.placement import enqueue
from osmo.scheduler.queue import Deadline
from osmo.scheduler.runs import Group, Queued, Run, group_outcome
from osmo.scheduler.state import TaskState
from osmo.scheduler.world import World
from osmo.status import ExitCode, TaskStatus

__all__ = [
    "cancel",
    "close_group",
    "expire_exec",
    "expire_no_worker",
    "expire_queue",
    "open_group",
    "settle",
    "start_exec_clock",
    "start_exec_clock_at",
]


def open_group(world: World, run: Run, group: Group) -> None:
    """All upstream groups completed: queue the whole group for gang placement."""
    for spec in group.spec.tasks:
        task = run.tasks[spec.name]
        task.scheduling_at = world.now
        world.set_status(run, task, TaskStatus.SCHEDULING)
    enqueue(world, run, group, tuple(t.name for t in group.spec.tasks), gang=True)


def settle(world: World, run: Run, task: TaskState) -> None:
    """``task`` just became terminal: end its group if that decides the group."""
    group = run.group_of(task)
    if group.closing:
        return
    decisive = task.name == group.spec.lead.name or (
        task.status.failed and not group.spec.ignore_nonlead_status)
    if decisive:
        _stop_rest(world, run, group, task)
        close_group(world, run, group)


def _stop_rest(world: World, run: Run, group: Group, cause: TaskState) -> None:
    group.closing = True
    completed = cause.status is TaskStatus.COMPLETED
    message = ("stopped: lead finished" if completed
               else f"stopped: task '{cause.name}' {cause.status.name}")
    status = TaskStatus.COMPLETED if completed else TaskStatus.FAILED
    _end_open_tasks(world, run, group, status, ExitCode.STOPPED, message, kill=message)


def close_group(world: World, run: Run, group: Group) -> None:
    """Record the ended group's outcome and open or fail what waits for it."""
    group.closing = True
    group.outcome = group_outcome(group.spec, run.tasks)
    run.open_groups -= 1
    if group.outcome is TaskStatus.COMPLETED:
        for name in sorted(run.graph.children(group.name), key=run.graph.index):
            child = run.groups[name]
            child.waiting_on -= 1
            if child.waiting_on == 0 and not child.closing:
                open_group(world, run, child)
    else:
        _cascade(world, run, group)


def _cascade(world: World, run: Run, failed: Group) -> None:
    message = f"upstream group '{failed.name}' {failed.outcome.name if failed.outcome else ''}"
    for name in sorted(run.graph.downstream(failed.name), key=run.graph.index):
        group = run.groups[name]
        if group.closing:
            continue
        group.closing = True
        _end_open_tasks(world, run, group, TaskStatus.FAILED_UPSTREAM, ExitCode.UPSTREAM_FAILED,
                        message)
        group.outcome = TaskStatus.FAILED_UPSTREAM
        run.open_groups -= 1


def start_exec_clock(world: World, run: Run, group: Group) -> None:
    """A task of ``group`` is RUNNING: start the group's exec timeout once."""
    start_exec_clock_at(world, run, group, world.now)


def start_exec_clock_at(world: World, run: Run, group: Group, started: float) -> None:
    """Start ``group``'s exec timeout as of ``started``, unless it already runs."""
    timeout = run.spec.timeout.exec_timeout
    if timeout is None or group.exec_deadline is not None:
        return
    group.exec_deadline = started + timeout
    world.deadlines.push(Deadline(group.exec_deadline, run=run, group=group))


def expire_exec(world: World, run: Run, group: Group) -> None:
    """The group's exec timeout expired: fail every non-terminal task of it."""
    group.closing = True
    message = f"exec timeout ({run.spec.timeout.exec_timeout:g}s) exceeded"
    _end_open_tasks(world, run, group, TaskStatus.FAILED_EXEC_TIMEOUT, ExitCode.EXEC_TIMEOUT,
                    message, kill="exec timeout")
    close_group(world, run, group)


def expire_queue(world: World, request: Queued) -> None:
    """``request`` waited longer than the queue timeout: fail its tasks."""
    _time_out(world, request,
              f"queue timeout ({request.run.spec.timeout.queue_timeout:g}s) exceeded")


def _time_out(world: World, request: Queued, message: str) -> None:
    """Fail the tasks of waiting ``request`` as FAILED_QUEUE_TIMEOUT with ``message``."""
    run = request.run
    world.queue.done(request)
    tasks = [run.tasks[n] for n in request.tasks]
    for task in tasks:
        world.end_task(run, task, TaskStatus.FAILED_QUEUE_TIMEOUT, ExitCode.QUEUE_TIMEOUT, message)
    for task in tasks:
        settle(world, run, task)


def expire_no_worker(world: World, pool: str | None) -> None:
    """``pool``'s alarm is due: fail what has waited on it, empty, for the no-worker timeout.

    Re-arms the alarm for the next request to reach it, if any still waits.
    """
    world.alarms.discard(pool)
    empty = world.pool_empty_since(pool)
    limit = world.no_worker_timeout
    if empty is None or limit is None:
        return
    where = f"pool '{pool}'" if pool is not None else "the cluster"
    later: list[float] = []
    for request in world.queue.waiting_in(pool):
        if not request.valid() or request.run.spec.timeout.queue_timeout is not None:
            continue  # (ended by an earlier request's failure, or it has its own timeout)
        due = max(request.since, empty) + limit
        if due > world.now:
            later.append(due)
            continue
        _time_out(world, request, f"{where} has had no online worker for {limit:g}s (the "
                                  f"queue timeout of a pool with no worker; set "
                                  f"timeout.queue_timeout to wait longer)")
    if later:
        world.arm_alarm(pool, at=min(later))


def cancel(world: World, run: Run) -> None:
    """Fail every non-terminal task of ``run`` as canceled (no-op once terminal)."""
    if run.state.status.terminal:
        return
    for group in run.groups.values():
        if group.closing:
            continue
        group.closing = True
        _end_open_tasks(world, run, group, TaskStatus.FAILED_CANCELED, ExitCode.CANCELED,
                        "canceled", kill="canceled")
        group.outcome = group_outcome(group.spec, run.tasks)
        run.open_groups -= 1
    world.touch(run)


def _end_open_tasks(world: World, run: Run, group: Group, status: TaskStatus, code: int,
                    message: str, kill: str | None = None) -> None:
    """End every task of ``group`` that is not terminal yet with ``status``.

    With ``kill``, its active attempt is stopped first (the kill's reason).
    """
    for spec in group.spec.tasks:
        task = run.tasks[spec.name]
        if not task.status.terminal:
            world.end_task(run, task, status, code, message, kill=kill)
