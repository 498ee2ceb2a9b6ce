"""The SQLite store on real files: migrations, atomic batches, reads from other threads."""

from __future__ import annotations

import sqlite3
import threading
from pathlib import Path

import pytest

from osmo.errors import InfrastructureError
from osmo.scheduler import TaskState, WorkflowState
from osmo.scheduler.types import Changes, Transition
from osmo.spec.stored import StoredSpec
from osmo.status import TaskStatus, WorkflowStatus
from osmo.store.sqlite import SCHEMA_VERSION, AttemptRow, NewWorkflowRow, Store
from osmo.store.submission import Submission


def _wf(status: WorkflowStatus = WorkflowStatus.PENDING) -> WorkflowState:
    return WorkflowState(id="w-1", name="w", status=status, pool=None, max_retries=3,
                         submitted_at=1.0, started_at=None, ended_at=None, message="")


def _task(name: str, status: TaskStatus) -> TaskState:
    return TaskState(workflow_id="w-1", name=name, group=name, status=status, retry=0,
                     attempt_id=None, node_id=None, exit_code=None, output=None, message="",
                     reused=False, user_retries=0, lost_retries=0, created_at=1.0,
                     scheduling_at=None, started_at=None, ended_at=None)


def _submit(store: Store) -> None:
    changes = Changes(workflows=[_wf()], tasks=[_task("a", TaskStatus.SCHEDULING)],
                      transitions=[Transition(1.0, "w-1", "a", 0, "SCHEDULING")])
    store.commit(changes, new_workflows=[NewWorkflowRow(
        "w-1", "w", 1, 1.0, StoredSpec({"workflow": {"name": "w"}}), Submission())])


def test_schema_is_created_and_versioned(tmp_path: Path) -> None:
    Store(tmp_path / "s.db").close()
    db = sqlite3.connect(tmp_path / "s.db")
    assert db.execute("SELECT version FROM schema_version").fetchone() == (SCHEMA_VERSION,)
    assert db.execute("PRAGMA journal_mode").fetchone() == ("wal",)


def test_newer_schema_is_refused(tmp_path: Path) -> None:
    Store(tmp_path / "s.db").close()
    db = sqlite3.connect(tmp_path / "s.db")
    db.execute("UPDATE schema_version SET version = 999")
    db.commit()
    with pytest.raises(InfrastructureError, match="newer than this osmo"):
        Store(tmp_path / "s.db")


def test_worker_tokens_of_an_older_store_serve_every_pool(tmp_path: Path) -> None:
    """Schema 7 binds worker tokens to pools; the ones made before keep serving every pool."""
    import osmo.store.sqlite as sqlite_store

    older = {v: m for v, m in sqlite_store._MIGRATIONS.items() if v < 7}  # noqa: SLF001
    db = sqlite3.connect(tmp_path / "s.db", isolation_level=None)
    db.execute("CREATE TABLE schema_version (version INTEGER NOT NULL)")
    db.execute("INSERT INTO schema_version VALUES (6)")
    for version in sorted(older):
        older[version](db)
    db.execute("INSERT INTO tokens VALUES ('w', 'worker', 'd1', 1.0, NULL)")
    db.execute("INSERT INTO tokens VALUES ('u', 'user', 'd2', 1.0, NULL)")
    db.close()
    store = Store(tmp_path / "s.db")
    assert store.token_pools("w") == ["*"] and store.token_pools("u") is None
    assert store.add_token("w2", "worker", "d3", 2.0, ["gpu"])
    assert store.token_pools("w2") == ["gpu"]
    store.close()


def test_commit_round_trips_and_numbers_grow(tmp_path: Path) -> None:
    store = Store(tmp_path / "s.db")
    assert store.next_number("w") == 1
    _submit(store)
    assert store.next_number("w") == 2
    reopened = Store(tmp_path / "s.db")
    row = reopened.workflow("w-1")
    assert row is not None and row.spec.data == {"workflow": {"name": "w"}}
    assert WorkflowState.from_dict(row.state) == _wf()
    assert [TaskState.from_dict(t) for t in reopened.tasks("w-1")] == [
        _task("a", TaskStatus.SCHEDULING)]
    assert [e["status"] for e in reopened.transitions("w-1")] == ["SCHEDULING"]
    assert reopened.workflows(active_only=True)[0].id == "w-1"


def test_a_failing_batch_leaves_nothing_behind(tmp_path: Path) -> None:
    store = Store(tmp_path / "s.db")
    _submit(store)
    duplicate = Changes(workflows=[_wf(WorkflowStatus.RUNNING)],
                        tasks=[_task("a", TaskStatus.RUNNING)])
    with pytest.raises(InfrastructureError):  # same id again violates the primary key
        store.commit(duplicate, new_workflows=[NewWorkflowRow("w-1", "w", 1, 1.0, StoredSpec({}),
                                                                   Submission())])
    assert store.workflow("w-1").status == "PENDING"  # type: ignore[union-attr]
    assert store.tasks("w-1")[0]["status"] == "SCHEDULING"


def test_attempt_rows_and_reads_from_another_thread(tmp_path: Path) -> None:
    store = Store(tmp_path / "s.db")
    _submit(store)
    row = AttemptRow("w-1:a:0", "w-1", "a", 0, "local", "/tmp/x", 42, 123.5)
    store.commit(Changes(), attempts=[row])
    seen: list[object] = []
    t = threading.Thread(target=lambda: seen.append(store.attempts("w-1", "a")))
    t.start()
    t.join()
    assert seen == [[row]]


def test_names_that_are_not_utf8_are_stored_as_their_bytes(tmp_path: Path) -> None:
    import hashlib
    import os

    from osmo.artifacts import Entry, Manifest
    from osmo.store.sqlite import LineageRow

    store = Store(tmp_path / "s.db")
    _submit(store)
    digest = "sha256:" + hashlib.sha256(b"x").hexdigest()
    names = [os.fsdecode(b"caf\xe9.csv"), "na\u00efve.txt"]
    manifest = Manifest(tuple(Entry(n, digest, 1) for n in names))
    row = LineageRow("w-1:a:0", "w-1", "a", manifest.digest, manifest.to_json(),
                     tuple((e.path, e.digest, e.size) for e in manifest.entries),
                     "/out", "{}", ())
    message = "output " + os.fsdecode(b"caf\xe9.csv") + " rejected"
    store.commit(Changes(transitions=[Transition(2.0, "w-1", "a", 0, "FAILED", message)]),
                 lineage=[row])
    db = sqlite3.connect(tmp_path / "s.db")
    stored = db.execute("SELECT CAST(path AS BLOB), typeof(path) FROM manifest_blobs "
                        "ORDER BY path").fetchall()
    assert sorted(stored) == [(b"caf\xe9.csv", "blob"), ("naïve.txt".encode(), "text")]
    assert store.transitions("w-1")[-1]["message"] == "output caf\\xe9.csv rejected"
    assert Manifest.from_json(str(store.manifest_body(manifest.digest))) == manifest
