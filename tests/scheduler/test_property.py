"""Property: random DAGs of groups driven by a random (but honest) worker world.

Every workflow ends terminal; no task is placed before its upstream groups completed; no
RunAttempt before the attempt reported prepared, none twice; every RunAttempt and KillAttempt
names the node its attempt was placed on; resources are never over-committed; duplicate
reports change nothing; everything is released at the end.
"""

from __future__ import annotations

from dataclasses import dataclass, field

from hypothesis import HealthCheck, event, given, settings
from hypothesis import strategies as st

from osmo.scheduler import (
    AttemptExited,
    AttemptLost,
    AttemptPrepared,
    AttemptStarted,
    AttemptStartFailed,
    CancelWorkflow,
    Command,
    Event,
    KillAttempt,
    Node,
    NodeDown,
    NodeUp,
    PrepareAttempt,
    RunAttempt,
    Scheduler,
    Tick,
    WorkflowSubmitted,
)
from osmo.spec.model import GroupSpec, ResourceSpec, WorkflowSpec

from .sim import group, node, task, workflow

RULES = [("RESCHEDULE", [(3, 3)])]


@st.composite
def workflows(draw: st.DrawFn) -> WorkflowSpec:
    n_groups = draw(st.integers(1, 6))
    groups: list[GroupSpec] = []
    names: list[list[str]] = []
    for g in range(n_groups):
        size = draw(st.integers(1, 3))
        ups = draw(st.lists(st.integers(0, g - 1), max_size=2, unique=True)) if g else []
        tasks = []
        for i in range(size):
            inputs = [draw(st.sampled_from(names[u])) for u in ups] if i == 0 or draw(
                st.booleans()) else []
            tasks.append(task(f"g{g}t{i}", *inputs, resource=f"c{draw(st.integers(1, 2))}",
                              lead=i == 0, rules=RULES if draw(st.booleans()) else ()))
        names.append([t.name for t in tasks])
        groups.append(group(f"g{g}", *tasks, barrier=draw(st.booleans()),
                            ignore=draw(st.booleans())))
    timeouts = draw(st.sampled_from([{}, {"exec_timeout": 50.0}, {"queue_timeout": 80.0}]))
    return workflow(*groups, resources={"c1": ResourceSpec(cpu=1), "c2": ResourceSpec(cpu=2)},
                    **timeouts)


@dataclass
class World:
    """The honest worker side: which attempts exist and in which phase."""

    s: Scheduler
    nodes: dict[str, Node]
    now: float = 0.0
    phase: dict[str, str] = field(default_factory=dict)  # aid → placed|prepared|run|started
    where: dict[str, str] = field(default_factory=dict)
    killed: set[str] = field(default_factory=set)
    finished: list[tuple[Event, bool]] = field(default_factory=list)
    ran: set[str] = field(default_factory=set)
    down: set[str] = field(default_factory=set)
    self_start: set[str] = field(default_factory=set)  # placed with PrepareAttempt(run=True)

    def send(self, event: Event) -> None:
        commands = self.s.handle(event, self.now)
        self.s.take_changes()
        self.check(commands)
        for command in commands:
            self.apply(command)

    def apply(self, command: Command) -> None:
        if isinstance(command, PrepareAttempt):
            self.phase[command.attempt_id] = "placed"
            self.where[command.attempt_id] = command.node_id
            if command.run:
                self.self_start.add(command.attempt_id)
        elif isinstance(command, RunAttempt):
            self.phase[command.attempt_id] = "run"
        elif isinstance(command, KillAttempt) and command.attempt_id in self.phase:
            self.killed.add(command.attempt_id)

    def check(self, commands: list[Command]) -> None:
        for n in self.nodes.values():
            assert self.s.used(n.id).fits_in(n.capacity), (n.id, self.s.used(n.id))
        for command in commands:
            if isinstance(command, RunAttempt | KillAttempt) and command.attempt_id in self.where:
                assert command.node_id == self.where[command.attempt_id], command  # its node
            if isinstance(command, PrepareAttempt):
                self.check_upstream(command)
            elif isinstance(command, RunAttempt):
                assert command.attempt_id not in self.self_start, command
                assert self.phase.get(command.attempt_id) == "prepared", command
                assert command.attempt_id not in self.ran
                self.ran.add(command.attempt_id)

    def check_upstream(self, command: PrepareAttempt) -> None:
        tasks = {t.name: t for t in self.s.tasks(command.workflow_id)}
        me = tasks[command.task]
        assert me.status.name == "INITIALIZING"
        spec_groups = {t.group for t in tasks.values()}
        for name in command.inputs:
            up_group = tasks[name].group
            members = [t for t in tasks.values() if t.group == up_group]
            assert all(t.status.terminal for t in members)
            assert up_group in spec_groups and up_group != me.group

    def final(self, aid: str, event: Event) -> None:
        self.phase.pop(aid, None)
        self.killed.discard(aid)
        self.finished.append((event, True))
        self.send(event)


