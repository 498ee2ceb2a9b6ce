"""Durable state in one SQLite file (WAL): workflows, tasks, attempts and the event log.

The only module that imports ``sqlite3``; its errors become ``InfrastructureError``.

Rows hold JSON payloads (``state``) beside the few columns that queries filter on, so the
schema stays small and inspectable with the ``sqlite3`` shell. No pickle. One writer (the
server's engine thread) commits each batch of scheduler changes in one transaction *before*
the matching commands are executed; readers (API threads) use their own connections.

Schema migrations are forward-only functions keyed by version in ``_MIGRATIONS``.

Text from tasks may hold bytes that are not UTF-8 (file names): see ``osmo.store.writes``.
"""

from __future__ import annotations

import json
import os
import sqlite3
import threading
from collections.abc import Callable, Iterator, Mapping, Sequence
from contextlib import contextmanager
from pathlib import Path
from typing import Any

from osmo.config import private_file
from osmo.errors import InfrastructureError
from osmo.scheduler.types import Changes
from osmo.store.instances import InstanceRows
from osmo.store.lineage import LineageQueries
from osmo.store.rows import (
    AttemptRow,
    DatasetRow,
    LineageRow,
    NewWorkflowRow,
    TagRow,
    WorkflowRow,
)
from osmo.store.submission import from_columns, options_column
from osmo.store.taskjson import task_rows
from osmo.store.taskrows import TaskQueries
from osmo.store.tokens import TokenRows
from osmo.store.writes import text_value, write_dataset, write_lineage, write_manifest

__all__ = ["AttemptRow", "DatasetRow", "LineageRow", "NewWorkflowRow", "Store", "TagRow",
           "WorkflowRow"]


def _v1(db: sqlite3.Connection) -> None:
    _run_script(
        db,
        """
        CREATE TABLE workflows (
            id TEXT PRIMARY KEY, name TEXT NOT NULL, n INTEGER NOT NULL,
            status TEXT NOT NULL, submitted_at REAL NOT NULL,
            spec TEXT NOT NULL, options TEXT NOT NULL, state TEXT NOT NULL,
            UNIQUE(name, n));
        CREATE INDEX workflows_status ON workflows(status);
        CREATE TABLE tasks (
            workflow_id TEXT NOT NULL, name TEXT NOT NULL, status TEXT NOT NULL,
            state TEXT NOT NULL, PRIMARY KEY (workflow_id, name));
        CREATE TABLE attempts (
            id TEXT PRIMARY KEY, workflow_id TEXT NOT NULL, task TEXT NOT NULL,
            retry INTEGER NOT NULL, node_id TEXT, dir TEXT, pid INTEGER, pid_start REAL);
        CREATE INDEX attempts_task ON attempts(workflow_id, task);
        CREATE TABLE events (
            seq INTEGER PRIMARY KEY AUTOINCREMENT, at REAL NOT NULL, workflow_id TEXT NOT NULL,
            task TEXT, retry INTEGER, status TEXT NOT NULL, message TEXT NOT NULL);
        CREATE INDEX events_workflow ON events(workflow_id, seq);
        """
    )


def _v2(db: sqlite3.Connection) -> None:
    """Artifacts and lineage: manifests, which blobs they hold, who made and used them."""
    _run_script(
        db,
        """
        CREATE TABLE manifests (digest TEXT PRIMARY KEY, body TEXT NOT NULL);
        CREATE TABLE manifest_blobs (
            manifest TEXT NOT NULL, path TEXT NOT NULL, digest TEXT NOT NULL, size INTEGER,
            PRIMARY KEY (manifest, path));
        CREATE INDEX manifest_blobs_digest ON manifest_blobs(digest);
        CREATE TABLE outputs (
            workflow_id TEXT NOT NULL, task TEXT NOT NULL, attempt_id TEXT NOT NULL,
            manifest TEXT NOT NULL, path TEXT NOT NULL, PRIMARY KEY (workflow_id, task));
        CREATE INDEX outputs_manifest ON outputs(manifest);
        CREATE INDEX outputs_path ON outputs(path);
        CREATE TABLE lineage (
            attempt_id TEXT PRIMARY KEY, workflow_id TEXT NOT NULL, task TEXT NOT NULL,
            manifest TEXT, record TEXT NOT NULL);
        CREATE INDEX lineage_manifest ON lineage(manifest);
        CREATE TABLE consumed (
            manifest TEXT NOT NULL, attempt_id TEXT NOT NULL, PRIMARY KEY (manifest, attempt_id));
        """,
    )


def _v3(db: sqlite3.Connection) -> None:
    """Task cache: fingerprint → the first successful attempt that had it."""
    db.execute(
        "CREATE TABLE cache (fingerprint TEXT PRIMARY KEY, attempt_id TEXT NOT NULL, "
        "workflow_id TEXT NOT NULL, task TEXT NOT NULL, output_path TEXT NOT NULL, "
        "manifest TEXT NOT NULL)")


