"""LocalPool under faults after a task exits: whatever promotion raises, the attempt gets its
one final report, and its credential files are deleted (issue 11, item 2)."""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

import pytest

from osmo.artifacts import ArtifactStore, Manifest
from osmo.artifacts.fsops import remove_tree
from osmo.layout import Home
from osmo.scheduler.types import AttemptExited, PrepareAttempt
from osmo.worker.pool import LocalPool
from tests.worker.test_pool import Events, attempt_dir, sh

PAYLOAD = {"key": "s3cr3t-value"}


class BrokenStore(ArtifactStore):
    """A store whose ingest raises what no handler expects (a bug, say)."""

    def ingest(self, folder: Path, **limits: Any) -> Manifest:
        raise RecursionError("maximum recursion depth exceeded (injected)")


def _run(pool: LocalPool, events: Events, script: str) -> tuple[AttemptExited, Path]:
    task = sh("t", script, credentials={"vault": "/etc/vault"})
    cmd = PrepareAttempt("wf-1:t:0", "wf-1", "t", 0, "local", {}, {}, run=True)
    pool.prepare(cmd, task, {"vault": PAYLOAD})
    final = events.final(cmd.attempt_id)
    assert isinstance(final, AttemptExited), final
    assert [type(e) for e in events.seen if getattr(e, "attempt_id", "") == cmd.attempt_id
            and isinstance(e, AttemptExited)] == [AttemptExited]
    folder = attempt_dir(pool, cmd.attempt_id)
    assert folder is not None
    return final, folder / "files" / "etc" / "vault"


def test_an_unexpected_error_in_promotion_still_reports_once(tmp_path: Path) -> None:
    events = Events()
    pool = LocalPool(home=Home(tmp_path / "home"), emit=events,
                     artifacts=BrokenStore(tmp_path / "store"))
    try:
        final, vault = _run(pool, events, "test -s /etc/vault/key && echo x > {{output}}/f")
    finally:
        pool.close()
    assert final.exit_code == 0 and final.output is None
    assert "could not be promoted" in final.message and "RecursionError" in final.message
    assert vault.is_dir() and not any(vault.iterdir())


@pytest.mark.parametrize("depth", [600, 2100])
def test_deep_output_trees_finish(tmp_path: Path, depth: int) -> None:
    events = Events()
    pool = LocalPool(home=Home(tmp_path / "home"), emit=events,
                     artifacts=ArtifactStore(tmp_path / "store"))
    nest = (f"cd {{{{output}}}} && python3 -c 'import os\\nfor _ in range({depth}): "
            "os.mkdir(\"d\"); os.chdir(\"d\")\\nopen(\"leaf\", \"w\").write(\"x\")'")
    try:
        final, vault = _run(pool, events, nest.replace("\\n", "\n"))
        assert not any(vault.iterdir())
        if depth == 600:
            assert final.output is not None and final.manifest is not None
            entry, = Manifest.from_json(final.manifest).entries
            assert entry.path == "d/" * depth + "leaf"
            assert os.path.isfile(os.path.join(final.output, entry.path))
        else:  # deeper than the system can open by path: a clear failure, not a hang
            assert final.output is None and "nested too deep" in final.message
    finally:
        pool.close()
        remove_tree(tmp_path / "home")  # pytest's own cleanup would recurse too deep
