"""docs/concepts/durability.md, The state store → Chaos test: the project's own chaos test (see ``tests/e2e/chaos.py``).

A few seeded trials; ``bench/bench_chaos.py`` runs many. The seed is printed (``-s`` or a
failure shows it); ``OSMO_CHAOS_SEED=N`` replays a trial.

Remote trials do not yet require that a SIGKILLed worker's tasks die with it (issue 15 item
1, another change): their leftover *task* processes are killed and reported, and every other
promise is checked. Server and worker processes left behind always fail the trial.

A kill that lands while the server applies an attempt's final report (about 1 kill in 70
here) makes the task run again; only a second such crash on the same task quarantines it
(docs/concepts/durability.md, "When the server itself fails"). The trials do not excuse a quarantined task.

Warm runners (issue 30): one local trial runs its pool unsandboxed, where typed tasks are
forks of warm runners, and the remote trial's worker w2 does too (w1 stays sandboxed). Their
typed tasks keep every promise above, and the runners under a killed server or worker are
gone with it.
"""

from __future__ import annotations

import json
import os
import signal
from pathlib import Path

import pytest

from tests.conftest import ended, wait_gone, write
from tests.e2e.chaos import Trial
from tests.e2e.cluster import Cluster

SEED = int(os.environ.get("OSMO_CHAOS_SEED", "1515"))


@pytest.mark.parametrize(("offset", "warm"), [(0, False), (1, False), (2, True)])
def test_chaos_server_kills_on_the_local_pool(tmp_path: Path, offset: int, warm: bool) -> None:
    seed = SEED + offset
    print(f"chaos seed {seed} (local pool{', warm runners' if warm else ''})")
    result = Trial(tmp_path / "t", seed, mode="local", kills=3, warm=warm).run()
    print(result)
    assert [k for k, _ in result.kills] == ["server"] * len(result.kills)
    assert result.kills, f"seed {seed}: the workflow ended before the first kill"
    assert result.problems() == [], f"seed {seed}: {result}"
    if warm:
        assert result.warm_starts > 0, f"seed {seed}: no typed task ran warm: {result}"
        assert result.warm_at_kills > 0, f"seed {seed}: no kill found a warm runner: {result}"


def test_chaos_server_and_worker_kills_with_remote_workers(tmp_path: Path) -> None:
    seed = SEED + 100
    print(f"chaos seed {seed} (remote workers)")
    result = Trial(tmp_path / "t", seed, mode="remote", kills=3, warm=True).run()
    print(result)
    assert result.kills, f"seed {seed}: the workflow ended before the first kill"
    problems = result.problems(task_leftovers=False)
    assert problems == [], f"seed {seed}: {result}"
    assert result.warm_starts > 0, f"seed {seed}: no typed task ran warm on w2: {result}"


def test_an_output_that_finishes_across_a_server_restart_keeps_its_lineage(
        tmp_path: Path) -> None:
    """Found by the chaos trials: a remote attempt placed by a server that was then SIGKILLed
    completed under the next server without an artifact or lineage record."""
    cluster = Cluster(tmp_path, env={"OSMO_HOST_ID": "shared-host"})
    try:
        cluster.start_server()
        cluster.start_worker("w1", "--cpus", "1")
        go = tmp_path / "go"
        spec = write(tmp_path / "wf.yaml", f"""
workflow:
  name: across
  tasks:
  - name: slow
    command: [sh, -c, "while [ ! -e {go} ]; do sleep 0.05; done; echo made > {{{{output}}}}/f"]
  - name: after
    command: [sh, -c, "cat {{{{input:slow}}}}/f > {{{{output}}}}/g"]
    inputs: [{{task: slow}}]
""")
        osmo = cluster.osmo
        wf = osmo.submit(spec)
        osmo.wait_for(wf, lambda i: i["tasks"][0]["status"] == "RUNNING")
        pid = osmo.server_pid()
        assert pid is not None
        os.kill(pid, signal.SIGKILL)
        wait_gone(pid)
        osmo("list", check=True)  # a new server, with the saved options
        go.touch()
        info = osmo.wait_for(wf, ended)
        assert info["status"] == "COMPLETED", info
        outputs = json.loads(osmo("artifacts", "list", wf, "--format", "json", check=True).out)
        assert sorted(o["task"] for o in outputs) == ["after", "slow"], outputs
        lineage = osmo("lineage", f"{wf}:after", "--format", "json", check=True).out
        assert f"{wf}:slow:0" in lineage, lineage
    finally:
        cluster.stop()
