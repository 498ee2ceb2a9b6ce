"""Attempt reports: prepared, started, waiting, exited, start-failed, lost (and node loss).

This module owns fencing and the per-task outcome of an attempt (documented behaviour):

- Fencing: a report applies only when its attempt is the task's *current* attempt and the
  task is still active (INITIALIZING/RUNNING). Anything else changes no state, except that
  an attempt's *final* report (Exited, StartFailed, Lost) always releases what that attempt
  holds, exactly once — this is how a killed attempt gives its resources back.
- Exit actions: ``task.exit_action(code)``. COMPLETE needs an output reference (None means
  promotion failed: FAILED with ``ExitCode.OUTPUT_ERROR``). RESCHEDULE retries while the
  task's ``user_retries`` < the workflow's ``max_retries``, else FAILED "retry cap N reached".
  Exit code ``ExitCode.EXEC_TIMEOUT`` (a worker's cluster job ended by the cluster's own
  time limit: Slurm's TIMEOUT) is FAILED_EXEC_TIMEOUT, whatever the exit actions say.
- A lost attempt (worker gone, node down) is RESCHEDULED without using a user retry, up to
  ``max_lost_retries`` times, then FAILED_SERVER_ERROR with ``ExitCode.LOST`` and a message
  saying that ``osmo restart`` runs it again. An attempt lost to a restart of the server
  before its command started (INITIALIZING: placed or preparing) is rescheduled without
  counting: a crash loop of the server is not the task's fault.
- A retried task is queued alone; it is not held by its group's barrier.
- Waiting (``AttemptWaiting``): a node's cluster holds the placed attempt (a pod Pending, a
  Slurm job PENDING). A new reason becomes the task's message and ``node_wait``, and one
  transition of its unchanged status ("waiting: REASON"); the same reason again changes
  nothing; an empty one clears them, with one transition ("waits no more"). The task keeps
  its status and its place; leaving INITIALIZING/RUNNING clears them (``World.set_status``).
"""

from __future__ import annotations

from osmo.scheduler.groups import settle, start_exec_clock
from osmo.scheduler.placement import enqueue
from osmo.scheduler.runs import Run
from osmo.scheduler.state import TaskState
from osmo.scheduler.types import (
    AttemptExited,
    AttemptLost,
    AttemptPrepared,
    AttemptStarted,
    AttemptStartFailed,
    AttemptWaiting,
    wait_reason,
)
from osmo.scheduler.world import World
from osmo.spec.model import ExitAction
from osmo.status import ExitCode, TaskStatus

__all__ = ["Report", "lose", "on_report"]

Report = (AttemptPrepared | AttemptStarted | AttemptExited | AttemptStartFailed | AttemptLost
          | AttemptWaiting)
_FINAL = (AttemptExited, AttemptStartFailed, AttemptLost)


def on_report(world: World, report: Report) -> None:
    """Apply one attempt report (see the module docstring for fencing)."""
    aid = report.attempt_id
    if isinstance(report, _FINAL) and world.ledger.release(aid):
        world.queue.capacity_grew()
    found = world.attempts.get(aid)
    if found is None:
        return
    run, name = found
    task = run.tasks[name]
    if task.attempt_id != aid or not task.status.active:
        return
    if isinstance(report, AttemptPrepared):
        _prepared(world, run, task)
    elif isinstance(report, AttemptStarted):
        _started(world, run, task)
    elif isinstance(report, AttemptWaiting):
        _waiting(world, run, task, wait_reason(report.reason))
    elif isinstance(report, AttemptExited):
        _exited(world, run, task, report)
    elif isinstance(report, AttemptStartFailed):
        _finish(world, run, task, TaskStatus.FAILED_START_ERROR, ExitCode.START_ERROR,
                report.message)
    elif report.server_restart and task.status is TaskStatus.INITIALIZING:
        _retry(world, run, task, f"{report.message} before it started running (not counted "
                                 f"against the lost-attempt cap)")
    else:
        lose(world, run, task, report.message)


