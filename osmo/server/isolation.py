"""The engine's fault isolation (see ``osmo.server.engine``).

A batch that raised is dropped from memory by rebuilding the scheduler from the store, and applied
again one item at a time; the item that raises again is the culprit, and becomes its failure.

:class:`Isolation` does it, a collaborator the engine owns; the rest are pure helpers: what
replaces a culprit (:func:`failures`), which attempts a rebuilt scheduler must start again
(:func:`restarting`), and how an exception is told in a stored message (:func:`reason`).
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from typing import Any

from osmo.errors import InfrastructureError, OsmoError
from osmo.scheduler.state import TaskState
from osmo.scheduler.types import (
    LOCAL_NODE,
    AttemptExited,
    AttemptLost,
    AttemptStartFailed,
    Command,
    Event,
    KillAttempt,
    Tick,
)
from osmo.server.inbox import STOP, Asked
from osmo.status import TaskStatus

__all__ = ["FINAL", "REBUILT", "Isolation", "describe", "failures", "guard", "reason",
           "restarting"]

log = logging.getLogger("osmo.server")

FINAL = (AttemptExited, AttemptStartFailed, AttemptLost)
"""Reports after which an attempt no longer runs."""

REBUILT = "the server rebuilt its state after an error; attempt started again"
"""Why an attempt that was starting during a rebuild is lost (and started again)."""

_BARE = "the server could not apply this attempt's report; see the server log"


class Isolation:
    """Applies a batch that raised again, one item at a time, and fails the culprit(s).

    The engine owns one and gives it what it needs of the engine: ``apply(items, tick)``
    (handle, commit and execute ``items``; raises only before the commit), ``rebuild()``
    (replace the scheduler by one built from the store) and ``execute(command)``, and
    ``node_of(attempt_id)``: where the scheduler placed an attempt (None if unknown).
    """

    def __init__(self, *, apply: Callable[[list[Any], bool], None],
                 rebuild: Callable[[], None], execute: Callable[[Command], None],
                 node_of: Callable[[str], str | None]) -> None:
        self._apply, self._rebuild, self._execute = apply, rebuild, execute
        self._node_of = node_of

    def isolate(self, items: list[Any]) -> None:
        """Rebuild from the store and apply ``items`` one at a time; fail the culprit(s)."""
        self._rebuild()
        for item in items:
            if item is STOP or isinstance(item, Tick) or (
                    isinstance(item, Asked) and item.future.done()):
                continue
            try:
                self._apply([item], False)
            except Exception as exc:  # noqa: BLE001 - this one is a culprit
                log.error("%s could not be applied: %s", describe(item), reason(exc),
                          exc_info=exc)
                self._rebuild()
                self._refuse(item, exc)
        self._apply([], True)  # timeouts due meanwhile; no one event to blame if this raises

    def _refuse(self, item: Any, exc: Exception) -> None:
        """Turn a culprit into its failure.

        A request gets the error, an attempt fails, anything else is a log line.
        """
        why = reason(exc)
        if isinstance(item, Asked):
            item.future.set_exception(InfrastructureError(
                f"the server could not apply this request: {why}"))
            return
        if not isinstance(getattr(item, "attempt_id", None), str):
            log.error("dropped %s: %s", describe(item), why)
            return
        node = self._node_of(item.attempt_id) or LOCAL_NODE
        for failure in failures(item, why):
            try:
                self._apply([failure], False)
                break
            except Exception as again:  # noqa: BLE001 - try the plainer failure next
                log.error("recording %s failed: %s", describe(failure), reason(again))
                self._rebuild()
        else:
            raise InfrastructureError(f"the failure of {describe(item)} cannot be recorded")
        if not isinstance(item, FINAL):  # it still runs: stop it
            self._execute(KillAttempt(item.attempt_id, node, f"the server could not apply its "
                                                              f"report ({why})"))


def reason(exc: BaseException) -> str:
    """A one-line, ASCII-safe account of ``exc`` for messages that are stored and shown."""
    text = str(exc) if isinstance(exc, OsmoError) else f"{type(exc).__name__}: {exc}"
    text = text.encode("ascii", "backslashreplace").decode("ascii").replace("\n", " ")
    return text if len(text) <= 500 else text[:497] + "..."


def describe(item: Any) -> str:
    """``AttemptExited of wf-1:t:0``: an event (or request) as the log names it."""
    if isinstance(item, Asked):
        return f"request {type(item.request).__name__}"
    aid = getattr(item, "attempt_id", None)
    return type(item).__name__.lstrip("_") + (f" of {aid}" if aid else "")


def failures(event: Any, why: str) -> list[Event]:
    """What replaces a culprit attempt report, plainest last.

    Tried in order until one can be applied: an exit without outputs (FAILED; exit code 3005 after a
    successful exit), or a start failure; the last one carries no text from the culprit at all.
    """
    aid = str(event.attempt_id)
    message = (f"the server could not apply this attempt's report ({why}); the attempt "
               "failed so that everything else could go on")
    out: list[Event] = [AttemptStartFailed(aid, message), AttemptStartFailed(aid, _BARE)]
    if isinstance(event, AttemptExited):
        out.insert(0, AttemptExited(aid, event.exit_code, None, message))
    return out


def restarting(active: list[TaskState]) -> list[KillAttempt]:
    """Attempts a rebuilt scheduler must start again, each as the kill that stops it.

    Those still starting, since where their group's barrier stood is not in the store (running ones
    carry on); the kill stops what their executor prepared.
    """
    return [KillAttempt(t.attempt_id, t.node_id or LOCAL_NODE, REBUILT) for t in active
            if t.attempt_id and t.status is TaskStatus.INITIALIZING]


def guard(fn: Callable[..., Any], *args: Any) -> None:
    """Call ``fn``; log what it raises (bookkeeping after a commit must not stop the loop)."""
    try:
        fn(*args)
    except Exception:  # noqa: BLE001 - logged; the batch is committed already
        log.exception("%s failed after a commit", getattr(fn, "__qualname__", fn))
