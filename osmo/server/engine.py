"""The engine: the one thread that feeds events to the scheduler and carries out its commands.

Owns the loop ``events → Scheduler.handle → commit to the store → execute commands``. Every
batch of state changes is committed in one transaction *before* any command of that batch is
executed, so a server killed at any instant restarts into a consistent state. Events from
executors and typed requests from API threads (``osmo.server.requests``) arrive in one
inbox (``osmo.server.inbox``); the loop blocks on it until something arrives or the
scheduler's next deadline (a timeout) is due — no polling. A turn that holds only start reports
(nothing to send for them) waits a few milliseconds more for the next report, so that both are
committed at once (``_starts_only``).

Fault isolation: no exception stops the loop. When applying a batch raises — in the
scheduler, while building lineage, or in the commit itself — nothing of the batch was
committed, so the engine drops it from memory by rebuilding the scheduler from the store
(``osmo.server.recovery``) and applies the batch's events again one at a time. The event that
raises again is the culprit: an attempt's report becomes a failure of that attempt (FAILED
with the message, exit code 3005 for an exit; FAILED_START_ERROR otherwise; a still-running
attempt is killed), a request gets the error, anything else is logged and dropped; every
other event is applied as usual (``osmo.server.isolation``). Attempts that were still
starting when the scheduler was rebuilt are reported lost and started again (a group
barrier's progress is not kept in the store). Only when even a failure cannot be committed,
or the store cannot be read, does the engine stop: it then calls ``on_fatal`` (the server
exits non-zero, so a supervisor sees it) and every waiting request gets an error. A hard
crash while reports are applied is covered by the quarantine file
(``osmo.server.recovery.InFlight``).

It must not parse specs, talk zenoh or format output; those belong to other layers.
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable, Sequence
from typing import Any

from osmo.artifacts import Manifest
from osmo.errors import InfrastructureError, NotFoundError, SubmitError, UsageError
from osmo.executor import Executor
from osmo.layout import Home
from osmo.scheduler import Scheduler
from osmo.scheduler.types import (
    DEFAULT_MAX_RETRIES,
    AttemptExited,
    AttemptLost,
    AttemptPrepared,
    AttemptStarted,
    AttemptStartFailed,
    CancelWorkflow,
    Changes,
    Command,
    Event,
    KillAttempt,
    NodeUp,
    PrepareAttempt,
    RunAttempt,
    Tick,
    WorkflowSubmitted,
)
from osmo.server.batch import Batch
from osmo.server.datasets import Datasets
from osmo.server.inbox import STOP, Asked, Inbox
from osmo.server.isolation import REBUILT, Isolation, guard, reason, restarting
from osmo.server.placing import Placements
from osmo.server.provenance import Provenance
from osmo.server.recovery import InFlight, Restored
from osmo.server.requests import (
    AddDatasetVersion,
    AttemptsOn,
    ListNodes,
    Request,
    SubmitWorkflow,
    TagDataset,
    TagWorkflow,
    WaitReasons,
)
from osmo.spec.model import WorkflowSpec
from osmo.status import TaskStatus
from osmo.store.sqlite import NewWorkflowRow, Store, TagRow

__all__ = ["Engine"]

log = logging.getLogger("osmo.server")

_RIDE = 0.01  # seconds a turn of start reports alone waits for more (``_starts_only``)


class Engine:
    """Runs the scheduler on its own thread.

    Args:
        store: the state store (the engine is its only writer).
        scheduler: the scheduler, already restored from the store if recovering.
        executors: what runs attempts (``osmo.executor``); each command goes to the first
            that owns its node. The engine closes them when it stops.
        inbox: where events and requests for the engine arrive.
        specs: workflow id → spec for every workflow the scheduler holds.
        on_changed: called with the ids of workflows whose state changed (after commit), and
            those of them that ended.
        on_finished: called with the id of each workflow that ended (after commit).
        datasets: resolves dataset inputs and records dataset outputs.
        reuse: workflow id → True if submitted with ``--reuse``, False with ``--no-cache``
            (kept current here).
        restore: rebuilds a scheduler from the store (``osmo.server.recovery.restore``);
            without it a batch that raises stops the engine.
        inflight: the quarantine file (``osmo.server.recovery.InFlight``), if any.
        on_fatal: called (on the engine thread) when the engine cannot go on.
        clock: time source (injectable for tests).
        image_ids: ``(workflow id, image) → id`` on this host, when image tasks run in
            containers (the cache fingerprints the id; ``osmo.server.placing.Placements``).
    """

    def __init__(self, *, store: Store, scheduler: Scheduler, executors: Sequence[Executor],
                 inbox: Inbox,
                 specs: dict[str, WorkflowSpec], on_changed: Callable[[set[str], set[str]], None],
                 home: Home, on_finished: Callable[[str], None] = lambda _wf: None,
                 datasets: Datasets | None = None, reuse: dict[str, bool] | None = None,
                 restore: Callable[[], Restored] | None = None,
                 inflight: InFlight | None = None,
                 on_fatal: Callable[[BaseException], None] = lambda _exc: None,
                 clock: Callable[[], float] = time.time,
                 image_ids: Callable[[str, str], str | None] | None = None) -> None:
        self.store = store
        self.scheduler = scheduler
        self._executors = tuple(executors)
        self.specs = specs
        self._inbox = inbox
        self._on_changed = on_changed
        self._on_finished = on_finished
        self.provenance = Provenance()
        self.reuse = reuse if reuse is not None else {}  # --reuse / --no-cache workflows
        self.datasets = datasets
        self._clock = clock
        self._home = home
        self.placements = Placements(store=store, specs=specs, reuse=self.reuse,
                                     post=inbox.post, provenance=self.provenance,
                                     datasets=datasets, image_ids=image_ids)
        self._numbers: dict[str, int] = {}
        self._restore, self._inflight, self._on_fatal = restore, inflight, on_fatal
        self._isolation = Isolation(apply=self._apply, rebuild=self._rebuild,
                                    execute=self._execute, node_of=self._node_of)
        self._applying: list[Any] = []  # the batch in hand (its requests fail if we stop)
        self._thread = threading.Thread(target=self._loop, name="osmo-engine", daemon=True)

    # ------------------------------------------------------------------ public API

    def start(self) -> None:
        """Start the engine thread."""
        self._thread.start()

    def stop(self) -> None:
        """Ask the loop to finish the current batch and exit; wait, then close the executors."""
        self._inbox.stop()
        self._thread.join(timeout=30)
        for executor in self._executors:
            guard(executor.close)

    def post(self, event: Event) -> None:
        """Queue an event (thread-safe)."""
        self._inbox.post(event)

    def ask(self, request: Request, timeout: float = 60) -> Any:
        """Apply ``request`` on the engine thread; return its answer after the commit.

        See ``osmo.server.requests``; raises what applying it raised.
        """
        return self._inbox.ask(request, timeout)

    # ------------------------------------------------------------------ the loop

    def _loop(self) -> None:
        try:
            while self._step(self._wait()):
                pass
        except BaseException as exc:  # noqa: BLE001 - the engine cannot go on: say so, loudly
            log.critical("the engine cannot go on; the server stops: %s", reason(exc),
                         exc_info=exc)
            self._inbox.close(reason(exc), self._applying)
            self._on_fatal(exc)

    def _wait(self) -> list[Any]:
        deadline = self.scheduler.next_deadline()
        timeout = None if deadline is None else max(0.0, deadline - self._clock())
        items = self._inbox.take(timeout) or [Tick()]
        if _starts_only(items):
            # Their attempts run already and nothing is to be sent for them: they ride with
            # what comes next (the exit of a short task, the other slot's report), one
            # commit for both, if it comes soon. Nothing else waits meanwhile.
            ride = _RIDE if deadline is None else min(_RIDE, max(0.0, deadline - self._clock()))
            items += self._inbox.take(ride)
        return items

    def _step(self, items: list[Any]) -> bool:
        """Apply what was queued (isolating a culprit if it raises); False after ``stop()``.

        Everything queued together is applied and committed in one transaction, the final
        reports of many attempts included (the quarantine file names them all while they
        are applied). A final report of a task a server already died on (a suspect,
        ``InFlight.suspect``) is applied and committed on its own, so that a second crash
        names exactly that report.
        """
        suspect = self._inflight.suspect if self._inflight is not None else None
        for part in _parts(items, suspect):
            self._applying = part
            try:
                self._apply(part)
            except Exception as exc:  # noqa: BLE001 - isolated below; only a double fault stops
                log.error("applying %d event(s) failed (%s); applying them one at a time to "
                          "isolate the cause", len(part), reason(exc), exc_info=exc)
                self._isolation.isolate(part)
            finally:
                if self._inflight is not None:
                    self._inflight.clear()
        self._applying = []
        return not any(item is STOP for item in items)

    def _apply(self, items: list[Any], tick: bool = True) -> None:
        """Handle ``items``, commit, execute.

        Raises only before the commit succeeded (then nothing of ``items`` is stored, though the
        scheduler may hold some of it).
        """
        batch = Batch()
        now = self._clock()
        self._mark(items)
        for item in items:
            if isinstance(item, Asked):
                self._answer(item, batch, now)
            elif item is not STOP:
                self._handle(item, batch, now)
        if tick:
            deadline = self.scheduler.next_deadline()
            if deadline is not None and deadline <= now:
                batch.commands += self.scheduler.handle(Tick(), now)
        changes, placed = batch.commit(self.store, self.scheduler, self._home)
        self._after_commit(batch, changes, placed)

    def _mark(self, items: list[Any]) -> None:
        """Write the quarantine file before applying attempts' final reports."""
        if self._inflight is not None:
            ids = [i.attempt_id for i in items if isinstance(i, (AttemptExited,
                                                                  AttemptStartFailed))]
            if ids:
                self._inflight.mark(ids)

    def _handle(self, event: Event, batch: Batch, now: float) -> None:
        if not isinstance(event, (AttemptExited, AttemptStartFailed, AttemptLost)):
            batch.commands += self.scheduler.handle(event, now)
            if isinstance(event, AttemptStarted) and event.pid is not None:
                # a local process: recorded so a restarted server can kill what is left
                batch.pids.append((event.attempt_id, event.pid, event.pid_start))
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

    # ------------------------------------------------------------------ requests

    def _answer(self, asked: Asked, batch: Batch, now: float) -> None:
        try:
            batch.replies.append((asked.future, self._request(asked.request, batch, now)))
        except BaseException as exc:  # noqa: BLE001 - handed to the asker's thread
            asked.future.set_exception(exc)

    def _request(self, request: Request, batch: Batch, now: float) -> Any:
        """Apply one request (see ``osmo.server.requests``); raise before changing anything."""
        match request:
            case SubmitWorkflow():
                return self._submit(request, batch, now)
            case CancelWorkflow(workflow_id=wf_id):
                try:
                    self.scheduler.workflow(wf_id)
                except KeyError:
                    return None  # it ended and was forgotten
                batch.commands += self.scheduler.handle(request, now)
                return None
            case TagDataset(name=name, tag=tag, version=version):
                batch.tags.append(TagRow(name, tag, version))
                return None
            case TagWorkflow(workflow_id=wf_id):
                return self._tag_workflow(request, batch)
            case AddDatasetVersion():
                if self.datasets is None:
                    raise UsageError("this server keeps no datasets")
                row = self.datasets.version_row(request.name, request.manifest, source=None,
                                                attempt_id=None, now=now,
                                                metadata=dict(request.metadata))
                batch.datasets.append(row)
                return row.version
            case AttemptsOn(node_id=node_id):
                return self.scheduler.attempts_on(node_id)
            case ListNodes():
                return [(node, self.scheduler.used(node.id),
                         {p: self.scheduler.used(node.id, p) for p in node.platforms})
                        for node in self.scheduler.nodes()]
            case WaitReasons(workflow_id=wf_id, names=names):
                return self.scheduler.waiting(wf_id, names)
        raise TypeError(f"not a request: {request!r}")

    def _tag_workflow(self, request: TagWorkflow, batch: Batch) -> list[str]:
        """The workflow's tags with ``add`` added and ``remove`` removed, to be committed."""
        tags = batch.workflow_tags.get(request.workflow_id)
        if tags is None:  # not changed earlier in this batch: as committed
            row = self.store.workflow(request.workflow_id, with_spec=False)
            if row is None:
                raise NotFoundError(f"no workflow {request.workflow_id}")
            tags = list(row.options.tags)
        kept = [t for t in tags if t not in request.remove]
        new = sorted(set(kept) | set(request.add))
        batch.workflow_tags[request.workflow_id] = new
        return new

    def _submit(self, request: SubmitWorkflow, batch: Batch, now: float) -> str:
        spec, pool = request.spec, request.options.pool
        reasons = self.scheduler.check_fit(spec, pool)
        if reasons:
            raise SubmitError("cannot run this workflow:\n  " + "\n  ".join(reasons))
        n = max(self._numbers.get(spec.name, 0), self.store.next_number(spec.name) - 1) + 1
        self._numbers[spec.name] = n
        wf_id = f"{spec.name}-{n}"
        retries = spec.max_retries if spec.max_retries is not None else DEFAULT_MAX_RETRIES
        batch.commands += self.scheduler.handle(
            WorkflowSubmitted(wf_id, spec, retries, pool, dict(request.reused),
                              request.options.priority), now)
        self.specs[wf_id] = spec
        submitted = request.options.reuses
        if submitted is not None:
            self.reuse[wf_id] = submitted
        batch.workflows.append(NewWorkflowRow(wf_id, spec.name, n, now, request.stored,
                                              request.options))
        return wf_id

    def _after_commit(self, batch: Batch, changes: Changes,
                      placed: list[PrepareAttempt]) -> None:
        """What follows a commit; never raises.

        The batch is stored, so it must not be isolated again: each step's failure is logged.
        """
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
            guard(self._on_changed, changed, {w.id for w in changes.workflows
                                              if w.status.terminal})
        for wf in changes.workflows:
            if wf.status.terminal:
                guard(self.scheduler.forget, wf.id)
                self.specs.pop(wf.id, None)
                guard(self._on_finished, wf.id)

    # ------------------------------------------------------------------ commands

    def _execute(self, cmd: Command) -> None:
        """Hand ``cmd`` to the executor of its node.

        A placement goes through the cache and the input resolution first (``osmo.server.placing``).
        """
        executor = next((e for e in self._executors if e.owns(cmd.node_id)), None)
        try:
            if isinstance(cmd, PrepareAttempt):
                self.placements.prepare(cmd, executor)
            elif executor is None and isinstance(cmd, KillAttempt):
                log.warning("%s not killed: no executor runs node '%s'", cmd.attempt_id,
                            cmd.node_id)
            elif executor is None:
                raise InfrastructureError(f"no executor runs node '{cmd.node_id}'")
            elif isinstance(cmd, RunAttempt):
                executor.run(cmd)
            else:
                executor.kill(cmd)
        except Exception as exc:  # noqa: BLE001 - a worker bug must not stop the engine
            log.exception("executing %r failed", cmd)
            if not isinstance(cmd, KillAttempt):  # else it would wait for ever to start
                self.post(AttemptStartFailed(cmd.attempt_id, f"cannot start: {reason(exc)}"))

    # ------------------------------------------------------------------ rebuilding

    def _rebuild(self) -> None:
        """Replace the scheduler by one built from the store.

        The known nodes are announced again, and what was starting is started again
        (``isolation.restarting``).
        """
        if self._restore is None:
            raise InfrastructureError("the scheduler cannot be rebuilt (no store to rebuild "
                                      "it from)")
        nodes = self.scheduler.nodes()
        restored = self._restore()
        self.scheduler = restored.scheduler
        self.specs.clear()
        self.specs.update(restored.specs)
        self.reuse.update(restored.reuse)
        again = restarting(restored.active)
        self._apply([*(NodeUp(n) for n in nodes),
                     *(AttemptLost(kill.attempt_id, REBUILT) for kill in again)], tick=False)
        for kill in again:
            self._execute(kill)

    def _node_of(self, attempt_id: str) -> str | None:
        """Where the scheduler placed ``attempt_id`` (None: not a current attempt)."""
        task = self.scheduler.attempt(attempt_id)
        return task.node_id if task is not None else None


def _starts_only(items: list[Any]) -> bool:
    """Whether ``items`` are start reports of attempts their worker started by itself.

    Each an ``AttemptStarted``, or an ``AttemptPrepared`` with its attempt's ``AttemptStarted``
    (no barrier held it: a prepared report alone may release a group's). Applied, they send
    nothing: the commit of their change (RUNNING) may wait for the next turn's, which is
    committed before any command of its own is sent. A crash meanwhile loses only what a crash
    before their arrival would have lost (their attempt is recovered as any that did not
    report its start).
    """
    started = {i.attempt_id for i in items if isinstance(i, AttemptStarted)}
    return bool(started) and all(isinstance(i, AttemptStarted) or (
        isinstance(i, AttemptPrepared) and i.attempt_id in started) for i in items)


def _parts(items: list[Any], suspect: Callable[[str], bool] | None) -> list[list[Any]]:
    """``items`` cut so that each suspect attempt's exit or start failure stands alone."""
    parts: list[list[Any]] = [[]]
    for item in items:
        if (suspect is not None and isinstance(item, (AttemptExited, AttemptStartFailed))
                and suspect(item.attempt_id)):
            parts += [[item], []]
        else:
            parts[-1].append(item)
    return [p for p in parts if p] or [[]]
