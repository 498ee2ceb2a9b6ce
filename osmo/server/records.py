"""Writes each finished workflow's MCAP run record: status events, lineage and logs.

The record lands at ``OSMO_HOME/runs/<workflow_id>/run.mcap`` and opens in Foxglove and
rerun. It is written on a background thread after the workflow's end is committed: a record
that fails to write is logged and never fails the workflow (the store stays the source of
truth, and ``osmo`` can write it again).
"""

from __future__ import annotations

import logging
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

from osmo.errors import OsmoError
from osmo.layout import Home
from osmo.record import Lineage, write_run_record
from osmo.server.logview import iter_logs
from osmo.store.sqlite import Store

__all__ = ["RunRecords", "write_record"]

log = logging.getLogger("osmo.server")


def write_record(store: Store, home: Home, workflow_id: str) -> Path | None:
    """Write the run record of a workflow from the store; returns its path (None: unknown)."""
    row = store.workflow(workflow_id, with_spec=False)
    if row is None:
        return None
    workflow = dict(row.state) or {"id": row.id, "name": row.name, "status": row.status}
    logs = (r for r in iter_logs(store, row) if r["stream"] != "osmo")  # in time order
    lineage = [Lineage.from_dict(d) for d in store.lineage_of_workflow(workflow_id)]
    path = home.run_record(workflow_id)
    write_run_record(path, workflow=workflow, transitions=store.transitions(workflow_id),
                     lineage=lineage, logs=logs, ordered=True)
    return path


class RunRecords:
    """Writes run records one at a time on a background thread."""

    def __init__(self, store: Store, home: Home) -> None:
        self._store = store
        self._home = home
        self._pool = ThreadPoolExecutor(1, thread_name_prefix="osmo-record")

    def finished(self, workflow_id: str) -> None:
        """Queue the record of a workflow that just ended."""
        self._pool.submit(self._write, workflow_id)

    def _write(self, workflow_id: str) -> None:
        try:
            write_record(self._store, self._home, workflow_id)
        except OsmoError as exc:
            log.warning("run record of %s not written: %s", workflow_id, exc)
        except Exception:  # noqa: BLE001 - a record must never take the server down
            log.exception("run record of %s not written", workflow_id)

    def close(self) -> None:
        """Finish queued records."""
        self._pool.shutdown(wait=True)
