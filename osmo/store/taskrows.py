"""Read queries over one workflow's task rows that do not decode every row.

For big workflows (``osmo query`` of a 100,000-task fan-out): the count per status, every
task's name and status, and the full state of only the tasks asked for. A mixin of
``osmo.store.sqlite.Store`` (which owns the connection); must not import sqlite3.
"""

from __future__ import annotations

import json
from collections.abc import Sequence
from typing import Any

__all__ = ["TaskQueries"]

_CHUNK = 500  # names per IN (...) query: well under SQLite's bound-parameter limit


class TaskQueries:
    """Queries that need only ``self._read(sql, args) -> rows``."""

    def _read(self, sql: str, args: tuple[Any, ...] = ()) -> list[Any]:
        raise NotImplementedError

    def task_counts(self, workflow_id: str) -> dict[str, int]:
        """Status → how many of the workflow's tasks have it."""
        rows = self._read("SELECT status, COUNT(*) FROM tasks WHERE workflow_id = ? "
                          "GROUP BY status", (workflow_id,))
        return {str(r[0]): int(r[1]) for r in rows}

    def task_names(self, workflow_id: str, statuses: Sequence[str]) -> set[str]:
        """Names of the workflow's tasks whose status is one of ``statuses``."""
        marks = ",".join("?" * len(statuses))
        rows = self._read(f"SELECT name FROM tasks WHERE workflow_id = ? AND status IN "
                          f"({marks})", (workflow_id, *statuses))
        return {str(r[0]) for r in rows}

    def tasks_named(self, workflow_id: str, names: Sequence[str]) -> list[dict[str, Any]]:
        """State payloads of the named tasks of the workflow (unordered; unknown names skipped)."""
        out: list[dict[str, Any]] = []
        for i in range(0, len(names), _CHUNK):
            chunk = tuple(names[i:i + _CHUNK])
            marks = ",".join("?" * len(chunk))
            rows = self._read(f"SELECT state FROM tasks WHERE workflow_id = ? AND name IN "
                              f"({marks})", (workflow_id, *chunk))
            out += [json.loads(r[0]) for r in rows]
        return out
