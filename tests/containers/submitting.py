"""Helpers for running workflows in containers through the real CLI (``osmo submit``)."""

from __future__ import annotations

import json
import re
import time
from pathlib import Path

from osmo.runtime.container import ContainerEngine, owner_id
from tests.conftest import Osmo

_SYSLOG = "failed to connect to syslog"
_LOG_LINE = re.compile(
    r"^\d{4}/\d\d/\d\d \d\d:\d\d:\d\d \[([^\] ]+)(?: retry-\d+)?\](\[osmo\])? ?(.*)$")


def container_osmo(home: Path, env: dict[str, str]) -> Osmo:
    """A CLI whose server runs image tasks in containers (``env``: with CONTAINERS_CONF)."""
    runner = Osmo(home)
    runner.env.update(env)
    runner.env["OSMO_RUNTIME"] = "container"
    return runner


def owner_labels(osmo: Osmo) -> dict[str, str]:
    """The label every container and network of ``osmo``'s server carries."""
    return {"osmo.owner": owner_id(osmo.home)}


def leftovers(engine: ContainerEngine, labels: dict[str, str],
              timeout: float = 20) -> tuple[list[str], list[str]]:
    """Containers and networks still carrying ``labels`` once ``timeout`` passed (or none).

    Removal after an attempt runs in the background: give it a moment before judging.
    """
    deadline = time.monotonic() + timeout
    while True:
        found = engine.containers(labels), engine.networks(labels)
        if not any(found) or time.monotonic() > deadline:
            return found
        time.sleep(0.2)


def submitted_id(out: str) -> str:
    """The workflow id from ``osmo submit``'s output."""
    line = next(ln for ln in out.splitlines() if ln.startswith("Workflow ID - "))
    return line.split(" - ", 1)[1].strip()


def task_lines(osmo: Osmo, wf_id: str) -> dict[str, list[str]]:
    """Each task's own log lines (osmo's lines left out).

    Also left out: podman's ``failed to connect to syslog`` (these machines have no
    ``/dev/log``; its CLI says so on stderr now and then, which is the task's stderr).
    """
    out: dict[str, list[str]] = {}
    for line in osmo("logs", wf_id, check=True).out.splitlines():
        m = _LOG_LINE.match(line)
        if m and not m.group(2) and m.group(1) != "workflow" and _SYSLOG not in m.group(3):
            out.setdefault(m.group(1), []).append(m.group(3))
    return out


def osmo_lines(osmo: Osmo, wf_id: str, task: str) -> list[str]:
    """osmo's own log lines about ``task``."""
    found = []
    for line in osmo("logs", wf_id, check=True).out.splitlines():
        m = _LOG_LINE.match(line)
        if m and m.group(2) and m.group(1) == task:
            found.append(m.group(3))
    return found


def tasks(osmo: Osmo, wf_id: str) -> dict[str, dict]:
    """``osmo query``'s tasks by name."""
    return {t["name"]: t for t in osmo.query(wf_id)["tasks"]}


def lineage_of(osmo: Osmo, target: str) -> dict:
    """The lineage node of ``WORKFLOW:TASK``."""
    graph = json.loads(osmo("lineage", target, "--format", "json", check=True).out)
    task = target.rsplit(":", 1)[1]
    return next(n for n in graph["nodes"].values() if n["task"] == task)


def check_serial_tutorial(lines: dict[str, list[str]], rows: dict[str, dict]) -> None:
    """What OSMO's serial_workflow tutorial must leave, on any runtime: task3 read both
    upstream outputs, and each task wrote its own file."""
    assert lines["task3"] == ["Hello from task3 /osmo/data/output", "Reading from task 1",
                              "a line: Data from task 1", "Reading from task 2",
                              "a line: Data from task 2"]
    for n in (1, 2, 3):
        output = Path(rows[f"task{n}"]["output"])
        assert (output / "test_read.txt").read_text() == f"Data from task {n}\n"
