"""A sandbox whose setup fails for a moment (a mount vanishing under bubblewrap) is retried.

bubblewrap's ``--ro-bind / /`` loses a race against mounts that vanish meanwhile (podman's
containers starting or stopping); the failure is bwrap's, before the command runs, and must
neither fail the task with exit 1 nor pass for the command's own exit
(tests/runtime/churn.py reproduces it).
"""

from __future__ import annotations

from pathlib import Path

from tests.conftest import Osmo, ended, write
from tests.runtime.churn import churning_mounts

TASKS = 60


def test_tasks_complete_while_mounts_come_and_go(osmo: Osmo, tmp_path: Path) -> None:
    tasks = "".join(f"  - name: t{i}\n    command: ['true', '{i}']\n" for i in range(TASKS))
    spec = write(tmp_path / "many.yaml", f"workflow:\n  name: many\n  tasks:\n{tasks}")
    with churning_mounts(count=10, pause=0.001):
        info = osmo.wait_for(osmo.submit(spec), ended)
    assert info["status"] == "COMPLETED", [
        (t["name"], t["status"], t.get("message")) for t in info["tasks"]
        if t["status"] != "COMPLETED"]
