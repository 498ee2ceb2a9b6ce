"""Merges a workflow's attempt logs and its status transitions into one time-ordered stream.

It is read a bounded chunk at a time. A cursor (attempt id → position in its log, see
``osmo.worker.logread``, plus the last event-log sequence number) names where a reader is;
each call returns what follows it, up to about :data:`CHUNK` bytes of log, and ``more`` when
it stopped short: the server never holds a whole log, and a client prints as it receives.

A chunk is a true merge: it reads a window of every attempt's log and returns the records
up to the earliest time at which a window stopped short, so the records come in time order
across calls too (each log in the order it was written). ``tail`` and ``since`` pick the
starting cursor: the last N records (walking each log back from its end) and the first
records at or after a time (bisecting each log).
"""

from __future__ import annotations

import heapq
import itertools
import math
from collections.abc import Iterable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from osmo.layout import AttemptDirs
from osmo.server.reused_logs import reused_blocks
from osmo.status import WorkflowStatus
from osmo.store.sqlite import AttemptRow, Store, WorkflowRow
from osmo.worker.logread import end_position, newest_first, position_at, read_window

__all__ = ["CHUNK", "LogFilter", "iter_logs", "last_progress", "last_pull", "read_logs"]

CHUNK = 256 << 10
"""Bytes of log one ``logs`` call reads at most (over all attempts; each reads 16 KiB or
more, and a record is never cut)."""
_MIN_WINDOW = 16 << 10

_TAIL = 16384
_PULL = "\tosmo\tpull: "  # how a worker logs each line of an image pull (worker.starts)


def _tail(log: Path) -> str | None:
    """The last 16 KiB of an attempt's log, or None if it cannot be read."""
    try:
        with open(log, "rb") as f:
            f.seek(max(0, f.seek(0, 2) - _TAIL))
            return f.read().decode("utf-8", "replace")
    except OSError:
        return None


def last_pull(log: Path, now: float) -> str | None:
    """``pulling (12s): <the engine's latest line>`` of an image pull in an attempt's log.

    None when its last 16 KiB hold no pull line. The time counts from the first pull line
    there (a pull's first lines are few and short).
    """
    lines = [line for line in (_tail(log) or "").splitlines() if _PULL in line]
    if not lines:
        return None
    try:
        since = float(lines[0].split("\t", 1)[0])
    except ValueError:
        since = now
    return f"pulling ({max(0.0, now - since):.0f}s): {lines[-1].split(_PULL, 1)[1]}"


def last_progress(log: Path) -> str | None:
    """The latest ``[osmo:progress] ...`` text in the last 16 KiB of an attempt's log."""
    from osmo.tasktypes.api import PROGRESS_PREFIX

    tail = _tail(log)
    if tail is None:
        return None
    for line in reversed(tail.splitlines()):
        at = line.find(PROGRESS_PREFIX)
        if at >= 0:
            return line[at + len(PROGRESS_PREFIX):].strip() or None
    return None


@dataclass(frozen=True)
class LogFilter:
    """Which records a reader wants: of one task, one retry, one stream, since a time."""

    task: str | None = None
    retry: int | None = None
    stream: str | None = None
    since: float | None = None

    def keeps(self, ts: float, stream: str) -> bool:
        """Whether a record at ``ts`` on ``stream`` (of a matching attempt) is wanted."""
        return ((self.stream is None or stream == self.stream)
                and (self.since is None or ts >= self.since))

    def keeps_event(self, event: dict[str, Any]) -> bool:
        """Whether a status transition is wanted (a workflow's own are every retry's)."""
        return ((self.task is None or event["task"] == self.task)
                and (self.retry is None or event["retry"] in (self.retry, None))
                and self.keeps(event["at"], "osmo"))


