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

A request that names no ``queue_timeout`` and does not fit because its pool has no node at
all arms the pool's alarm (``World.arm_alarm``): the no-worker timeout then fails what still
waits there (``groups.expire_no_worker``).
"""

from __future__ import annotations

from osmo.scheduler.queue import Deadline
from osmo.scheduler.runs import Batch, Group, Queued, Run
from osmo.scheduler.types import PrepareAttempt, attempt_id, priority_key
from osmo.scheduler.world import World
from osmo.status import TaskStatus

__all__ = ["enqueue", "place_pending", "placement_of"]


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
    start = world.now if since is None else since
    key = priority_key(run.state.priority, run.state.submitted_at)
    request = Queued(run, group, names, tuple(tasks[n].retry for n in names),
                     (key, run.seq, group.index, next(world.seq)), shape, gang, start)
    world.queue.push(request)
    timeout = run.spec.timeout.queue_timeout
    if timeout is not None:
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
            if run.spec.timeout.queue_timeout is None:
                world.arm_alarm(run.state.pool)
            continue
        queue.done(request)
        _commit(world, request, plan)


def _commit(world: World, request: Queued, plan: dict[str, str]) -> None:
    run, group = request.run, request.group
    for name in request.tasks:
        task = run.tasks[name]
        aid = attempt_id(run.id, name, task.retry)
        task.attempt_id, task.node_id = aid, plan[name]
        request_of = run.requests[name]
        world.ledger.reserve(aid, plan[name], request_of.capacity, request_of.platform)
        world.attempts[aid] = (run, name)
        world.set_status(run, task, TaskStatus.INITIALIZING, "")
    held = request.gang and group.spec.barrier and len(request.tasks) > 1
    if held:
        group.batch = Batch(list(request.tasks))
    hosts = _hosts(world, run, group)
    for name in request.tasks:
        world.out.append(_command(run, name, hosts, start=not held))


def placement_of(world: World, run: Run, name: str) -> PrepareAttempt:
    """The ``PrepareAttempt`` that placed the current attempt of active task ``name``.

    Derived again from the state (inputs and hosts are what they were at placement: upstream
    outputs and group placements do not change while the attempt is active), for a restarted
    server that must know an attempt it did not place. ``run`` is False: nothing is started.
    """
    return _command(run, name, _hosts(world, run, run.group_of(run.tasks[name])), start=False)


def _command(run: Run, name: str, hosts: dict[str, str], *, start: bool) -> PrepareAttempt:
    task = run.tasks[name]
    assert task.attempt_id is not None and task.node_id is not None
    return PrepareAttempt(
        attempt_id=task.attempt_id, workflow_id=run.id, task=name, retry=task.retry,
        node_id=task.node_id, inputs=_inputs(run, name), hosts=hosts, run=start)


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
