"""The engine: the one thread that feeds events to the scheduler and carries out its commands.

Owns the loop ``events → Scheduler.handle → commit to the store → execute commands``. Every
batch of state changes is committed in one transaction *before* any command of that batch is
executed, so a server killed at any instant restarts into a consistent state. Events from
workers and calls from API threads arrive on one queue; the loop blocks on it until an event
arrives or the scheduler's next deadline (a timeout) is due — no polling.

Fault isolation: no exception stops the loop. When applying a batch raises — in the
scheduler, while building lineage, or in the commit itself — nothing of the batch was
committed, so the engine drops it from memory by rebuilding the scheduler from the store
(``osmo.server.recovery``) and applies the batch's events again one at a time. The event that
raises again is the culprit: an attempt's report becomes a failure of that attempt (FAILED
with the message, exit code 3005 for an exit; FAILED_START_ERROR otherwise; a still-running
attempt is killed), an API call gets the error, anything else is logged and dropped; every
other event is applied as usual. Attempts that were still starting when the scheduler was
rebuilt are reported lost and started again (a group barrier's progress is not kept in the
store). Only when even a failure cannot be committed, or the store cannot be read, does the
engine stop: it then calls ``on_fatal`` (the server exits non-zero, so a supervisor sees it)
and every waiting API call gets an error. A hard crash while reports are applied is covered
by the quarantine file (``osmo.server.recovery.InFlight``).

It must not parse specs, talk zenoh or format output; those belong to other layers.
"""

from __future__ import annotations

import logging
import queue
import threading
import time
from collections.abc import Callable
from concurrent.futures import Future
from dataclasses import dataclass, field
from typing import Any, Protocol

from osmo.scheduler import Scheduler
from osmo.scheduler.types import (
    AttemptExited,
    AttemptLost,
    AttemptStarted,
    AttemptStartFailed,
    Changes,
    Command,
    Event,
    KillAttempt,
    PrepareAttempt,
    RunAttempt,
    Tick,
)
from osmo.spec.model import TaskSpec, WorkflowSpec
from osmo.artifacts import Manifest
from osmo.errors import InfrastructureError
from osmo.server.datasets import Datasets
from osmo.server.placing import Placements
from osmo.server.isolation import STOP, Call, FaultIsolation, guard, reason
from osmo.server.provenance import Provenance
from osmo.server.recovery import InFlight, Restored, attempt_row
from osmo.status import TaskStatus
from osmo.store.sqlite import AttemptRow, DatasetRow, LineageRow, Store

__all__ = ["Engine", "Executor"]

log = logging.getLogger("osmo.server")



class Executor(Protocol):
    """What the engine needs from a pool of workers (the local pool, later remote ones)."""

    def prepare(self, cmd: PrepareAttempt, task: TaskSpec, *,
                max_output_bytes: int | None = None) -> None: ...
    def run(self, cmd: RunAttempt) -> None: ...
    def kill(self, cmd: KillAttempt) -> None: ...


@dataclass
class _Batch:
    """What one loop iteration accumulates before committing."""

    commands: list[Command] = field(default_factory=list)
    new_workflows: list[tuple[str, str, int, float, dict[str, Any], dict[str, Any]]] = field(
        default_factory=list)
    attempts: list[AttemptRow] = field(default_factory=list)
    lineage: list[LineageRow] = field(default_factory=list)
    datasets: list[DatasetRow] = field(default_factory=list)
    tags: list[tuple[str, str, int]] = field(default_factory=list)
    replies: list[tuple[Future[Any], Any]] = field(default_factory=list)
    ended: list[str] = field(default_factory=list)  # attempts whose final report is applied


_Call = Call
_STOP = STOP


