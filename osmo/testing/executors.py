"""The executor conformance kit: :func:`check_executor`.

For executors (``osmo.executor.Executor``: the local pool, the remote-worker hub, and the
Kubernetes or Slurm executors to come): ``check_executor(executor, events, node_id)`` drives
a started executor through the contract the engine relies on (see :func:`check_executor`);
it needs ``sh``, ``true`` and ``sleep`` where the executor runs its tasks.
"""

from __future__ import annotations

import queue
import time
from collections import defaultdict
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING, Any, Protocol

if TYPE_CHECKING:
    from osmo.executor import Executor
    from osmo.spec.model import WorkflowSpec

__all__ = ["EventSource", "check_executor"]


class EventSource(Protocol):
    """Where a checked executor's events arrive (a ``queue.Queue`` its ``emit`` puts into)."""

    def get(self, block: bool = ..., timeout: float | None = ...) -> Any:
        """The next event; raises ``queue.Empty`` after ``timeout`` seconds."""


_TASKS = {  # task name → (command, placed with run=True)
    "ok": (["sh", "-c", "echo hi > {{output}}/hello.txt"], True),
    "held": (["sh", "-c", "echo held > {{output}}/held.txt"], False),
    "exit3": (["sh", "-c", "exit 3"], True),
    "missing": (["osmo-conformance-no-such-command"], True),
    "sleeper": (["sleep", "600"], True),
    "early": (["true"], False),
    "sentinel": (["true"], True),
}


class _Watch:
    """The events of one workflow's attempts, filed by attempt id as they arrive."""

    def __init__(self, source: EventSource, workflow_id: str, timeout: float) -> None:
        self._source, self._prefix, self._timeout = source, f"{workflow_id}:", timeout
        self.of: dict[str, list[Any]] = defaultdict(list)

    def until(self, attempt_id: str, kinds: tuple[type, ...]) -> Any:
        """Wait for an event of one of ``kinds`` about ``attempt_id``; None after timeout."""
        deadline = time.monotonic() + self._timeout
        while True:
            found = next((e for e in self.of[attempt_id] if isinstance(e, kinds)), None)
            if found is not None:
                return found
            left = deadline - time.monotonic()
            if left <= 0:
                return None
            try:
                event = self._source.get(timeout=left)
            except queue.Empty:
                return None
            aid = getattr(event, "attempt_id", None)
            if isinstance(aid, str) and aid.startswith(self._prefix):
                self.of[aid].append(event)


def check_executor(executor: Executor, events: EventSource, node_id: str, *,
                   admit: Callable[[str, WorkflowSpec], None] = lambda _wf, _spec: None,
                   workflow_id: str = "conformance-1", timeout: float = 60.0) -> None:
    """Check that a started ``executor`` keeps the executor contract on ``node_id``.

    It owns ``node_id``; a placement with ``run`` reports prepared, started, then one exit
    with the exit code (0: an output folder holding what the task wrote there); one without
    ``run`` waits for ``run``; a command that cannot start ends in ``AttemptStartFailed``;
    a kill ends a running or a prepared attempt with one failed exit; ``run`` of an attempt
    never prepared fails its start; a kill of an unknown attempt reports nothing; and every
    attempt gets exactly one final report, nothing after it.

    Args:
        executor: the executor under test, ready to run attempts on ``node_id``.
        node_id: the node it runs attempts on.
        events: where the events it emits arrive.
        admit: called with the workflow's id and spec before any of its attempts is
            prepared (an executor that reads specs from the state store needs it there).
        workflow_id: the id its attempts carry (``<workflow_id>:<task>:0``).
        timeout: seconds to wait for each expected event.

    Raises:
        AssertionError: listing every broken promise.
    """
    check = _ExecutorCheck(executor, events, node_id, workflow_id, timeout)
    admit(workflow_id, check.spec)
    check.drive()
    check.verify()
    if check.problems:
        raise AssertionError(f"{executor!r} breaks the executor contract:\n  - "
                             + "\n  - ".join(check.problems))


