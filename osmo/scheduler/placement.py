"""Gang placement: turn queued requests into reserved attempts and PrepareAttempt commands.

This module owns the placement pass. Requests are tried by priority with ageing
(``types.priority_key``: HIGH before NORMAL before LOW, unless the lower one has waited a
level's ``PRIORITY_AGEING`` longer), then in FIFO order (workflow submit order, then group
order, then enqueue order); a request that does not fit is skipped, so it does not block
smaller requests behind it, whatever their priority. That keeps the cluster busy but can
starve a big group while small ones keep arriving: a known trade-off, bounded by
``queue_timeout``.

Requests of a *shape* (pool and per-task requests) that failed are not tried again until
capacity grows (see ``queue.PlacementQueue``), so a pass costs O(shapes) plus O(nodes) per
placement attempt, not O(queue).
"""

from __future__ import annotations

from osmo.scheduler.queue import Deadline
from osmo.scheduler.runs import Batch, Group, Queued, Run
from osmo.scheduler.types import PrepareAttempt, attempt_id, priority_key
from osmo.scheduler.world import World
from osmo.status import TaskStatus

__all__ = ["enqueue", "place_pending"]


def enqueue(world: World, run: Run, group: Group, names: tuple[str, ...], *, gang: bool,
            since: float | None = None) -> None:
    """Queue ``names`` of ``group`` (already SCHEDULING) for placement all at once.

    Args:
        world: the engine.
        run: the workflow.
        group: the tasks' group.
        names: tasks to place together, in group order.
        gang: True for the group's first placement (barrier applies); False for a retry.
        since: when the request started waiting (defaults to now), for ``queue_timeout``.
    """
    tasks = run.tasks
    shape = (run.state.pool, tuple(run.requests[n] for n in names))
    key = priority_key(run.state.priority, run.state.submitted_at)
    request = Queued(run, group, names, tuple(tasks[n].retry for n in names),
                     (key, run.seq, group.index, next(world.seq)), shape, gang)
    world.queue.push(request)
    timeout = run.spec.timeout.queue_timeout
    if timeout is not None:
        start = world.now if since is None else since
        world.deadlines.push(Deadline(start + timeout, request=request))


def place_pending(world: World) -> None:
    """Place every queued request that fits now, in FIFO order."""
    queue = world.queue
    for request in queue.pending():
        if not request.valid():
            queue.done(request)
            continue
        run = request.run
        plan = world.ledger.place([(n, run.requests[n]) for n in request.tasks], run.state.pool)
        if plan is None:
            queue.block(request.shape)
            continue
        queue.done(request)
        _commit(world, request, plan)


def _commit(world: World, request: Queued, plan: dict[str, str]) -> None:
    run, group = request.run, request.group
    for name in request.tasks:
        task = run.tasks[name]
        aid = attempt_id(run.id, name, task.retry)
        task.attempt_id, task.node_id = aid, plan[name]
        world.ledger.reserve(aid, plan[name], run.requests[name].capacity)
        world.attempts[aid] = (run, name)
        world.set_status(run, task, TaskStatus.INITIALIZING, "")
    held = request.gang and group.spec.barrier and len(request.tasks) > 1
    if held:
        group.batch = Batch(list(request.tasks))
    hosts = _hosts(world, run, group)
    for name in request.tasks:
        task = run.tasks[name]
        assert task.attempt_id is not None and task.node_id is not None
        world.out.append(PrepareAttempt(
            attempt_id=task.attempt_id, workflow_id=run.id, task=name, retry=task.retry,
            node_id=task.node_id, inputs=_inputs(run, name), hosts=hosts, run=not held))


def _hosts(world: World, run: Run, group: Group) -> dict[str, str]:
    hosts: dict[str, str] = {}
    for spec in group.spec.tasks:
        node_id = run.tasks[spec.name].node_id
        node = world.ledger.node(node_id) if node_id is not None else None
        if node is not None:
            hosts[spec.name] = node.address
    return hosts


def _inputs(run: Run, name: str) -> dict[str, str]:
    """Upstream task → output ref. A stopped non-lead upstream has no output: left out."""
    found: dict[str, str] = {}
    for upstream in run.task_specs[name].upstream_tasks():
        output = run.tasks[upstream].output
        if output is not None:
            found[upstream] = output
    return found
