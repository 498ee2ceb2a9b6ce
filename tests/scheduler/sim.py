"""Test helpers: spec builders and a simulated shell around one Scheduler (fake clock)."""

from __future__ import annotations

from collections.abc import Iterable, Sequence

from osmo.scheduler import (
    AttemptExited,
    AttemptLost,
    AttemptPrepared,
    AttemptStarted,
    AttemptStartFailed,
    CancelWorkflow,
    Capacity,
    Changes,
    Command,
    Event,
    KillAttempt,
    Node,
    NodeDown,
    NodeUp,
    PrepareAttempt,
    RunAttempt,
    Scheduler,
    TaskState,
    Tick,
    Transition,
    WorkflowState,
    WorkflowSubmitted,
)
from osmo.spec.model import (
    ExitAction,
    ExitRule,
    GroupSpec,
    InputSpec,
    ResourceSpec,
    TaskSpec,
    Timeouts,
    WorkflowSpec,
)

GiB = 1 << 30


def task(name: str, *inputs: str, resource: str = "default", lead: bool = False,
         rules: Iterable[tuple[str, Sequence[tuple[int, int]]]] = ()) -> TaskSpec:
    """A task taking ``inputs`` (upstream task names) with optional exit rules."""
    return TaskSpec(
        name=name, command=("true",), inputs=tuple(InputSpec(task=i) for i in inputs),
        resource=resource, lead=lead,
        exit_actions=tuple(ExitRule(ExitAction[a], tuple(r)) for a, r in rules))


def group(name: str, *tasks: TaskSpec, barrier: bool = True, ignore: bool = True) -> GroupSpec:
    """A group; the first task is the lead unless one is marked."""
    if len(tasks) > 1 and not any(t.lead for t in tasks):
        first = tasks[0]
        tasks = (TaskSpec(**{**first.__dict__, "lead": True}), *tasks[1:])
    return GroupSpec(name=name, tasks=tasks, barrier=barrier, ignore_nonlead_status=ignore)


def workflow(*items: TaskSpec | GroupSpec, resources: dict[str, ResourceSpec] | None = None,
             exec_timeout: float | None = None, queue_timeout: float | None = None,
             name: str = "wf") -> WorkflowSpec:
    """A workflow of bare tasks (each its own group) and/or groups."""
    groups = tuple(i if isinstance(i, GroupSpec) else GroupSpec(i.name, (i,)) for i in items)
    return WorkflowSpec(name=name, groups=groups,
                        bare_tasks=all(isinstance(i, TaskSpec) for i in items),
                        resources=resources or {},
                        timeout=Timeouts(exec_timeout=exec_timeout, queue_timeout=queue_timeout))


def node(node_id: str = "n1", cpu: float = 4, gpu: int = 0, memory: int = 16 * GiB,
         pool: str = "local", platform: str | None = None) -> Node:
    """A node with an address derived from its id."""
    return Node(node_id, pool, Capacity(cpu, gpu, memory, 100 * GiB), platform,
                address=f"addr-{node_id}")