def step(world: World, data: st.DataObject) -> None:
    choices: list[str] = ["tick"] + (["cancel"] if data.draw(st.integers(0, 30)) == 0 else [])
    choices += ["down"] if not world.down else ["up"]
    choices += ["dup"] if world.finished else []
    choices += ["attempt"] * 4 if world.phase else []
    action = data.draw(st.sampled_from(choices))
    if action == "tick":
        world.now += data.draw(st.sampled_from([1.0, 10.0, 60.0]))
        world.send(Tick())
    elif action == "cancel":
        world.send(CancelWorkflow("wf-1"))
    elif action == "down":
        node_id = data.draw(st.sampled_from(sorted(world.nodes)))
        world.down.add(node_id)
        for aid in [a for a, n in world.where.items() if n == node_id and a in world.phase]:
            world.phase.pop(aid)
            world.killed.discard(aid)
        world.send(NodeDown(node_id))
    elif action == "up":
        world.send(NodeUp(world.nodes[world.down.pop()]))
    elif action == "dup":
        event, _ = data.draw(st.sampled_from(world.finished))
        assert world.s.handle(event, world.now) == []
        assert not world.s.take_changes()
    else:
        aid = data.draw(st.sampled_from(sorted(world.phase)))
        act(world, aid, data.draw(st.integers(0, 9)))


def act(world: World, aid: str, roll: int) -> None:
    """One honest report for ``aid``; ``roll`` picks success (high) or trouble (low)."""
    phase = world.phase[aid]
    if aid in world.killed:
        world.final(aid, AttemptExited(aid, 137))
    elif roll == 0:
        world.final(aid, AttemptLost(aid))
    elif phase == "placed":
        if roll == 1:
            world.final(aid, AttemptStartFailed(aid, "boom"))
        else:
            world.phase[aid] = "prepared"
            world.send(AttemptPrepared(aid))
            if aid in world.self_start and world.phase.get(aid) == "prepared":
                world.phase[aid] = "run"  # placed with run=True: the worker starts it
    elif phase == "run":
        world.phase[aid] = "started"
        world.send(AttemptStarted(aid))
    elif phase == "started":
        code = {1: 1, 2: 3, 3: 3}.get(roll, 0)
        world.final(aid, AttemptExited(aid, code, f"out:{aid}"))


def drain(world: World) -> None:
    """Let everything succeed until the workflow is terminal and all reports are in."""
    while world.down:
        world.send(NodeUp(world.nodes[world.down.pop()]))
    for _ in range(10_000):
        ready = sorted(a for a, p in world.phase.items() if p != "prepared" or a in world.killed)
        if ready:
            act(world, ready[0], 9)
            continue
        if world.s.workflow("wf-1").status.terminal and not world.phase:
            return
        deadline = world.s.next_deadline()
        assert deadline is not None, ("stuck", world.phase, world.s.tasks("wf-1"))
        world.now = max(world.now, deadline)
        world.send(Tick())
    raise AssertionError("did not finish")


@settings(max_examples=300, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(spec=workflows(), n_nodes=st.integers(1, 3), data=st.data())
def test_random_workflows_end_terminal_without_breaking_invariants(
        spec: WorkflowSpec, n_nodes: int, data: st.DataObject) -> None:
    nodes = {f"n{i}": node(f"n{i}", cpu=3 + i % 2) for i in range(n_nodes)}
    world = World(Scheduler(max_lost_retries=2), nodes)
    for n in nodes.values():
        world.send(NodeUp(n))
    if world.s.check_fit(spec, "local"):
        event("refused")
        return  # the server would refuse it
    world.send(WorkflowSubmitted("wf-1", spec, max_retries=1))
    for _ in range(data.draw(st.integers(0, 120))):
        step(world, data)
    drain(world)
    tasks = world.s.tasks("wf-1")
    assert all(t.status.terminal for t in tasks), tasks
    assert all(world.s.used(n).cpu == 0 for n in nodes)
    event(world.s.workflow("wf-1").status.name)
    completed = world.s.workflow("wf-1").status.name == "COMPLETED"
    leads_ok = all(t.status.name == "COMPLETED" for t in tasks if t.name.endswith("t0"))
    assert completed == leads_ok
