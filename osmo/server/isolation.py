"""The pure parts of the engine's fault isolation: what a culprit becomes, and messages.

``osmo.server.engine`` applies a batch that raised again one event at a time; the event that
raises again is the culprit. This module says what replaces it (:func:`failures`), which
attempts a rebuilt scheduler must start again (:func:`restarting`), and how an exception is
told in a stored message (:func:`reason`). No I/O, no engine state.
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from typing import Any

from osmo.errors import OsmoError
from osmo.scheduler.state import TaskState
from osmo.scheduler.types import AttemptExited, AttemptLost, AttemptStartFailed, Event
from osmo.status import TaskStatus

__all__ = ["FINAL", "REBUILT", "describe", "failures", "guard", "reason", "restarting"]

log = logging.getLogger("osmo.server")

FINAL = (AttemptExited, AttemptStartFailed, AttemptLost)
"""Reports after which an attempt no longer runs."""

REBUILT = "the server rebuilt its state after an error; attempt started again"
"""Why an attempt that was starting during a rebuild is lost (and started again)."""

_BARE = "the server could not apply this attempt's report; see the server log"


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


def restarting(active: list[TaskState]) -> list[str]:
    """Attempts a rebuilt scheduler must start again: those still starting, since where
    their group's barrier stood is not in the store (running ones carry on)."""
    return [t.attempt_id for t in active
            if t.attempt_id and t.status is TaskStatus.INITIALIZING]


def guard(fn: Callable[..., Any], *args: Any) -> None:
    """Call ``fn``; log what it raises (bookkeeping after a commit must not stop the loop)."""
    try:
        fn(*args)
    except Exception:  # noqa: BLE001 - logged; the batch is committed already
        log.exception("%s failed after a commit", getattr(fn, "__qualname__", fn))
