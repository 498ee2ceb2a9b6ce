r"""How the store writes rows that carry task-chosen text: outputs, lineage, dataset versions.

Text from tasks may hold bytes that are not UTF-8 (see ``osmo.artifacts.manifest`` for the
one rule on file names). SQLite only takes valid UTF-8 text, so a file name that is not
valid UTF-8 is stored as a ``BLOB`` of its exact bytes (:func:`name_value`; ``CAST(path AS
BLOB)`` gives the bytes of either form), and a message has such bytes shown as ``\xNN``
(:func:`text_value`). ``osmo.store.sqlite`` calls these inside its transactions; this
module does not import ``sqlite3`` (it only needs a connection's ``execute``).
"""

from __future__ import annotations

import json
from collections.abc import Iterable
from typing import Any, Protocol

from osmo.store.rows import DatasetRow, LineageRow

__all__ = ["name_value", "text_value", "write_dataset", "write_lineage", "write_manifest"]


class _Db(Protocol):
    """The part of a ``sqlite3.Connection`` these writes use."""

    def execute(self, sql: str, args: tuple[Any, ...] = ..., /) -> Any: ...
    def executemany(self, sql: str, rows: Iterable[tuple[Any, ...]], /) -> Any: ...


def write_lineage(db: _Db, row: LineageRow) -> None:
    """Record a completed attempt's manifest, output folder, lineage, inputs and cache key."""
    write_manifest(db, row.manifest, row.manifest_body, row.entries)
    db.execute("INSERT OR REPLACE INTO outputs VALUES (?,?,?,?,?)",
               (row.workflow_id, row.task, row.attempt_id, row.manifest, row.output_path))
    db.execute("INSERT OR REPLACE INTO lineage VALUES (?,?,?,?,?)",
               (row.attempt_id, row.workflow_id, row.task, row.manifest, row.record))
    db.executemany("INSERT OR IGNORE INTO consumed VALUES (?,?)",
                   [(m, row.attempt_id) for m in row.consumed])
    if row.fingerprint is not None:
        db.execute("INSERT OR IGNORE INTO cache VALUES (?,?,?,?,?,?)",
                   (row.fingerprint, row.attempt_id, row.workflow_id, row.task,
                    row.output_path, row.manifest))


def write_dataset(db: _Db, ds: DatasetRow) -> None:
    """Record a new dataset version and its manifest."""
    write_manifest(db, ds.manifest, ds.manifest_body, ds.entries)
    db.execute("INSERT INTO datasets VALUES (?,?,?,?,?,?,?)",
               (ds.name, ds.version, ds.manifest, ds.source_manifest, ds.attempt_id,
                ds.created_at, json.dumps(ds.metadata)))


def write_manifest(db: _Db, digest: str, body: str,
                   entries: tuple[tuple[str, str, int], ...]) -> None:
    """Record a manifest and which blob each of its names holds (kept if already there)."""
    db.execute("INSERT OR IGNORE INTO manifests VALUES (?,?)", (digest, body))
    db.executemany("INSERT OR IGNORE INTO manifest_blobs VALUES (?,?,?,?)",
                   [(digest, name_value(path), blob, size) for path, blob, size in entries])


def name_value(path: str) -> str | bytes:
    """A file name as SQLite keeps it: TEXT when valid UTF-8, else a BLOB of its bytes."""
    try:
        path.encode("utf-8")
    except UnicodeEncodeError:
        return path.encode("utf-8", "surrogateescape")
    return path


def text_value(message: str) -> str:
    r"""A message as valid UTF-8 text: bytes that are not UTF-8 shown as ``\xNN``."""
    try:
        message.encode("utf-8")
    except UnicodeEncodeError:
        pass
    try:
        raw = message.encode("utf-8", "surrogateescape")
    except UnicodeEncodeError:  # a surrogate that stands for no byte
        return message.encode("utf-8", "backslashreplace").decode("utf-8")
    return raw.decode("utf-8", "backslashreplace")
