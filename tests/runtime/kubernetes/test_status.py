"""The status table (``osmo.runtime.kubernetes.status.TABLE``): one case per row, each a pod
status as the API shows it, and a check that every row has its case."""

from __future__ import annotations

from typing import Any

import pytest

from osmo.runtime.kubernetes.status import TABLE, Outcome, verdict


def pod(phase: str = "Pending", state: dict[str, Any] | None = None, **status: Any) -> dict:
    containers = [{"name": "task", "state": state}] if state else []
    return {"status": {"phase": phase, "containerStatuses": containers, **status}}


def condition(kind: str, reason: str, message: str = "", value: str = "True") -> dict:
    return {"type": kind, "status": value, "reason": reason, "message": message}


ROWS: dict[str, tuple[dict | None, Outcome, int | None, str]] = {
    "gone": (None, Outcome.LOST, None, "deleted"),
    "node-lost": (pod("Unknown", reason="NodeLost", message="Node n1 is unresponsive"),
                  Outcome.LOST, None, "Node n1 is unresponsive"),
    "evicted": (pod("Failed", {"terminated": {"exitCode": 137}}, reason="Evicted",
                    message="The node was low on resource: memory."),
                Outcome.LOST, None, "low on resource"),
    "disrupted": (pod("Running", {"running": {}}, conditions=[condition(
        "DisruptionTarget", "PreemptionByScheduler", "preempting")]), Outcome.LOST, None,
        "PreemptionByScheduler"),
    "init-failed": (pod("Failed", {"waiting": {"reason": "PodInitializing"}},
                        initContainerStatuses=[{"name": "osmo-fetch", "state": {"terminated": {
                            "exitCode": 1, "reason": "Error",
                            "message": "fetch: a.txt does not match its digest"}}}]),
                    Outcome.START_FAILED, None, "a.txt does not match its digest"),
    "pull-failed": (pod(state={"waiting": {"reason": "ImagePullBackOff",
                                           "message": 'Back-off pulling image "x:1"'}}),
                    Outcome.START_FAILED, None, 'Back-off pulling image "x:1"'),
    "config-failed": (pod(state={"waiting": {"reason": "CreateContainerError",
                                             "message": "no such file"}}),
                      Outcome.START_FAILED, None, "no such file"),
    "oom-killed": (pod("Failed", {"terminated": {"exitCode": 137, "reason": "OOMKilled"}}),
                   Outcome.EXITED, 137, "OOMKilled"),
    "terminated": (pod("Failed", {"terminated": {"exitCode": 3, "reason": "Error"}}),
                   Outcome.EXITED, 3, "Error"),
    "running": (pod("Running", {"running": {"startedAt": "now"}}), Outcome.RUNNING, None, ""),
    "unschedulable": (pod(conditions=[condition(
        "PodScheduled", "Unschedulable", "0/3 nodes are available: 3 Insufficient cpu.",
        "False")]), Outcome.WAITING, None, "0/3 nodes are available: 3 Insufficient cpu."),
    "pending": (pod(state={"waiting": {"reason": "ContainerCreating"}}), Outcome.WAITING, None,
                "ContainerCreating"),
}


def test_every_row_has_a_case() -> None:
    assert [row.name for row in TABLE] == list(ROWS)


@pytest.mark.parametrize("row", list(ROWS))
def test_row(row: str) -> None:
    status, outcome, code, words = ROWS[row]
    found = verdict(status)
    assert (found.row, found.outcome, found.exit_code) == (row, outcome, code)
    assert words in found.message, found
