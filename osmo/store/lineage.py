"""Read queries over artifacts and lineage: outputs, manifests, producers and consumers.

A mixin of ``osmo.store.sqlite.Store`` (which owns the connection and the writes); kept
apart so the store module stays small. Must not import sqlite3.
"""

from __future__ import annotations

import json
from typing import Any, cast

__all__ = ["LineageQueries"]


class LineageQueries:
    """Queries that need only ``self._read(sql, args) -> rows``."""

    def _read(self, sql: str, args: tuple[Any, ...] = ()) -> list[Any]:
        raise NotImplementedError

    def output_of(self, path: str) -> tuple[str, str] | None:
        """``(manifest digest, workflow id)`` of the output folder ``path``, or None."""
        rows = self._read("SELECT manifest, workflow_id FROM outputs WHERE path = ? LIMIT 1",
                          (path,))
        return (str(rows[0][0]), str(rows[0][1])) if rows else None

    def output_makers(self, path: str) -> list[dict[str, Any]]:
        """Attempts recorded with the output folder ``path``: its maker and those that reused it.

        Each as workflow_id, task, attempt_id, retry and dir (the attempt's folder).
        """
        rows = self._read("SELECT o.workflow_id, o.task, o.attempt_id, a.retry, a.dir "
                          "FROM outputs o JOIN attempts a ON a.id = o.attempt_id "
                          "WHERE o.path = ?", (path,))
        return [dict(r) for r in rows]

    def lineage_of_workflow(self, workflow_id: str) -> list[dict[str, Any]]:
        """Lineage records (JSON payloads) of a workflow's attempts, in commit order."""
        rows = self._read("SELECT record FROM lineage WHERE workflow_id = ? ORDER BY rowid",
                          (workflow_id,))
        return [json.loads(r[0]) for r in rows]

    def cached(self, fingerprint: str) -> dict[str, Any] | None:
        """The cache entry for ``fingerprint`` (attempt_id, output_path, manifest), or None."""
        rows = self._read("SELECT * FROM cache WHERE fingerprint = ?", (fingerprint,))
        return dict(rows[0]) if rows else None

    def next_dataset_version(self, name: str) -> int:
        """1 + the highest version of dataset ``name``."""
        rows = self._read("SELECT MAX(version) FROM datasets WHERE name = ?", (name,))
        return int(rows[0][0] or 0) + 1

    def dataset(self, name: str, tag_or_version: str | None = None) -> dict[str, Any] | None:
        """One version of a dataset: a number, a tag, or None/``latest`` for the newest."""
        version: int | None = None
        if tag_or_version and tag_or_version.isdigit():
            version = int(tag_or_version)
        elif tag_or_version and tag_or_version != "latest":
            rows = self._read("SELECT version FROM dataset_tags WHERE name = ? AND tag = ?",
                              (name, tag_or_version))
            if not rows:
                return None
            version = int(rows[0][0])
        if version is None:
            rows = self._read("SELECT * FROM datasets WHERE name = ? "
                              "ORDER BY version DESC LIMIT 1", (name,))
        else:
            rows = self._read("SELECT * FROM datasets WHERE name = ? AND version = ?",
                              (name, version))
        return _dataset_dict(self, rows[0]) if rows else None

    def datasets(self, name: str | None = None) -> list[dict[str, Any]]:
        """Every dataset version (of one dataset), newest first."""
        sql, args = "SELECT * FROM datasets", cast(tuple[Any, ...], ())
        if name is not None:
            sql, args = sql + " WHERE name = ?", (name,)
        rows = self._read(sql + " ORDER BY name, version DESC", args)
        return [_dataset_dict(self, r) for r in rows]

    def dataset_of_manifest(self, manifest: str) -> dict[str, Any] | None:
        """The first dataset version whose manifest is ``manifest``."""
        rows = self._read("SELECT * FROM datasets WHERE manifest = ? ORDER BY rowid LIMIT 1",
                          (manifest,))
        return _dataset_dict(self, rows[0]) if rows else None

    def outputs(self, workflow_id: str, task: str | None = None) -> list[dict[str, Any]]:
        """Promoted outputs of a workflow: task, attempt_id, manifest, path."""
        sql, args = "SELECT * FROM outputs WHERE workflow_id = ?", [workflow_id]
        if task is not None:
            sql += " AND task = ?"
            args.append(task)
        return [dict(r) for r in self._read(sql + " ORDER BY rowid", tuple(args))]

    def manifest_body(self, digest: str) -> str | None:
        """The JSON of manifest ``digest``."""
        rows = self._read("SELECT body FROM manifests WHERE digest = ?", (digest,))
        return str(rows[0][0]) if rows else None

    def manifests_holding(self, blob: str) -> list[str]:
        """Manifests that contain blob ``blob``."""
        rows = self._read("SELECT DISTINCT manifest FROM manifest_blobs WHERE digest = ?", (blob,))
        return [str(r[0]) for r in rows]

    def lineage_of_manifest(self, manifest: str) -> list[dict[str, Any]]:
        """Lineage records (JSON payloads) of the attempts that produced ``manifest``."""
        rows = self._read("SELECT record FROM lineage WHERE manifest = ? ORDER BY rowid",
                          (manifest,))
        return [json.loads(r[0]) for r in rows]

    def consumers_of(self, manifest: str) -> list[dict[str, Any]]:
        """Lineage records of the attempts that read ``manifest`` as an input."""
        rows = self._read(
            "SELECT l.record FROM consumed c JOIN lineage l ON l.attempt_id = c.attempt_id "
            "WHERE c.manifest = ? ORDER BY l.rowid", (manifest,))
        return [json.loads(r[0]) for r in rows]

    def all_blob_digests(self) -> set[str]:
        """Every blob digest any recorded manifest references (for garbage collection)."""
        return {str(r[0]) for r in self._read("SELECT DISTINCT digest FROM manifest_blobs")}


def _dataset_dict(store: LineageQueries, row: Any) -> dict[str, Any]:
    out = dict(row)
    out["metadata"] = json.loads(out["metadata"])
    tags = store._read("SELECT tag FROM dataset_tags WHERE name = ? AND version = ?",
                       (out["name"], out["version"]))
    out["tags"] = sorted(str(t[0]) for t in tags)
    return out
