"""The logs a reused task shows: those of the attempt whose outputs it took.

A task completed from the cache (``osmo.server.cache``) or reused by ``osmo restart`` ran no
process, so it has no log of its own. ``osmo logs`` shows in its place the log of the attempt
that made its outputs (the attempt whose own output folder the task's output is), under a
header line naming that attempt's workflow, task and retry. The block sits where the task
was reused (at its end time), its lines keeping their own, earlier, times.

A :class:`ReusedBlock` is one such block: ``osmo.server.logview`` reads its log a bounded
window at a time, like any attempt's, and sorts its lines at the block's ``anchor``. A
producer whose log is gone (an unrecorded attempt) leaves the header alone, saying so.
Writes nothing.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

from osmo.layout import AttemptDirs
from osmo.store.sqlite import Store, WorkflowRow

__all__ = ["ReusedBlock", "reused_blocks"]


@dataclass(frozen=True)
class ReusedBlock:
    """One reused task's block: where it sorts, its header, the log it shows.

    Attributes:
        key: its entry in a log reader's cursor (``reused:<task>``).
        task, retry: the reused task.
        anchor: when it was reused (its lines sort here).
        text: the header line.
        log: the producer's log (None: not recorded here).
    """

    key: str
    task: str
    retry: int
    anchor: float
    text: str
    log: Path | None

    def record(self, ts: float, stream: str, text: str) -> dict[str, Any]:
        """A record of this block (``at``: where it sorts; the reader drops it)."""
        return {"ts": ts, "task": self.task, "retry": self.retry, "stream": stream,
                "text": text, "at": self.anchor}

    @property
    def header(self) -> dict[str, Any]:
        """The header record."""
        return self.record(self.anchor, "osmo", self.text)


def reused_blocks(store: Store, row: WorkflowRow, *, task: str | None,
                  retry: int | None) -> list[ReusedBlock]:
    """The blocks of ``row``'s reused tasks (only ``task`` / ``retry`` if given)."""
    blocks = []
    for state in store.tasks(row.id):
        name = str(state.get("name"))
        if (not state.get("reused") or not state.get("output")
                or task is not None and name != task
                or retry is not None and state.get("retry") != retry):
            continue
        blocks.append(_block(store, state))
    return blocks


def _block(store: Store, state: dict[str, Any]) -> ReusedBlock:
    name, retry = str(state["name"]), int(state.get("retry") or 0)
    anchor = float(state.get("ended_at") or state.get("created_at") or 0.0)
    producer = _producer(store, str(state["output"]))
    if producer is None:
        return ReusedBlock(f"reused:{name}", name, retry, anchor,
                           "reused: the outputs of an earlier run; the log of the attempt "
                           "that made them is not recorded here", None)
    log = AttemptDirs(Path(producer["dir"])).log
    header = (f"reused: the log of {producer['workflow_id']} task {producer['task']} retry "
              f"{producer['retry']} follows; this task did not run")
    if not log.exists():
        header = header.replace(" follows", " (none was kept)")
    return ReusedBlock(f"reused:{name}", name, retry, anchor, header, log)


def _producer(store: Store, output: str) -> dict[str, Any] | None:
    """The attempt whose own output folder is ``output`` (workflow_id, task, retry, dir...)."""
    for found in store.output_makers(output):
        if found["dir"] and AttemptDirs(Path(found["dir"])).output == Path(output):
            return found
    return None
