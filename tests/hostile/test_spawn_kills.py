"""A ``kill -9`` of the server the instant after it spawned a task leaves nothing running.

A real server (``tests/hostile/faulty_server.py``, fault ``spawn``) SIGKILLs itself right after
it started a task's process, before the start was reported or committed. bubblewrap's
``--die-with-parent`` does not cover a sandbox still being set up (its outer process is then
reparented to init), and the store holds no pid for that attempt yet; the next server must
still kill it, so it never runs beside the retry that replaces it.
"""

from __future__ import annotations

import time
from pathlib import Path

from tests.conftest import Osmo, write
from tests.hostile.test_engine_faults import Faulty, faulty  # noqa: F401 - the fixture


def test_a_task_spawned_just_before_a_kill_does_not_outlive_the_server(
        osmo: Osmo, faulty: list[Faulty], tmp_path: Path) -> None:  # noqa: F811
    log, marker = tmp_path / "log", tmp_path / "killed"
    server = Faulty(osmo, f"spawn:victim-{tmp_path.name}:{marker}")
    faulty.append(server)
    wf = osmo.submit(write(tmp_path / "wf.yaml", f"""
workflow:
  name: spawned
  tasks:
  - name: t
    command: [sh, -c, "echo start >> {log}; sleep 3; echo done >> {log}",
              victim-{tmp_path.name}]
"""))
    server.killed_itself(marker)
    info = osmo.wait_for(wf, lambda i: i["status"] not in ("PENDING", "RUNNING", "WAITING"),
                         timeout=120)  # the CLI starts the next server (no fault)
    assert info["status"] == "COMPLETED", info
    time.sleep(3.5)  # the first process, had it survived, would have finished by now
    lines = log.read_text().split()
    assert lines.count("done") == 1, lines  # only the retry ran to its end