def _v4(db: sqlite3.Connection) -> None:
    """Datasets: named, versioned manifests with tags, linked to what made them."""
    _run_script(
        db,
        """
        CREATE TABLE datasets (
            name TEXT NOT NULL, version INTEGER NOT NULL, manifest TEXT NOT NULL,
            source_manifest TEXT, attempt_id TEXT, created_at REAL NOT NULL,
            metadata TEXT NOT NULL, PRIMARY KEY (name, version));
        CREATE INDEX datasets_manifest ON datasets(manifest);
        CREATE TABLE dataset_tags (
            name TEXT NOT NULL, tag TEXT NOT NULL, version INTEGER NOT NULL,
            PRIMARY KEY (name, tag));
        """,
    )


def _v5(db: sqlite3.Connection) -> None:
    """Credentials: named secrets (key → value) used for data URLs."""
    db.execute("CREATE TABLE credentials (name TEXT PRIMARY KEY, payload TEXT NOT NULL, "
               "updated_at REAL NOT NULL)")


def _v6(db: sqlite3.Connection) -> None:
    """API tokens (``osmo.store.tokens``): only each token's sha256 is kept."""
    db.execute("CREATE TABLE tokens (name TEXT PRIMARY KEY, role TEXT NOT NULL, "
               "digest TEXT NOT NULL UNIQUE, created_at REAL NOT NULL, revoked_at REAL)")


def _v7(db: sqlite3.Connection) -> None:
    """The pools a worker token may serve (a JSON list; ``["*"]``: every pool).

    Worker tokens made before pools were bound serve every pool, as they did.
    """
    db.execute("ALTER TABLE tokens ADD COLUMN pools TEXT")
    db.execute("""UPDATE tokens SET pools = '["*"]' WHERE role = 'worker'""")


def _v8(db: sqlite3.Connection) -> None:
    """Cluster nodes' instance labels, and the instances of nodes down for good to sweep."""
    _run_script(
        db,
        """
        CREATE TABLE node_instances (
            node TEXT PRIMARY KEY, pool TEXT NOT NULL, instance TEXT NOT NULL);
        CREATE TABLE sweeps (
            pool TEXT NOT NULL, instance TEXT NOT NULL, PRIMARY KEY (pool, instance));
        """,
    )


def _run_script(db: sqlite3.Connection, script: str) -> None:
    """Run ``;``-separated DDL inside the caller's transaction (``executescript`` would commit)."""
    for statement in script.split(";"):
        if statement.strip():
            db.execute(statement)


_NO_SPEC = "id, name, status, submitted_at, '{}' AS spec, options, state"

_MIGRATIONS: dict[int, Callable[[sqlite3.Connection], None]] = {
    1: _v1, 2: _v2, 3: _v3, 4: _v4, 5: _v5, 6: _v6, 7: _v7, 8: _v8}
SCHEMA_VERSION = max(_MIGRATIONS)


