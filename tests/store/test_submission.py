"""A workflow's submission as one typed record in the store, and rows older servers wrote."""

from __future__ import annotations

import json
import sqlite3
from pathlib import Path

from osmo.spec import Workflow, spec_to_dict
from osmo.spec.model import ResolvedType, ResourceSpec
from osmo.spec.stored import StoredSpec
from osmo.store.sqlite import NewWorkflowRow, Store
from osmo.store.submission import Submission

SPEC = spec_to_dict(Workflow("w").task("a", ["true"]).build())
RESOLVED = ResolvedType("3", ResourceSpec(cpu=2.0), ("/srv/types",))


def _insert_raw(path: Path, wf_id: str, options: dict[str, object]) -> None:
    """A workflow row as an older server wrote it (its options an untyped JSON dict)."""
    Store(path).close()
    db = sqlite3.connect(path)
    db.execute("INSERT INTO workflows VALUES (?,?,?,?,?,?,?,?)",
               (wf_id, "w", 1, "PENDING", 1.0, json.dumps(SPEC), json.dumps(options), "{}"))
    db.commit()
    db.close()


def test_a_row_written_the_old_way_loads(tmp_path: Path) -> None:
    _insert_raw(tmp_path / "s.db", "w-1", {
        "pool": "gpu", "filename": "wf.yaml", "reused_from": "w-0",
        "labels": {"team": "a"}, "priority": "HIGH", "no_cache": False, "reuse": True,
        "type_paths": ["/srv/types"], "submitted_by": "ann",
        "types": {"a": RESOLVED.to_dict()}, "tags": ["best"]})
    row = Store(tmp_path / "s.db").workflow("w-1")
    assert row is not None
    assert row.options == Submission(pool="gpu", priority="HIGH", labels={"team": "a"},
                                     reuse=True, submitted_by="ann", reused_from="w-0",
                                     tags=("best",))
    assert row.options.reuses is True
    assert row.spec == StoredSpec(SPEC, "wf.yaml", {"a": RESOLVED.to_dict()})
    assert row.spec.load().task("a").resolved == RESOLVED


def test_a_row_from_before_priorities_and_owners_loads(tmp_path: Path) -> None:
    """The first servers kept only the pool, the file name and no_cache."""
    _insert_raw(tmp_path / "s.db", "w-1", {"pool": None, "filename": None, "no_cache": True})
    row = Store(tmp_path / "s.db").workflow("w-1")
    assert row is not None
    assert row.options == Submission(no_cache=True)
    assert row.options.priority == "NORMAL" and row.options.reuses is False
    assert row.spec.source == "<submitted>" and row.spec.load().task("a").command == ("true",)


def test_a_submission_round_trips_through_the_store(tmp_path: Path) -> None:
    store = Store(tmp_path / "s.db")
    spec = StoredSpec(SPEC, "<builder>", {"a": RESOLVED.to_dict()})
    options = Submission(pool="p", priority="LOW", labels={"k": "v"}, no_cache=True,
                         submitted_by="bob")
    from osmo.scheduler.types import Changes

    store.commit(Changes(), new_workflows=[NewWorkflowRow("w-1", "w", 1, 1.0, spec, options)])
    row = Store(tmp_path / "s.db").workflow("w-1")
    assert row is not None and (row.spec, row.options) == (spec, options)
    listed = store.workflows()[0]  # without its spec: the rest of the record all the same
    assert listed.options == options and listed.spec.data == {}
    assert listed.spec.types == spec.types and listed.spec.filename == "<builder>"


def test_the_worker_form_of_a_stored_spec_round_trips() -> None:
    spec = StoredSpec(SPEC, "wf.yaml", {"a": RESOLVED.to_dict()})
    assert StoredSpec.from_dict(spec.to_dict()) == spec
    assert StoredSpec.from_dict({"spec": SPEC}) == StoredSpec(SPEC)
