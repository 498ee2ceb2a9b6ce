"""Helpers the data-path hostile tests share: submit and wait, read a workflow's tasks."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from tests.conftest import Osmo


def finished(osmo: Osmo, spec: Path, *args: str, code: int = 0, timeout: float = 120) -> str:
    """``osmo submit SPEC --wait``: assert its exit code, return the workflow id."""
    r = osmo("submit", str(spec), "--wait", *args, timeout=timeout)
    assert r.code == code, r.out + r.err
    return r.out.splitlines()[0].split(" - ")[1]


def tasks(osmo: Osmo, workflow_id: str) -> dict[str, dict[str, Any]]:
    """The workflow's tasks by name, as ``osmo query --format json`` shows them."""
    return {t["name"]: t for t in osmo.query(workflow_id)["tasks"]}
