"""Merges a workflow's attempt logs and its status transitions into one time-ordered stream.

A cursor (attempt id → byte offset, plus the last event-log sequence number) lets a client
follow the stream: each call returns only what is new since the cursor.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from osmo.layout import AttemptDirs
from osmo.server.reused_logs import with_reused
from osmo.status import WorkflowStatus
from osmo.store.sqlite import Store, WorkflowRow
from osmo.worker.logs import read_log

__all__ = ["last_progress", "last_pull", "read_logs"]

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


def read_logs(store: Store, row: WorkflowRow, *, task: str | None = None,
              retry: int | None = None, cursor: dict[str, Any] | None = None) -> dict[str, Any]:
    """New log records of a workflow since ``cursor``.

    Returns:
        ``{"records": [{ts, task, retry, stream, text}], "cursor": {...}, "done": bool}``;
        ``done`` is true once the workflow is terminal and everything was returned.
    """
    cursor = {"files": dict((cursor or {}).get("files", {})), "seq": (cursor or {}).get("seq", 0)}
    terminal = WorkflowStatus[row.status].terminal
    records: list[dict[str, Any]] = []
    for attempt in store.attempts(row.id, task):
        if retry is not None and attempt.retry != retry or not attempt.dir:
            continue
        offset = int(cursor["files"].get(attempt.id, 0))
        lines, new_offset = read_log(AttemptDirs(Path(attempt.dir)).log, offset)
        cursor["files"][attempt.id] = new_offset
        records += [{"ts": r.ts, "task": attempt.task, "retry": attempt.retry,
                     "stream": r.stream, "text": r.text} for r in lines]
    for event in store.transitions(row.id, cursor["seq"]):
        cursor["seq"] = event["seq"]
        if task is not None and event["task"] != task:
            continue
        if retry is not None and event["retry"] not in (retry, None):
            continue
        text = event["status"] + (f": {event['message']}" if event["message"] else "")
        records.append({"ts": event["at"], "task": event["task"], "retry": event["retry"],
                        "stream": "osmo", "text": text})
    records.sort(key=lambda r: r["ts"])
    records = with_reused(store, row, records, task=task, retry=retry, cursor=cursor)
    return {"records": records, "cursor": cursor, "done": terminal}
