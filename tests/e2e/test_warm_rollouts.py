"""Warm runners end to end: a sweep of tiny ``sim.rollout`` tasks through the real CLI.

The server's pool runs unsandboxed (``--sandbox off``) or in the default sandbox (a
built-in type's runner is then a sandbox of its own, each attempt a fork of it in the view
bubblewrap would give it cold): every
rollout after the first is forked from one runner that imported gymnasium and MuJoCo once,
and ``osmo resource list`` shows that runner, how many attempts it started and its memory;
a remote worker's runners too, as its last beat said.
"""

from __future__ import annotations

import os
import time
from pathlib import Path

import pytest

from tests.conftest import Osmo, write
from tests.e2e.cluster import Cluster

pytest.importorskip("mujoco")
pytest.importorskip("gymnasium")

TASKS = 6
SWEEP = "workflow:\n  name: warm-sweep\n  tasks:\n" + "".join(
    f"  - name: rollout-{i}\n    type: sim.rollout\n"
    + ("    environment: {OSMO_TASK_TIMING: '1'}\n" if i == 3 else "")
    + f"    params: {{episodes: 1, max_steps: 20, seed: {i}}}\n" for i in range(TASKS))


@pytest.mark.parametrize("sandbox", ["off", "auto"])
def test_a_rollout_sweep_runs_on_one_warm_runner(osmo: Osmo, tmp_path: Path,
                                                 sandbox: str) -> None:
    """Unsandboxed, and in the default sandbox (a built-in type, a root osmo)."""
    if sandbox == "auto" and os.geteuid() != 0:
        pytest.skip("sandboxed warm starts need a root osmo (a non-root one starts cold)")
    osmo("server", "start", "--sandbox", sandbox, "--warm-idle", "300", check=True)
    wf = osmo.submit(write(tmp_path / "sweep.yaml", SWEEP), "--wait", timeout=300)
    tasks = osmo.query(wf)["tasks"]
    assert {t["status"] for t in tasks} == {"COMPLETED"}, tasks
    for task in tasks:
        assert any(Path(task["output"]).rglob("*.mcap")), task
    nodes = osmo("resource", "list", "--format", "json", check=True).json()
    assert isinstance(nodes, list)
    runners = nodes[0]["warm"]
    assert [(r["type"], r["started"], r["running"]) for r in runners] == [
        ("sim.rollout@2", TASKS, 0)], runners
    assert runners[0]["rss"] > 20 << 20, runners  # gymnasium and MuJoCo, imported once
    text = osmo("resource", "list", check=True).out
    assert f"sim.rollout@2 x{TASKS}" in text, text
    log = osmo("logs", wf, "-t", "rollout-3", check=True).out
    assert "warm start: forked from a runner of sim.rollout" in log, log
    # OSMO_TASK_TIMING: the run's own seconds, its imports done by the runner before
    compute = [line for line in log.splitlines() if "osmo: compute " in line]
    assert len(compute) == 1 and 0 < float(compute[0].split()[-1]) < 30, log
    assert "osmo: compute " not in osmo("logs", wf, "-t", "rollout-2", check=True).out


def test_a_remote_workers_warm_runners_show_in_resource_list(tmp_path: Path) -> None:
    """A worker's beat carries its runners: ``osmo resource list`` shows them for its node."""
    with Cluster.started(tmp_path) as cluster:
        cluster.start_worker("w1", "--sandbox", "off", "--cpus", "2")
        spec = write(tmp_path / "sweep.yaml", SWEEP.replace(f"rollout-{TASKS - 1}", "last"))
        wf = cluster.osmo.submit(spec, "--wait", timeout=300)
        assert {t["status"] for t in cluster.osmo.query(wf)["tasks"]} == {"COMPLETED"}
        deadline = time.monotonic() + 30
        while True:  # a later beat (every 2 s) says it: one from mid-sweep counts fewer
            nodes = cluster.osmo("resource", "list", "--format", "json", check=True).json()
            assert isinstance(nodes, list)
            warm = [r for n in nodes if n["node"] == "w1" for r in n.get("warm") or []]
            if [r["started"] for r in warm] == [TASKS] or time.monotonic() > deadline:
                break
            time.sleep(0.5)
        assert [(r["type"], r["started"]) for r in warm] == [("sim.rollout@2", TASKS)], nodes