def _prepared(world: World, run: Run, task: TaskState) -> None:
    group = run.group_of(task)
    if task.status is not TaskStatus.INITIALIZING or task.name in group.prepared:
        return
    group.prepared.add(task.name)
    batch = group.batch
    if batch is not None and not batch.released and task.name in batch.members:
        world.release_barrier(run, group)
    # Otherwise no barrier holds it: it was placed with PrepareAttempt(run=True) and the
    # worker starts it by itself.


def _started(world: World, run: Run, task: TaskState) -> None:
    if task.status is not TaskStatus.INITIALIZING:
        return
    task.started_at = world.now
    world.set_status(run, task, TaskStatus.RUNNING,  # its pod may wait already
                     f"waiting: {task.node_wait}" if task.node_wait else "")
    start_exec_clock(world, run, run.group_of(task))


def _waiting(world: World, run: Run, task: TaskState, reason: str) -> None:
    if reason == task.node_wait:
        return
    task.node_wait, task.node_wait_since = reason, world.now if reason else None
    task.message = f"waiting: {reason}" if reason else ""
    world.note_task(run, task)
    world.log(run, task, task.status.name, task.message or "waits no more")


def _exited(world: World, run: Run, task: TaskState, report: AttemptExited) -> None:
    code = report.exit_code
    if code == ExitCode.EXEC_TIMEOUT:  # a cluster's own time limit ended it (Slurm TIMEOUT)
        _finish(world, run, task, TaskStatus.FAILED_EXEC_TIMEOUT, code,
                report.message or "the cluster's time limit for its job was reached")
        return
    action = run.task_specs[task.name].exit_action(code)
    if action is ExitAction.COMPLETE:
        if report.output is None:
            _finish(world, run, task, TaskStatus.FAILED, ExitCode.OUTPUT_ERROR,
                    report.message or f"exit code {code} but outputs could not be promoted")
            return
        task.output = report.output
        task.reused = task.reused or report.cached
        _finish(world, run, task, TaskStatus.COMPLETED, code, report.message)
    elif action is ExitAction.RESCHEDULE and task.user_retries < run.max_retries:
        task.user_retries += 1
        _retry(world, run, task, report.message or f"exit code {code}: RESCHEDULE")
    elif action is ExitAction.RESCHEDULE:
        _finish(world, run, task, TaskStatus.FAILED, code,
                f"exit code {code}: retry cap {run.max_retries} reached")
    else:
        _finish(world, run, task, TaskStatus.FAILED, code, report.message or f"exit code {code}")


def lose(world: World, run: Run, task: TaskState, message: str) -> None:
    """The current attempt of active ``task`` is lost: retry it, or fail past the cap."""
    if task.lost_retries < world.max_lost_retries:
        task.lost_retries += 1
        _retry(world, run, task, message)
    else:
        _finish(world, run, task, TaskStatus.FAILED_SERVER_ERROR, ExitCode.LOST,
                f"{message}; lost-attempt cap {world.max_lost_retries} reached; once the "
                f"cause is fixed, `osmo restart {run.id}` runs it again")


def _finish(world: World, run: Run, task: TaskState, status: TaskStatus, code: int,
            message: str) -> None:
    world.end_task(run, task, status, code, message)
    settle(world, run, task)


def _retry(world: World, run: Run, task: TaskState, reason: str) -> None:
    world.set_status(run, task, TaskStatus.RESCHEDULED, reason)
    if task.attempt_id is not None:
        world.attempts.pop(task.attempt_id, None)
    task.retry += 1
    task.attempt_id = task.node_id = task.exit_code = task.output = None
    task.started_at = task.ended_at = None
    task.scheduling_at = world.now
    world.set_status(run, task, TaskStatus.SCHEDULING, f"retry {task.retry} after: {reason}")
    enqueue(world, run, run.group_of(task), (task.name,), gang=False)