class Sim:
    """Drives a Scheduler like the server would, recording every command and change."""

    def __init__(self, *nodes: Node, **options: int) -> None:
        self.s = Scheduler(**options)
        self.now = 0.0
        self.commands: list[Command] = []
        self.self_started: set[str] = set()
        self.transitions: list[Transition] = []
        self.last: list[Command] = []
        self.stored_tasks: dict[tuple[str, str], dict[str, object]] = {}  # a fake store
        self.stored_workflows: dict[str, dict[str, object]] = {}
        for n in nodes or (node(),):
            self.send(NodeUp(n))

    def send(self, event: Event, at: float | None = None) -> list[Command]:
        """Handle ``event`` (at time ``at``, else the current time)."""
        if at is not None:
            self.now = at
        self.last = self.s.handle(event, self.now)
        self.commands.extend(self.last)
        self.changes: Changes = self.s.take_changes()
        self.transitions.extend(self.changes.transitions)
        for t in self.changes.tasks:
            assert isinstance(t, TaskState)
            self.stored_tasks[(t.workflow_id, t.name)] = t.to_dict()
        for w in self.changes.workflows:
            assert isinstance(w, WorkflowState)
            self.stored_workflows[w.id] = w.to_dict()
        return self.last

    def restored(self, specs: dict[str, WorkflowSpec], *nodes: Node, **options: int) -> Sim:
        """A new Sim whose scheduler restored this one's stored state (like a restart)."""
        sim = Sim.__new__(Sim)
        sim.s = Scheduler(**options)
        sim.now, sim.commands, sim.transitions, sim.last = self.now, [], [], []
        sim.self_started = set()
        sim.stored_tasks, sim.stored_workflows = dict(self.stored_tasks), dict(
            self.stored_workflows)
        sim.s.restore(specs, [WorkflowState.from_dict(w) for w in self.stored_workflows.values()],
                      [TaskState.from_dict(t) for t in self.stored_tasks.values()])
        for n in nodes:
            sim.send(NodeUp(n))
        return sim

    def submit(self, spec: WorkflowSpec, wid: str = "wf-1", **kw: object) -> list[Command]:
        return self.send(WorkflowSubmitted(wid, spec, **kw))  # type: ignore[arg-type]

    # -- reading
    def task(self, name: str, wid: str = "wf-1"):
        return next(t for t in self.s.tasks(wid) if t.name == name)

    def status(self, name: str, wid: str = "wf-1") -> str:
        return self.task(name, wid).status.name

    def statuses(self, wid: str = "wf-1") -> dict[str, str]:
        return {t.name: t.status.name for t in self.s.tasks(wid)}

    def wf(self, wid: str = "wf-1") -> str:
        return self.s.workflow(wid).status.name

    def aid(self, name: str, wid: str = "wf-1") -> str:
        found = self.task(name, wid).attempt_id
        assert found is not None, f"{name} has no attempt"
        return found

    def of(self, kind: type, commands: Sequence[Command] | None = None) -> list[str]:
        """Task names (attempt ids' middle part) of commands of ``kind``."""
        found = []
        for c in self.last if commands is None else commands:
            if isinstance(c, kind):
                assert isinstance(c, (PrepareAttempt, RunAttempt, KillAttempt))
                found.append(c.attempt_id.split(":")[1])
        return found

    # -- acting as the worker
    def prepare(self, name: str, wid: str = "wf-1") -> list[Command]:
        """Report prepared. An attempt placed with ``run=True`` starts by itself then; the
        returned commands show that as a ``RunAttempt`` so tables read the same either way."""
        aid = self.aid(name, wid)
        placed = [c for c in self.commands if isinstance(c, PrepareAttempt) and c.attempt_id == aid]
        out = self.send(AttemptPrepared(aid))
        if (placed and placed[-1].run and aid not in self.self_started
                and self.task(name, wid).status.name == "INITIALIZING"):
            self.self_started.add(aid)
            assert not [c for c in out if isinstance(c, RunAttempt) and c.attempt_id == aid]
            out = [*out, RunAttempt(aid, placed[-1].node_id)]
            self.last = out
        return out

    def start(self, name: str, wid: str = "wf-1") -> list[Command]:
        return self.send(AttemptStarted(self.aid(name, wid)))

    def exit(self, name: str, code: int = 0, wid: str = "wf-1",
             output: str | None = "auto") -> list[Command]:
        aid = self.aid(name, wid)
        ref = f"out:{name}" if output == "auto" else output
        return self.send(AttemptExited(aid, code, ref))

    def start_failed(self, name: str, wid: str = "wf-1") -> list[Command]:
        return self.send(AttemptStartFailed(self.aid(name, wid), "boom"))

    def lost(self, name: str, wid: str = "wf-1") -> list[Command]:
        return self.send(AttemptLost(self.aid(name, wid)))

    def run(self, name: str, code: int = 0, wid: str = "wf-1") -> list[Command]:
        """Prepare, start and exit ``name`` (its attempt must be placed)."""
        self.prepare(name, wid)
        self.start(name, wid)
        return self.exit(name, code, wid)


def play(sim: Sim, script: str, wid: str = "wf-1") -> list[Command]:
    """Run a compact script; returns every command emitted while running it.

    Steps, separated by ``;``: ``run a`` / ``run a=3`` (prepare+start+exit code),
    ``prepare a``, ``start a``, ``exit a=3``, ``lost a``, ``startfail a``, ``cancel``,
    ``tick 12.5`` (advance the clock to 12.5 and tick), ``down n1``.
    """
    emitted: list[Command] = []
    for step in filter(None, (s.strip() for s in script.split(";"))):
        verb, _, arg = step.partition(" ")
        name, _, code = arg.partition("=")
        if verb == "run":
            sim.prepare(name, wid)
            emitted += sim.last
            sim.start(name, wid)
            emitted += sim.last
            sim.exit(name, int(code or 0), wid)
        elif verb == "exit":
            sim.exit(name, int(code or 0), wid)
        elif verb in ("prepare", "start", "lost"):
            getattr(sim, verb)(name, wid)
        elif verb == "startfail":
            sim.start_failed(name, wid)
        elif verb == "cancel":
            sim.send(CancelWorkflow(wid))
        elif verb == "tick":
            sim.send(Tick(), at=float(arg))
        elif verb == "down":
            sim.send(NodeDown(arg))
        else:
            raise ValueError(f"unknown step {step!r}")
        emitted += sim.last
    return emitted


def parse_statuses(text: str) -> dict[str, str]:
    """``"a=COMPLETED b=FAILED"`` → dict."""
    return dict(item.split("=") for item in text.split())