class Engine(FaultIsolation):
    """Runs the scheduler on its own thread.

    Args:
        store: the state store (the engine is its only writer).
        scheduler: the scheduler, already restored from the store if recovering.
        executor: the pool that runs attempts.
        specs: workflow id → spec for every workflow the scheduler holds.
        on_changed: called with the ids of workflows whose state changed (after commit).
        on_finished: called with the id of each workflow that ended (after commit).
        datasets: resolves dataset inputs and records dataset outputs.
        no_cache: ids of workflows submitted with ``--no-cache`` (kept current here).
        restore: rebuilds a scheduler from the store (``osmo.server.recovery.restore``);
            without it a batch that raises stops the engine.
        inflight: the quarantine file (``osmo.server.recovery.InFlight``), if any.
        on_fatal: called (on the engine thread) when the engine cannot go on.
        clock: time source (injectable for tests).
    """

    def __init__(self, *, store: Store, scheduler: Scheduler, executor: Executor,
                 specs: dict[str, WorkflowSpec], on_changed: Callable[[set[str]], None],
                 home: Any, on_finished: Callable[[str], None] = lambda _wf: None,
                 datasets: Datasets | None = None, no_cache: set[str] | None = None,
                 restore: Callable[[], Restored] | None = None,
                 inflight: InFlight | None = None,
                 on_fatal: Callable[[BaseException], None] = lambda _exc: None,
                 clock: Callable[[], float] = time.time) -> None:
        self.store = store
        self.scheduler = scheduler
        self.executor = executor
        self.specs = specs
        self._on_changed = on_changed
        self._on_finished = on_finished
        self.provenance = Provenance()
        self.no_cache = no_cache if no_cache is not None else set()  # --no-cache workflows
        self.datasets = datasets
        self._clock = clock
        self._home = home
        self._queue: queue.SimpleQueue[Any] = queue.SimpleQueue()
        self.placements = Placements(store=store, specs=specs, no_cache=self.no_cache,
                                     executor=executor, post=self._queue.put,
                                     provenance=self.provenance, datasets=datasets)
        self._numbers: dict[str, int] = {}
        self._restore, self._inflight, self._on_fatal = restore, inflight, on_fatal
        self._applying: list[Any] = []  # the batch in hand (its calls fail if the engine stops)
        self._dead: BaseException | None = None
        self._thread = threading.Thread(target=self._loop, name="osmo-engine", daemon=True)

    # ------------------------------------------------------------------ public API

    def start(self) -> None:
        """Start the engine thread."""
        self._thread.start()

    def stop(self) -> None:
        """Ask the loop to finish the current batch and exit; wait for it."""
        self._queue.put(_STOP)
        self._thread.join(timeout=30)

    def post(self, event: Event) -> None:
        """Queue an event (thread-safe; called by workers' threads)."""
        self._queue.put(event)

    def call(self, fn: Callable[[Engine, _Batch, float], Any], timeout: float = 60) -> Any:
        """Run ``fn(engine, batch, now)`` on the engine thread; return its result after commit.

        Exceptions raised by ``fn`` propagate to the caller and nothing of it is committed
        (``fn`` must raise before mutating the scheduler).
        """
        if self._dead is not None:
            raise InfrastructureError(f"the server's engine stopped: {reason(self._dead)}")
        future: Future[Any] = Future()
        self._queue.put(_Call(fn, future))
        return future.result(timeout=timeout)

    def next_number(self, name: str) -> int:
        """Allocate the next ``N`` for a workflow called ``name`` (engine thread only)."""
        n = max(self._numbers.get(name, 0), self.store.next_number(name) - 1) + 1
        self._numbers[name] = n
        return n

    # ------------------------------------------------------------------ the loop

    def _loop(self) -> None:
        try:
            while self._step(self._wait()):
                pass
        except BaseException as exc:  # noqa: BLE001 - the engine cannot go on: say so, loudly
            log.critical("the engine cannot go on; the server stops: %s", reason(exc),
                         exc_info=exc)
            self._dead = exc
            self._abandon(exc)
            self._on_fatal(exc)

    def _wait(self) -> list[Any]:
        deadline = self.scheduler.next_deadline()
        timeout = None if deadline is None else max(0.0, deadline - self._clock())
        items: list[Any] = []
        try:
            items.append(self._queue.get(timeout=timeout))
        except queue.Empty:
            return [Tick()]
        while len(items) < 4096:
            try:
                items.append(self._queue.get_nowait())
            except queue.Empty:
                break
        return items

    def _step(self, items: list[Any]) -> bool:
        """Apply what was queued (isolating a culprit if it raises); False after ``stop()``.

        A final report (which carries a task's outputs or messages) is applied and committed
        on its own, so the quarantine file names exactly the report being applied; the
        other events go in batches."""
        for part in _parts(items):
            self._applying = part
            try:
                self._apply(part)
            except Exception as exc:  # noqa: BLE001 - isolated below; only a double fault stops
                log.error("applying %d event(s) failed (%s); applying them one at a time to "
                          "isolate the cause", len(part), reason(exc), exc_info=exc)
                self._isolate(part)
            finally:
                if self._inflight is not None:
                    self._inflight.clear()
        self._applying = []
        return not any(item is _STOP for item in items)

    def _apply(self, items: list[Any], *, tick: bool = True) -> None:
        """Handle ``items``, commit, execute. Raises only before the commit succeeded (then
        nothing of ``items`` is stored, though the scheduler may hold some of it)."""
        batch = _Batch()
        now = self._clock()
        self._mark(items)
        for item in items:
            if isinstance(item, _Call):
                self._run_call(item, batch, now)
            elif item is not _STOP:
                self._handle(item, batch, now)
        if tick:
            deadline = self.scheduler.next_deadline()
            if deadline is not None and deadline <= now:
                batch.commands += self.scheduler.handle(Tick(), now)
        changes, placed = self._commit(batch)
        self._after_commit(batch, changes, placed)

    def _mark(self, items: list[Any]) -> None:
        """Write the quarantine file before applying attempts' final reports."""
        if self._inflight is not None:
            ids = [i.attempt_id for i in items if isinstance(i, (AttemptExited,
                                                                  AttemptStartFailed))]
            if ids:
                self._inflight.mark(ids)

    def _handle(self, event: Event, batch: _Batch, now: float) -> None:
        if not isinstance(event, (AttemptExited, AttemptStartFailed, AttemptLost)):
            batch.commands += self.scheduler.handle(event, now)
            if isinstance(event, AttemptStarted):
                self._note_pid(event, batch)
            return
        before = self.scheduler.attempt(event.attempt_id)  # None: a stale (fenced) report
        if before is None:
            log.info("report on %s ignored: not its task's current attempt", event.attempt_id)
        batch.commands += self.scheduler.handle(event, now)
        after = self.scheduler.attempt(event.attempt_id)
        batch.ended.append(event.attempt_id)
        if (not isinstance(event, AttemptExited) or before is None or not before.status.active
                or after is None or after.status is not TaskStatus.COMPLETED):
            return
        task = self.specs[before.workflow_id].task(before.name)
        row = self.provenance.exited(event, task, started_at=before.started_at, now=now)
        if row is not None:
            batch.lineage.append(row)
            if self.datasets is not None and event.manifest is not None:
                batch.datasets += self.datasets.versions_made(
                    task, Manifest.from_json(event.manifest), event.attempt_id, now)

    def _run_call(self, call: _Call, batch: _Batch, now: float) -> None:
        try:
            batch.replies.append((call.future, call.fn(self, batch, now)))
        except BaseException as exc:  # noqa: BLE001 - handed to the caller's thread
            call.future.set_exception(exc)

    def _commit(self, batch: _Batch) -> tuple[Changes, list[PrepareAttempt]]:
        changes = self.scheduler.take_changes()
        placed = [c for c in batch.commands if isinstance(c, PrepareAttempt)]
        batch.attempts += [attempt_row(self._home, p.attempt_id, p.node_id) for p in placed]
        if (changes or batch.new_workflows or batch.attempts or batch.lineage or batch.datasets
                or batch.tags):
            self.store.commit(changes, new_workflows=batch.new_workflows,
                              attempts=batch.attempts, lineage=batch.lineage,
                              datasets=batch.datasets, tags=batch.tags)
        return changes, placed

    def _after_commit(self, batch: _Batch, changes: Changes,
                      placed: list[PrepareAttempt]) -> None:
        """What follows a commit; never raises (the batch is stored: it must not be isolated
        again), each step's failure is logged."""
        for aid in batch.ended:
            self.provenance.forget(aid)
        for prep in placed:  # after the commit: an upstream completed in this batch is readable
            self.placements.resolve(prep)
        for future, result in batch.replies:
            guard(future.set_result, result)
        for cmd in batch.commands:
            self._execute(cmd)
        changed = {w.id for w in changes.workflows}
        changed |= {t.workflow_id for t in changes.tasks}
        if changed:
            guard(self._on_changed, changed)
        for wf in changes.workflows:
            if wf.status.terminal:
                guard(self.scheduler.forget, wf.id)
                self.specs.pop(wf.id, None)
                guard(self._on_finished, wf.id)

    # ------------------------------------------------------------------ commands

    def _execute(self, cmd: Command) -> None:
        try:
            if isinstance(cmd, PrepareAttempt):
                self.placements.prepare(cmd)
            elif isinstance(cmd, RunAttempt):
                self.executor.run(cmd)
            elif isinstance(cmd, KillAttempt):
                self.executor.kill(cmd)
        except Exception as exc:  # noqa: BLE001 - a worker bug must not stop the engine
            log.exception("executing %r failed", cmd)
            if not isinstance(cmd, KillAttempt):  # else it would wait for ever to start
                self.post(AttemptStartFailed(cmd.attempt_id, f"cannot start: {reason(exc)}"))

    def _note_pid(self, event: AttemptStarted, batch: _Batch) -> None:
        """Record a local attempt's pid so a restarted server can kill a leftover process."""
        task = self.scheduler.attempt(event.attempt_id)
        if event.pid is None or task is None:
            return
        batch.attempts.append(attempt_row(self._home, event.attempt_id, task.node_id,
                                          event.pid, event.pid_start))


def _parts(items: list[Any]) -> list[list[Any]]:
    """``items`` cut so that each attempt's exit or start failure stands alone."""
    parts: list[list[Any]] = [[]]
    for item in items:
        if isinstance(item, (AttemptExited, AttemptStartFailed)):
            parts += [[item], []]
        else:
            parts[-1].append(item)
    return [p for p in parts if p] or [[]]
