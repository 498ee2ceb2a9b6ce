"""The logs a reused task shows: those of the attempt whose outputs it took.

A task completed from the cache (``osmo.server.cache``) or reused by ``osmo restart`` ran no
process, so it has no log of its own. ``osmo logs`` shows in its place the log of the attempt
that made its outputs (the attempt whose own output folder the task's output is), under a
header line naming that attempt's workflow, task and retry. The block sits where the task
was reused (after the task's last line up to its end time), its lines keeping their own,
earlier, times.

Read by ``osmo.server.logview``; writes nothing. A producer whose log is gone (an
unrecorded attempt) leaves the header alone, saying so.
"""

from __future__ import annotations

import bisect
from pathlib import Path
from typing import Any

from osmo.layout import AttemptDirs
from osmo.store.sqlite import Store, WorkflowRow
from osmo.worker.logs import read_log

__all__ = ["with_reused"]

_SEEN = "reused:"  # cursor key prefix: a reused task's block is sent once


def with_reused(store: Store, row: WorkflowRow, records: list[dict[str, Any]], *,
                task: str | None, retry: int | None,
                cursor: dict[str, Any]) -> list[dict[str, Any]]:
    """``records`` (sorted by time) with the reused logs of ``row``'s reused tasks merged in.

    Only tasks matching ``task``/``retry``, and only those ``cursor`` has not seen; each one
    sent is marked in ``cursor["files"]``.
    """
    blocks: dict[str, tuple[float, list[dict[str, Any]]]] = {}
    for state in store.tasks(row.id):
        name = str(state.get("name"))
        if (not state.get("reused") or not state.get("output") or
                task is not None and name != task or
                retry is not None and state.get("retry") != retry or
                f"{_SEEN}{name}" in cursor["files"]):
            continue
        cursor["files"][f"{_SEEN}{name}"] = 1
        blocks[name] = _block(store, state)
    if not blocks:
        return records
    after: dict[str, int] = {}  # task → index of its last record up to its reuse
    for i, r in enumerate(records):
        if r["task"] in blocks and r["ts"] <= blocks[r["task"]][0]:
            after[r["task"]] = i + 1
    times = [r["ts"] for r in records]
    places = sorted(((after.get(name) or bisect.bisect_right(times, anchor), block)
                     for name, (anchor, block) in blocks.items()), key=lambda p: p[0])
    for at, block in reversed(places):  # the last first: the earlier positions stay true
        records[at:at] = block
    return records


def _block(store: Store, state: dict[str, Any]) -> tuple[float, list[dict[str, Any]]]:
    """``(when the task was reused, [header, the producer's records...])``."""
    anchor = float(state.get("ended_at") or state.get("created_at") or 0.0)

    def record(ts: float, stream: str, text: str) -> dict[str, Any]:
        return {"ts": ts, "task": state["name"], "retry": state.get("retry", 0),
                "stream": stream, "text": text}

    producer = _producer(store, str(state["output"]))
    if producer is None:
        return anchor, [record(anchor, "osmo", "reused: the outputs of an earlier run; "
                                               "the log of the attempt that made them is not "
                                               "recorded here")]
    lines, _ = read_log(AttemptDirs(Path(producer["dir"])).log)
    header = (f"reused: the log of {producer['workflow_id']} task {producer['task']} retry "
              f"{producer['retry']} follows; this task did not run")
    if not lines:
        header = header.replace(" follows", " (none was kept)")
    return anchor, [record(anchor, "osmo", header),
                    *(record(r.ts, r.stream, r.text) for r in lines)]


def _producer(store: Store, output: str) -> dict[str, Any] | None:
    """The attempt whose own output folder is ``output`` (workflow_id, task, retry, dir...)."""
    for found in store.output_makers(output):
        if found["dir"] and AttemptDirs(Path(found["dir"])).output == Path(output):
            return found
    return None