def read_logs(store: Store, row: WorkflowRow, *, task: str | None = None,
              retry: int | None = None, cursor: dict[str, Any] | None = None,
              tail: int | None = None, since: float | None = None, stream: str | None = None,
              chunk: int = CHUNK) -> dict[str, Any]:
    """The next chunk of a workflow's log records after ``cursor``.

    Args:
        store: the state store.
        row: the workflow.
        task: only this task's records (and status transitions).
        retry: only this retry's records.
        since: only records at or after this time (seconds since the epoch).
        stream: only this stream's records.
        cursor: where the previous call stopped (None: from the start, or see ``tail``).
        tail: with no cursor, start at the last ``tail`` records (None or 0: all).
        chunk: bytes of log to read at most (a record is never cut).

    Returns:
        ``{"records": [{ts, task, retry, stream, text}], "cursor": {...}, "more": bool,
        "done": bool}``: ``more`` when the chunk stopped before the end of what is written
        (call again at once); ``done`` once the workflow is terminal and all was returned.
    """
    wanted = LogFilter(task, retry, stream, since)
    terminal = WorkflowStatus[row.status].terminal
    attempts = [a for a in store.attempts(row.id, task)
                if (retry is None or a.retry == retry) and a.dir]
    blocks = reused_blocks(store, row, task=task, retry=retry)
    if cursor is None:
        cursor = _start(store, row.id, attempts, wanted, tail)
        if tail:  # the last N records of what ran; a reused block is not among them
            cursor["files"].update({b.key: end_position(b.log) for b in blocks if b.log})
    files = dict(cursor.get("files", {}))
    seq = int(cursor.get("seq", 0))
    size = max(chunk // max(len(attempts) + len(blocks), 1), _MIN_WINDOW)
    windows = [(a, read_window(_log(a), int(files.get(a.id, 0)), size)) for a in attempts]
    reused = [(b, read_window(b.log, int(files.get(b.key, 0)), size) if b.log else None)
              for b in blocks]
    events = store.transitions(row.id, seq)
    cut = min([w.records[-1].ts if w.records else -math.inf
               for _, w in windows if not w.complete]
              + [b.anchor for b, w in reused if w is not None and not w.complete],
              default=math.inf)
    sources: list[list[dict[str, Any]]] = []
    more = False
    for block, window in reused:  # a block sorts at its task's reuse, its lines keep their times
        if block.anchor > cut:
            more = True
            continue
        records = [] if block.key in files or not wanted.keeps(block.anchor, "osmo") \
            else [block.header]
        if window is not None:
            more = more or not window.complete
            files[block.key] = window.end
            records += [block.record(r.ts, r.stream, r.text) for r in window.records
                        if wanted.keeps(r.ts, r.stream)]
        else:
            files[block.key] = 0
        sources.append(records)
    for attempt, window in windows:
        n = _upto(window.records, cut)
        more = more or not window.complete or n < len(window.records)
        files[attempt.id] = window.ends[n - 1] if n else (
            window.end if not window.records else files.get(attempt.id, 0))
        sources.append([{"ts": r.ts, "task": attempt.task, "retry": attempt.retry,
                         "stream": r.stream, "text": r.text}
                        for r in window.records[:n] if wanted.keeps(r.ts, r.stream)])
    n = len(events)
    while n and events[n - 1]["at"] > cut:
        n -= 1
    more = more or n < len(events)
    if n:
        seq = events[n - 1]["seq"]
    sources.append([_event_record(e) for e in events[:n] if wanted.keeps_event(e)])
    records = list(heapq.merge(*sources, key=lambda r: r.get("at", r["ts"])))
    for record in records:
        record.pop("at", None)
    return {"records": records, "cursor": {"files": files, "seq": seq}, "more": more,
            "done": terminal and not more}


def iter_logs(store: Store, row: WorkflowRow, **filters: Any) -> Iterator[dict[str, Any]]:
    """Every log record written so far, chunk by chunk (``filters``: as :func:`read_logs`)."""
    cursor = None
    while True:
        reply = read_logs(store, row, cursor=cursor, **filters)
        yield from reply["records"]
        if not reply["more"]:
            return
        cursor = reply["cursor"]


def _newest(attempt: AttemptRow, wanted: LogFilter) -> Iterator[tuple[float, str, int]]:
    """``(time, attempt id, position)`` of an attempt's wanted records, newest first."""
    for record, at in newest_first(_log(attempt)):
        if wanted.since is not None and record.ts < wanted.since:
            return
        if wanted.keeps(record.ts, record.stream):
            yield record.ts, attempt.id, at


def _log(attempt: AttemptRow) -> Path:
    return AttemptDirs(Path(attempt.dir or "")).log


def _upto(records: list[Any], cut: float) -> int:
    """How many of ``records`` to return: up to the last one written at or before ``cut``."""
    n = len(records)
    while n and records[n - 1].ts > cut:
        n -= 1
    return n


def _event_record(event: dict[str, Any]) -> dict[str, Any]:
    text = event["status"] + (f": {event['message']}" if event["message"] else "")
    return {"ts": event["at"], "task": event["task"], "retry": event["retry"],
            "stream": "osmo", "text": text}


def _start(store: Store, workflow_id: str, attempts: list[AttemptRow], wanted: LogFilter,
           tail: int | None) -> dict[str, Any]:
    """The first cursor: at ``wanted.since`` (or the start), then back to the last ``tail``.

    Going back merges every log read from its end with the status transitions, newest first.
    """
    since = wanted.since
    files = {a.id: position_at(_log(a), since) if since is not None else 0 for a in attempts}
    if not tail:
        return {"files": files, "seq": 0}
    events = [e for e in store.transitions(workflow_id) if wanted.keeps_event(e)]
    newest: list[Iterable[tuple[float, str, int]]] = [
        ((e["at"], "", e["seq"] - 1) for e in reversed(events))]
    newest += [_newest(a, wanted) for a in attempts]
    starts: dict[str, int] = {}
    for _, source, at in itertools.islice(
            heapq.merge(*newest, key=lambda item: item[0], reverse=True), tail):
        starts[source] = at  # each source's oldest record kept so far
    files = {a.id: starts[a.id] if a.id in starts else end_position(_log(a)) for a in attempts}
    seq = starts.get("", events[-1]["seq"] if events else 0)
    return {"files": files, "seq": seq}