class _ExecutorCheck:
    """The steps of :func:`check_executor` and the problems they found."""

    def __init__(self, executor: Executor, events: EventSource, node_id: str,
                 workflow_id: str, timeout: float) -> None:
        from osmo.spec.builder import Workflow

        self.executor, self.node_id, self.workflow_id = executor, node_id, workflow_id
        self.timeout = timeout
        self.watch = _Watch(events, workflow_id, timeout)
        flow = Workflow("conformance")
        for name, (command, _run) in _TASKS.items():
            flow.task(name, command)
        self.spec = flow.build()
        self.problems = [] if executor.owns(node_id) else [f"it does not own {node_id!r}"]

    def aid(self, name: str) -> str:
        return f"{self.workflow_id}:{name}:0"

    def place(self, name: str) -> None:
        from osmo.scheduler.types import PrepareAttempt

        self.executor.prepare(PrepareAttempt(self.aid(name), self.workflow_id, name, 0,
                                             self.node_id, {}, {}, run=_TASKS[name][1]),
                              self.spec.task(name))

    def wait(self, name: str, kinds: tuple[type, ...], what: str) -> Any:
        found = self.watch.until(self.aid(name), kinds)
        if found is None:
            seen = [type(e).__name__ for e in self.watch.of[self.aid(name)]]
            self.problems.append(f"{name}: no {what} within {self.timeout:g}s (saw {seen})")
        return found

    def drive(self) -> None:
        """Place every task, run the held one, kill a running and a prepared one.

        Also run one never prepared, and kill one unknown.
        """
        from osmo.scheduler.types import AttemptPrepared, AttemptStarted, KillAttempt, RunAttempt

        for name in ("ok", "held", "exit3", "missing", "sleeper", "early"):
            self.place(name)
        self.executor.run(RunAttempt(self.aid("ghost"), self.node_id))
        self.executor.kill(KillAttempt(self.aid("unknown"), self.node_id, "conformance"))
        if self.wait("held", (AttemptPrepared,), "AttemptPrepared") is not None:
            self.executor.run(RunAttempt(self.aid("held"), self.node_id))
        if self.wait("sleeper", (AttemptStarted,), "AttemptStarted") is not None:
            self.executor.kill(KillAttempt(self.aid("sleeper"), self.node_id, "conformance"))
        if self.wait("early", (AttemptPrepared,), "AttemptPrepared") is not None:
            self.executor.kill(KillAttempt(self.aid("early"), self.node_id, "conformance"))

    def verify(self) -> None:
        """How each attempt ended; one final report each, nothing for the unknown one."""
        from osmo.scheduler.types import AttemptExited, AttemptStartFailed

        final = (AttemptExited, AttemptStartFailed)
        for name in ("ok", "held"):
            exited = self.wait(name, final, "final report")
            if exited is not None:
                self.problems += _success_problems(name, exited, self.watch.of[self.aid(name)])
        for name, expect in (("exit3", "exit code 3"), ("missing", "AttemptStartFailed"),
                             ("sleeper", "a failed exit"), ("early", "a failed exit"),
                             ("ghost", "AttemptStartFailed")):
            ended = self.wait(name, final, "final report")
            if ended is not None and not _ended_as(ended, expect):
                self.problems.append(f"{name}: expected {expect}, got {ended!r}")
        self.place("sentinel")  # its end comes after any late report of the others
        self.wait("sentinel", final, "final report")
        for attempt, seen in sorted(self.watch.of.items()):
            count = sum(isinstance(e, final) for e in seen)
            if attempt != self.aid("unknown") and (count != 1 or not isinstance(seen[-1],
                                                                               final)):
                self.problems.append(f"{attempt}: {count} final reports, events "
                                     f"{[type(e).__name__ for e in seen]}")
        if self.watch.of.get(self.aid("unknown")):
            self.problems.append(f"a kill of an unknown attempt reported "
                                 f"{self.watch.of[self.aid('unknown')]}")


def _success_problems(name: str, exited: Any, seen: list[Any]) -> list[str]:
    from osmo.scheduler.types import AttemptExited, AttemptPrepared, AttemptStarted

    kinds = [type(e) for e in seen]
    problems = [] if kinds[:3] == [AttemptPrepared, AttemptStarted, AttemptExited] else [
        f"{name}: events {[k.__name__ for k in kinds]}, expected prepared, started, exited"]
    if not isinstance(exited, AttemptExited) or exited.exit_code != 0 or not exited.output:
        return [*problems, f"{name}: expected a successful exit with an output, got {exited!r}"]
    written = Path(exited.output) / f"{'hello' if name == 'ok' else 'held'}.txt"
    if not written.is_file():
        problems.append(f"{name}: its output {exited.output} lacks {written.name}")
    return problems


def _ended_as(event: Any, expect: str) -> bool:
    from osmo.scheduler.types import AttemptExited, AttemptStartFailed

    if expect == "AttemptStartFailed":
        return isinstance(event, AttemptStartFailed)
    if not isinstance(event, AttemptExited) or event.output is not None:
        return False
    return event.exit_code == 3 if expect == "exit code 3" else event.exit_code != 0