class Store(LineageQueries, TaskQueries, TokenRows, InstanceRows):
    """The SQLite state store under ``OSMO_HOME``.

    Args:
        path: the database file; created (with parents) and migrated on open.
    """

    def __init__(self, path: Path) -> None:
        self.path = Path(path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        # The store holds credentials and token digests: its owner's only. SQLite gives the
        # -wal and -shm files the database file's mode.
        os.close(os.open(self.path, os.O_RDWR | os.O_CREAT | os.O_CLOEXEC, 0o600))
        for suffix in ("", "-wal", "-shm"):
            private_file(self.path.with_name(self.path.name + suffix))
        self._local = threading.local()
        with self._tx() as db:
            self._migrate(db)

    # -------------------------------------------------------------- connection plumbing

    def _db(self) -> sqlite3.Connection:
        db: sqlite3.Connection | None = getattr(self._local, "db", None)
        if db is None:
            try:
                db = sqlite3.connect(self.path, timeout=30, isolation_level=None)
                db.execute("PRAGMA journal_mode=WAL")
                # NORMAL in WAL mode survives a process crash (kill -9); only power loss can
                # lose the last commits, which is the usual trade for orchestrator state.
                db.execute("PRAGMA synchronous=NORMAL")
            except sqlite3.Error as exc:
                raise InfrastructureError(f"cannot open state store {self.path}: {exc}") from exc
            self._local.db = db
        return db

    @contextmanager
    def _tx(self) -> Iterator[sqlite3.Connection]:
        db = self._db()
        try:
            db.execute("BEGIN IMMEDIATE")
            yield db
            db.execute("COMMIT")
        except sqlite3.Error as exc:
            db.execute("ROLLBACK") if db.in_transaction else None
            raise InfrastructureError(f"state store {self.path}: {exc}") from exc
        except BaseException:
            if db.in_transaction:
                db.execute("ROLLBACK")
            raise

    def _read(self, sql: str, args: tuple[Any, ...] = ()) -> list[sqlite3.Row]:
        db = self._db()
        db.row_factory = sqlite3.Row
        try:
            return db.execute(sql, args).fetchall()
        except sqlite3.Error as exc:
            raise InfrastructureError(f"state store {self.path}: {exc}") from exc

    def _migrate(self, db: sqlite3.Connection) -> None:
        db.execute("CREATE TABLE IF NOT EXISTS schema_version (version INTEGER NOT NULL)")
        row = db.execute("SELECT version FROM schema_version").fetchone()
        current = row[0] if row else 0
        if current > SCHEMA_VERSION:
            raise InfrastructureError(
                f"state store {self.path} has schema {current}, newer than this osmo "
                f"({SCHEMA_VERSION}); upgrade osmo"
            )
        for version in range(current + 1, SCHEMA_VERSION + 1):
            _MIGRATIONS[version](db)
        if row is None:
            db.execute("INSERT INTO schema_version VALUES (?)", (SCHEMA_VERSION,))
        else:
            db.execute("UPDATE schema_version SET version = ?", (SCHEMA_VERSION,))

    def close(self) -> None:
        """Close this thread's connection."""
        db = getattr(self._local, "db", None)
        if db is not None:
            db.close()
            self._local.db = None

    # -------------------------------------------------------------- writes (engine thread)

    def next_number(self, name: str) -> int:
        """1 + the highest N used by a workflow called ``name`` (the id is ``name-N``)."""
        rows = self._read("SELECT MAX(n) FROM workflows WHERE name = ?", (name,))
        return int(rows[0][0] or 0) + 1

    def commit(
        self,
        changes: Changes,
        *,
        new_workflows: Sequence[NewWorkflowRow] = (),
        attempts: Sequence[AttemptRow] = (),
        lineage: Sequence[LineageRow] = (),
        datasets: Sequence[DatasetRow] = (),
        tags: Sequence[TagRow] = (),
        pids: Sequence[tuple[str, int, float | None]] = (),
        workflow_tags: Mapping[str, Sequence[str]] | None = None,
    ) -> None:
        """Write one batch atomically.

        Args:
            changes: scheduler snapshots and transitions.
            new_workflows: workflows to create.
            attempts: attempt rows to insert or replace (placement, pid).
            lineage: outputs and lineage of attempts that completed in this batch.
            datasets: new dataset versions.
            tags: dataset tags to (re)point.
            pids: ``(attempt id, pid, pid start time)`` of attempts whose process started
                (their rows exist: written with their placement).
            workflow_tags: workflow id → its new tag list (kept in its options).
        """
        with self._tx() as db:
            for new in new_workflows:
                db.execute(
                    "INSERT INTO workflows VALUES (?,?,?,?,?,?,?,?)",
                    (new.id, new.name, new.n, "PENDING", new.submitted_at,
                     json.dumps(new.spec.data), json.dumps(options_column(new.spec, new.options)),
                     "{}"),
                )
            for wf in changes.workflows:
                state = wf.to_dict()
                db.execute(
                    "UPDATE workflows SET status = ?, state = ? WHERE id = ?",
                    (state["status"], json.dumps(state), state["id"]),
                )
            db.executemany("INSERT OR REPLACE INTO tasks VALUES (?,?,?,?)",
                           task_rows(changes.tasks))
            db.executemany(
                "INSERT INTO events (at, workflow_id, task, retry, status, message) "
                "VALUES (?,?,?,?,?,?)",
                [
                    (t.at, t.workflow_id, t.task, t.retry, t.status, text_value(t.message))
                    for t in changes.transitions
                ],
            )
            db.executemany(
                "INSERT OR REPLACE INTO attempts VALUES (?,?,?,?,?,?,?,?)",
                [
                    (a.id, a.workflow_id, a.task, a.retry, a.node_id, a.dir, a.pid, a.pid_start)
                    for a in attempts
                ],
            )
            db.executemany("UPDATE attempts SET pid = ?, pid_start = ? WHERE id = ?",
                           [(pid, start, aid) for aid, pid, start in pids])
            db.executemany("UPDATE workflows SET options = json_set(options, '$.tags', json(?)) "
                           "WHERE id = ?", [(json.dumps(list(tags)), wf)
                                            for wf, tags in (workflow_tags or {}).items()])
            for row in lineage:
                write_lineage(db, row)
            for ds in datasets:
                write_dataset(db, ds)
            db.executemany("INSERT OR REPLACE INTO dataset_tags VALUES (?,?,?)",
                           [(t.name, t.tag, t.version) for t in tags])

    def set_credential(self, name: str, payload: dict[str, str], now: float) -> None:
        """Store (or replace) credential ``name``."""
        with self._tx() as db:
            db.execute("INSERT OR REPLACE INTO credentials VALUES (?,?,?)",
                       (name, json.dumps(payload), now))

    def delete_credential(self, name: str) -> bool:
        """Remove credential ``name``; False if there was none."""
        with self._tx() as db:
            return db.execute("DELETE FROM credentials WHERE name = ?", (name,)).rowcount > 0

    def credential(self, name: str) -> dict[str, str] | None:
        """The payload of credential ``name``, or None."""
        rows = self._read("SELECT payload FROM credentials WHERE name = ?", (name,))
        return dict(json.loads(rows[0][0])) if rows else None

    def credentials(self) -> list[dict[str, Any]]:
        """Every credential's name, keys (never values) and update time."""
        rows = self._read("SELECT * FROM credentials ORDER BY name")
        return [{"name": r["name"], "keys": sorted(json.loads(r["payload"])),
                 "updated_at": r["updated_at"]} for r in rows]

    def register_output(self, workflow_id: str, task: str, manifest: str, body: str,
                        entries: tuple[tuple[str, str, int], ...], path: str) -> None:
        """Record a folder (e.g. a materialized dataset) as holding ``manifest``."""
        with self._tx() as db:
            write_manifest(db, manifest, body, entries)
            db.execute("INSERT OR REPLACE INTO outputs VALUES (?,?,?,?,?)",
                       (workflow_id, task, "", manifest, path))

    # -------------------------------------------------------------- reads (any thread)

    def workflow(self, workflow_id: str, *, with_spec: bool = True) -> WorkflowRow | None:
        """One workflow, or None. ``with_spec=False`` skips decoding the (large) spec."""
        columns = "*" if with_spec else _NO_SPEC
        rows = self._read(f"SELECT {columns} FROM workflows WHERE id = ?", (workflow_id,))
        return _workflow_row(rows[0]) if rows else None

    def workflows(
        self,
        *,
        statuses: list[str] | None = None,
        name: str | None = None,
        limit: int | None = None,
        active_only: bool = False,
        labels: Mapping[str, str] | None = None,
    ) -> list[WorkflowRow]:
        """Workflows, newest first, filtered by status names, a name substring and labels.

        ``labels``: a workflow must have every one of them (key and value). Rows come without
        their spec's data (``spec.data == {}``); use ``workflow()`` for it.
        """
        sql = f"SELECT {_NO_SPEC} FROM workflows WHERE 1=1"
        args: list[Any] = []
        if statuses:
            sql += f" AND status IN ({','.join('?' * len(statuses))})"
            args += statuses
        if active_only:
            sql += " AND status IN ('PENDING', 'RUNNING', 'WAITING')"
        if name:
            sql += " AND (name LIKE ? OR id LIKE ?)"
            args += [f"%{name}%", f"%{name}%"]
        for key, value in (labels or {}).items():
            sql += (" AND EXISTS (SELECT 1 FROM json_each(workflows.options, '$.labels') "
                    "WHERE key = ? AND value = ?)")
            args += [key, value]
        sql += " ORDER BY submitted_at DESC, rowid DESC"
        if limit:
            sql += " LIMIT ?"
            args.append(limit)
        return [_workflow_row(r) for r in self._read(sql, tuple(args))]

    def tasks(self, workflow_id: str) -> list[dict[str, Any]]:
        """Task state payloads of a workflow (unordered)."""
        rows = self._read("SELECT state FROM tasks WHERE workflow_id = ?", (workflow_id,))
        return [json.loads(r[0]) for r in rows]

    def transitions(self, workflow_id: str, after_seq: int = 0) -> list[dict[str, Any]]:
        """The workflow's event log (status transitions), oldest first, with ``seq``."""
        rows = self._read(
            "SELECT * FROM events WHERE workflow_id = ? AND seq > ? ORDER BY seq",
            (workflow_id, after_seq),
        )
        return [dict(r) for r in rows]

    def attempts(self, workflow_id: str, task: str | None = None) -> list[AttemptRow]:
        """Attempt rows of a workflow (optionally one task), by task then retry."""
        sql, args = "SELECT * FROM attempts WHERE workflow_id = ?", [workflow_id]
        if task is not None:
            sql += " AND task = ?"
            args.append(task)
        rows = self._read(sql + " ORDER BY task, retry", tuple(args))
        return [AttemptRow(**dict(r)) for r in rows]


def _workflow_row(r: sqlite3.Row) -> WorkflowRow:
    spec, options = from_columns(json.loads(r["spec"]), json.loads(r["options"]))
    return WorkflowRow(id=r["id"], name=r["name"], status=r["status"],
                       submitted_at=r["submitted_at"], spec=spec, options=options,
                       state=json.loads(r["state"]))
