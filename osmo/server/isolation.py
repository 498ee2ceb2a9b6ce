"""The engine's fault isolation (see ``osmo.server.engine``): a batch that raised is dropped
from memory by rebuilding the scheduler from the store, and applied again one event at a
time; the event that raises again is the culprit, and becomes its failure.

:class:`FaultIsolation` is the engine's part that does it (a mixin of
``osmo.server.engine.Engine``); the rest are pure helpers: what replaces a culprit
(:func:`failures`), which attempts a rebuilt scheduler must start again
(:func:`restarting`), and how an exception is told in a stored message (:func:`reason`).
"""

from __future__ import annotations

import logging
import queue
from collections.abc import Callable
from concurrent.futures import Future
from dataclasses import dataclass
from typing import Any

from osmo.errors import InfrastructureError, OsmoError
from osmo.scheduler import Scheduler
from osmo.scheduler.state import TaskState
from osmo.scheduler.types import (LOCAL_NODE, AttemptExited, AttemptLost, AttemptStartFailed,
                                  Command, Event, KillAttempt, NodeUp, Tick)
from osmo.server.recovery import Restored
from osmo.spec.model import WorkflowSpec
from osmo.status import TaskStatus

__all__ = ["FINAL", "REBUILT", "STOP", "Call", "FaultIsolation", "describe", "failures",
           "guard", "reason", "restarting"]

log = logging.getLogger("osmo.server")

FINAL = (AttemptExited, AttemptStartFailed, AttemptLost)
"""Reports after which an attempt no longer runs."""

REBUILT = "the server rebuilt its state after an error; attempt started again"
"""Why an attempt that was starting during a rebuild is lost (and started again)."""

_BARE = "the server could not apply this attempt's report; see the server log"

STOP = object()
"""Queued by ``Engine.stop``: finish what is in hand, then leave the loop."""


@dataclass
class Call:
    """``Engine.call``'s request: ``fn(engine, batch, now)`` and where its result goes."""

    fn: Callable[..., Any]
    future: Future[Any]


class FaultIsolation:
    """The engine's fault isolation (a mixin: the engine provides what is declared here)."""

    scheduler: Scheduler
    specs: dict[str, WorkflowSpec]
    no_cache: set[str]
    _restore: Callable[[], Restored] | None
    _queue: queue.SimpleQueue[Any]
    _applying: list[Any]

    def _apply(self, items: list[Any], *, tick: bool = True) -> None:
        raise NotImplementedError

    def _execute(self, cmd: Command) -> None:
        raise NotImplementedError

    def _isolate(self, items: list[Any]) -> None:
        """Rebuild from the store and apply ``items`` one at a time; fail the culprit(s)."""
        self._rebuild()
        for item in items:
            if item is STOP or isinstance(item, Tick) or (
                    isinstance(item, Call) and item.future.done()):
                continue
            try:
                self._apply([item], tick=False)
            except Exception as exc:  # noqa: BLE001 - this one is a culprit
                log.error("%s could not be applied: %s", describe(item), reason(exc),
                          exc_info=exc)
                self._rebuild()
                self._refuse(item, exc)
        self._apply([])  # timeouts due meanwhile; no one event to blame if this raises

    def _rebuild(self) -> None:
        """Replace the scheduler by one built from the store; re-announce the known nodes,
        start again what was starting (``isolation.restarting``)."""
        if self._restore is None:
            raise InfrastructureError("the scheduler cannot be rebuilt (no store to rebuild "
                                      "it from)")
        nodes = self.scheduler.nodes()
        restored = self._restore()
        self.scheduler = restored.scheduler
        self.specs.clear()
        self.specs.update(restored.specs)
        self.no_cache |= restored.no_cache
        again = restarting(restored.active)
        self._apply([*(NodeUp(n) for n in nodes), *(AttemptLost(k.attempt_id, REBUILT)
                                                     for k in again)], tick=False)
        for kill in again:
            self._execute(kill)

    def _refuse(self, item: Any, exc: Exception) -> None:
        """Turn a culprit into its failure: an API call's error, an attempt's failure, or
        (anything else) a log line."""
        why = reason(exc)
        if isinstance(item, Call):
            item.future.set_exception(InfrastructureError(
                f"the server could not apply this request: {why}"))
            return
        if not isinstance(getattr(item, "attempt_id", None), str):
            log.error("dropped %s: %s", describe(item), why)
            return
        placed = self.scheduler.attempt(item.attempt_id)
        node = placed.node_id if placed is not None and placed.node_id else LOCAL_NODE
        for failure in failures(item, why):
            try:
                self._apply([failure], tick=False)
                break
            except Exception as again:  # noqa: BLE001 - try the plainer failure next
                log.error("recording %s failed: %s", describe(failure), reason(again))
                self._rebuild()
        else:
            raise InfrastructureError(f"the failure of {describe(item)} cannot be recorded")
        if not isinstance(item, FINAL):  # it still runs: stop it
            self._execute(KillAttempt(item.attempt_id, node, f"the server could not apply its "
                                                              f"report ({why})"))

    def _abandon(self, exc: BaseException) -> None:
        """The engine stopped: every call in hand or queued gets an error."""
        error = InfrastructureError(f"the server's engine stopped: {reason(exc)}")
        pending = list(self._applying)
        while True:
            try:
                pending.append(self._queue.get_nowait())
            except queue.Empty:
                break
        for item in pending:
            if isinstance(item, Call) and not item.future.done():
                item.future.set_exception(error)


def reason(exc: BaseException) -> str:
    """A one-line, ASCII-safe account of ``exc`` for messages that are stored and shown."""
    text = str(exc) if isinstance(exc, OsmoError) else f"{type(exc).__name__}: {exc}"
    text = text.encode("ascii", "backslashreplace").decode("ascii").replace("\n", " ")
    return text if len(text) <= 500 else text[:497] + "..."


def describe(item: Any) -> str:
    """``AttemptExited of wf-1:t:0``: an event (or call) as the log names it."""
    aid = getattr(item, "attempt_id", None)
    return type(item).__name__.lstrip("_") + (f" of {aid}" if aid else "")


def failures(event: Any, why: str) -> list[Event]:
    """What replaces a culprit attempt report, plainest last (tried in order until one can be
    applied): an exit without outputs (FAILED; exit code 3005 after a successful exit), or
    a start failure; the last one carries no text from the culprit at all."""
    aid = str(event.attempt_id)
    message = (f"the server could not apply this attempt's report ({why}); the attempt "
               "failed so that everything else could go on")
    out: list[Event] = [AttemptStartFailed(aid, message), AttemptStartFailed(aid, _BARE)]
    if isinstance(event, AttemptExited):
        out.insert(0, AttemptExited(aid, event.exit_code, None, message))
    return out


def restarting(active: list[TaskState]) -> list[KillAttempt]:
    """Attempts a rebuilt scheduler must start again: those still starting, since where
    their group's barrier stood is not in the store (running ones carry on); each as the
    kill that stops what its executor prepared."""
    return [KillAttempt(t.attempt_id, t.node_id or LOCAL_NODE, REBUILT) for t in active
            if t.attempt_id and t.status is TaskStatus.INITIALIZING]


def guard(fn: Callable[..., Any], *args: Any) -> None:
    """Call ``fn``; log what it raises (bookkeeping after a commit must not stop the loop)."""
    try:
        fn(*args)
    except Exception:  # noqa: BLE001 - logged; the batch is committed already
        log.exception("%s failed after a commit", getattr(fn, "__qualname__", fn))
