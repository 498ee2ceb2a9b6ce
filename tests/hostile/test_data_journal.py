"""A node's adoption journal read back after tampering (osmo.worker.journal; issue 29 item 6).

The journal sits in the node's private home (0700). Whatever an entry says, reading it back
never trusts it as a path: a corrupt or tampered entry (bad JSON, a name that climbs out,
a folder swapped for a symlink, an entry filed under another attempt's name, fields of the
wrong types, a huge file) is dropped with a warning and its file removed; the good entry
beside it is kept. A journal folder that is a symlink is refused.
"""

from __future__ import annotations

import json
import logging
import os
import stat
from collections.abc import Callable
from pathlib import Path

import pytest

from osmo.errors import OsmoError
from osmo.layout import Home
from osmo.scheduler.types import PrepareAttempt
from osmo.spec.stored import StoredSpec
from osmo.worker.journal import Journal

SPEC = StoredSpec({"workflow": {"name": "w", "tasks": [
    {"name": "t", "command": ["true"]}, {"name": "u", "command": ["true"]}]}})


def _journal(tmp_path: Path) -> tuple[Home, Journal]:
    home = Home(tmp_path / "home")
    journal = Journal(home.root / "journal", {"w-1": SPEC}.get)
    for task in ("t", "u"):
        home.attempt("w-1", task, 0).root.mkdir(parents=True)
        journal.add(PrepareAttempt(f"w-1:{task}:0", "w-1", task, 0, "n", {}, {}),
                    argv=("true",), image_id=None, secrets=("s3cret",), max_output_bytes=None)
    return home, journal


def _entry_file(journal: Journal, task: str) -> Path:
    for path in journal.folder.glob("attempt-*.json"):
        if json.loads(path.read_text())["task"] == task:
            return path
    raise AssertionError(f"no entry of {task}")


def _rewrite(field: str, value: object) -> Callable[[Home, Journal, Path], None]:
    def tamper(_home: Home, _journal: Journal, path: Path) -> None:
        data = json.loads(path.read_text())
        data[field] = value
        path.write_text(json.dumps(data))
    return tamper


def _garbage(_home: Home, _journal: Journal, path: Path) -> None:
    path.write_text("{not json")


def _huge(_home: Home, _journal: Journal, path: Path) -> None:
    path.write_text(json.dumps({"pad": "x" * (5 << 20)}))


def _symlinked_folder(home: Home, _journal: Journal, _path: Path) -> None:
    outside = home.root.parent / "outside"
    outside.mkdir()
    folder = home.attempt("w-1", "t", 0).root
    folder.rmdir()
    folder.symlink_to(outside)


def _filed_under_another(_home: Home, journal: Journal, path: Path) -> None:
    other = _entry_file(journal, "u")
    other.write_text(path.read_text())  # t's entry under u's name


def _symlinked_entry(home: Home, _journal: Journal, path: Path) -> None:
    target = home.root.parent / "planted.json"
    target.write_text(path.read_text())
    path.unlink()
    path.symlink_to(target)


ATTACKS = {
    "garbage": _garbage,
    "huge": _huge,
    "task_climbs_out": _rewrite("task", "../../../../etc"),
    "workflow_with_slash": _rewrite("workflow_id", "w-1/../../x"),
    "retry_as_text": _rewrite("retry", "0"),
    "retry_negative": _rewrite("retry", -1),
    "argv_not_a_list": _rewrite("argv", "rm -rf /"),
    "secrets_not_strings": _rewrite("secrets", [1, 2]),
    "unknown_task": _rewrite("task", "nope"),
    "folder_is_a_symlink_out": _symlinked_folder,
    "entry_is_a_symlink": _symlinked_entry,
}


@pytest.mark.parametrize("attack", ATTACKS.values(), ids=ATTACKS.keys())
def test_a_tampered_entry_is_dropped_with_a_warning_and_the_good_one_kept(
        tmp_path: Path, attack: Callable[[Home, Journal, Path], None],
        caplog: pytest.LogCaptureFixture) -> None:
    home, journal = _journal(tmp_path)
    victim = _entry_file(journal, "t")
    attack(home, journal, victim)
    with caplog.at_level(logging.WARNING, logger="osmo.worker"):
        entries = Journal(home.root / "journal", {}.get).read(home)
    kept = [(e.attempt_id, e.dirs.root) for e in entries]
    if attack is _filed_under_another:  # u's file held t's entry: that one goes, t's stays
        assert kept == [("w-1:t:0", home.attempt("w-1", "t", 0).root)], kept
    else:
        assert kept == [("w-1:u:0", home.attempt("w-1", "u", 0).root)], kept
    assert "dropped the journal entry" in caplog.text, caplog.text
    assert not victim.exists() or attack is _filed_under_another
    for entry in entries:
        assert entry.dirs.root.resolve().is_relative_to(home.runs.resolve())


def test_the_journal_is_private_and_a_symlinked_one_is_refused(tmp_path: Path) -> None:
    home, journal = _journal(tmp_path)
    assert stat.S_IMODE(os.stat(journal.folder).st_mode) == 0o700
    assert all(stat.S_IMODE(os.stat(p).st_mode) == 0o600 for p in journal.folder.iterdir())
    other = tmp_path / "other"
    other.mkdir()
    (tmp_path / "linked").symlink_to(other)
    with pytest.raises(OsmoError, match="not a folder"):
        Journal(tmp_path / "linked", {}.get)
    entries = journal.read(home)
    assert [e.secrets for e in entries] == [("s3cret",), ("s3cret",)]
