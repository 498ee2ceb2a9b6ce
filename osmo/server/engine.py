"""The engine: the one thread that feeds events to the scheduler and carries out its commands.

Owns the loop ``events → Scheduler.handle → commit to the store → execute commands``. Every
batch of state changes is committed in one transaction *before* any command of that batch is
executed, so a server killed at any instant restarts into a consistent state. Events from
workers and calls from API threads arrive on one queue; the loop blocks on it until an event
arrives or the scheduler's next deadline (a timeout) is due — no polling.

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
    AttemptPrepared,
    AttemptStarted,
    AttemptStartFailed,
    Command,
    Event,
    KillAttempt,
    PrepareAttempt,
    RunAttempt,
    Tick,
)
from osmo.spec.model import TaskSpec, WorkflowSpec
from osmo.artifacts import Manifest
from osmo.errors import OsmoError
from osmo.record import LineageInput
from osmo.server import cache
from osmo.server.datasets import Datasets
from osmo.server.cache import CacheHit
from osmo.server.provenance import Provenance
from osmo.status import TaskStatus
from osmo.worker.workdir import AttemptDirs
from osmo.store.sqlite import AttemptRow, DatasetRow, LineageRow, Store

__all__ = ["Engine", "Executor"]

log = logging.getLogger("osmo.server")


class Executor(Protocol):
    """What the engine needs from a pool of workers (the local pool, later remote ones)."""

    def prepare(self, cmd: PrepareAttempt, task: TaskSpec) -> None: ...
    def run(self, attempt_id: str) -> None: ...
    def kill(self, attempt_id: str, reason: str) -> None: ...
    def running(self) -> dict[str, int]: ...


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


@dataclass
class _Call:
    fn: Callable[[Engine, _Batch, float], Any]
    future: Future[Any]


_STOP = object()


class Engine:
    """Runs the scheduler on its own thread.

    Args:
        store: the state store (the engine is its only writer).
        scheduler: the scheduler, already restored from the store if recovering.
        executor: the pool that runs attempts.
        specs: workflow id → spec for every workflow the scheduler holds.
        on_changed: called with the ids of workflows whose state changed (after commit).
        on_finished: called with the id of each workflow that ended (after commit).
        clock: time source (injectable for tests).
    """

    def __init__(self, *, store: Store, scheduler: Scheduler, executor: Executor,
                 specs: dict[str, WorkflowSpec], on_changed: Callable[[set[str]], None],
                 home: Any, on_finished: Callable[[str], None] = lambda _wf: None,
                 datasets: Datasets | None = None,
                 clock: Callable[[], float] = time.time) -> None:
        self.store = store
        self.scheduler = scheduler
        self.executor = executor
        self.specs = specs
        self._on_changed = on_changed
        self._on_finished = on_finished
        self.provenance = Provenance()
        self.no_cache: set[str] = set()  # workflows submitted with --no-cache
        self._hits: dict[str, CacheHit] = {}
        self.datasets = datasets
        self._ready: dict[str, PrepareAttempt | str] = {}  # placed: final command, or why not
        self._clock = clock
        self._home = home
        self._queue: queue.SimpleQueue[Any] = queue.SimpleQueue()
        self._numbers: dict[str, int] = {}
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
        while True:
            items = self._wait()
            if not self._run_batch(items):
                return

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

    def _run_batch(self, items: list[Any]) -> bool:
        batch = _Batch()
        keep_going = True
        now = self._clock()
        for item in items:
            if item is _STOP:
                keep_going = False
            elif isinstance(item, _Call):
                self._run_call(item, batch, now)
            else:
                self._handle(item, batch, now)
        deadline = self.scheduler.next_deadline()
        if deadline is not None and deadline <= now:
            batch.commands += self.scheduler.handle(Tick(), now)
        self._commit_and_execute(batch)
        return keep_going

    def _handle(self, event: Event, batch: _Batch, now: float) -> None:
        if not isinstance(event, (AttemptExited, AttemptStartFailed, AttemptLost)):
            batch.commands += self.scheduler.handle(event, now)
            if isinstance(event, AttemptStarted):
                self._note_pid(event.attempt_id, batch)
            return
        before = self.scheduler.attempt(event.attempt_id)  # None: a stale (fenced) report
        if before is None:
            log.info("report on %s ignored: not its task's current attempt", event.attempt_id)
        batch.commands += self.scheduler.handle(event, now)
        after = self.scheduler.attempt(event.attempt_id)
        if (not isinstance(event, AttemptExited) or before is None or not before.status.active
                or after is None or after.status is not TaskStatus.COMPLETED):
            self.provenance.forget(event.attempt_id)
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

    def _commit_and_execute(self, batch: _Batch) -> None:
        changes = self.scheduler.take_changes()
        placed = [c for c in batch.commands if isinstance(c, PrepareAttempt)]
        batch.attempts += [self._attempt_row(p.attempt_id, p.node_id) for p in placed]
        if (changes or batch.new_workflows or batch.attempts or batch.lineage or batch.datasets
                or batch.tags):
            self.store.commit(changes, new_workflows=batch.new_workflows,
                              attempts=batch.attempts, lineage=batch.lineage,
                              datasets=batch.datasets, tags=batch.tags)
        for prep in placed:  # after the commit: an upstream completed in this batch is readable
            self._resolve(prep)
        for future, result in batch.replies:
            future.set_result(result)
        for cmd in batch.commands:
            self._execute(cmd)
        changed = {w.id for w in changes.workflows}  # type: ignore[attr-defined]
        changed |= {t.workflow_id for t in changes.tasks}  # type: ignore[attr-defined]
        if changed:
            self._on_changed(changed)
        for wf in changes.workflows:
            if wf.status.terminal:  # type: ignore[attr-defined]
                self.scheduler.forget(wf.id)  # type: ignore[attr-defined]
                self.specs.pop(wf.id, None)  # type: ignore[attr-defined]
                self._on_finished(wf.id)  # type: ignore[attr-defined]

    def _resolve(self, cmd: PrepareAttempt) -> None:
        """Settle what a placed attempt needs before it is prepared: dataset and other-workflow
        inputs, its cache key, and a cache hit if there is one."""
        try:
            if self.datasets is not None:
                cmd = self.datasets.resolve_inputs(cmd, self.specs[cmd.workflow_id].task(cmd.task))
        except OsmoError as exc:
            self._ready[cmd.attempt_id] = str(exc)
            return
        self._ready[cmd.attempt_id] = cmd
        sources = cache.input_sources(self.store, cmd)
        key = self._cache_key(cmd, sources)
        self.provenance.placed(cmd, cmd.hosts.get(cmd.task, cmd.node_id), key, sources)
        hit = cache.lookup(self.store, key) if key else None
        if hit is not None:
            self._hits[cmd.attempt_id] = hit

    def _attempt_row(self, attempt_id: str, node_id: str | None, pid: int | None = None,
                     pid_start: float | None = None) -> AttemptRow:
        dirs = AttemptDirs.of_attempt(self._home, attempt_id)
        wf, task, retry = attempt_id.rsplit(":", 2)
        return AttemptRow(attempt_id, wf, task, int(retry), node_id,
                          str(dirs.root) if dirs else None, pid, pid_start)

    def _cache_key(self, cmd: PrepareAttempt,
                   sources: list[LineageInput | None]) -> str | None:
        """The attempt's cache fingerprint, or None when it must run (see osmo.server.cache)."""
        task = self.specs[cmd.workflow_id].task(cmd.task)
        if not cmd.run or not task.cache or cmd.workflow_id in self.no_cache:
            return None
        if any(i.url for i in task.inputs) or any(o.url for o in task.outputs):
            return None  # URL contents are unknown at placement; a hit would skip the upload
        if any(s is None for s in sources):
            return None  # an input without a recorded manifest: its content is unknown
        return cache.fingerprint(task, [(s.task, s.manifest_digest) for s in sources if s])

    def _prepare(self, cmd: PrepareAttempt) -> None:
        ready = self._ready.pop(cmd.attempt_id, cmd)
        hit = self._hits.pop(cmd.attempt_id, None)
        if isinstance(ready, str):
            self._queue.put(AttemptStartFailed(cmd.attempt_id, ready))
        elif hit is not None:
            self._replay(ready, hit)
        else:
            self.executor.prepare(ready, self.specs[ready.workflow_id].task(ready.task))

    def _replay(self, cmd: PrepareAttempt, hit: CacheHit) -> None:
        """Complete a cache hit at once: the scheduler sees an ordinary successful attempt."""
        message = f"cached: outputs of {hit.attempt_id}"
        for event in (AttemptPrepared(cmd.attempt_id), AttemptStarted(cmd.attempt_id),
                      AttemptExited(cmd.attempt_id, 0, hit.output_path, message,
                                    manifest=hit.manifest_body, cached=True)):
            self._queue.put(event)

    def _execute(self, cmd: Command) -> None:
        try:
            if isinstance(cmd, PrepareAttempt):
                self._prepare(cmd)
            elif isinstance(cmd, RunAttempt):
                self.executor.run(cmd.attempt_id)
            elif isinstance(cmd, KillAttempt):
                self.executor.kill(cmd.attempt_id, cmd.reason)
        except Exception:  # noqa: BLE001 - a worker bug must not stop the engine
            log.exception("executing %r failed", cmd)

    def _note_pid(self, attempt_id: str, batch: _Batch) -> None:
        """Record the attempt's pid so a restarted server can kill a leftover process."""
        from osmo.runtime.process import process_start_time

        pid = self.executor.running().get(attempt_id)
        task = self.scheduler.attempt(attempt_id)
        if pid is None or task is None:
            return
        batch.attempts.append(self._attempt_row(attempt_id, task.node_id, pid,
                                                process_start_time(pid)))
