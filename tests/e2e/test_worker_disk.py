"""A remote worker's disk: ended attempts' folders go, the artifact store stays under its limit.

Real processes on loopback (``tests.e2e.cluster``): a server and an ``osmo worker`` on another
"host" (its own ``OSMO_HOST_ID``), so every input is fetched over zenoh and every output pulled
from the worker's store.
"""

from __future__ import annotations

import time
from collections.abc import Iterator
from pathlib import Path

import pytest

from osmo.artifacts import ArtifactStore
from tests.conftest import ended, write
from tests.e2e.cluster import Cluster

MIB = 1 << 20
LIMIT = 3 * MIB


@pytest.fixture
def cluster(tmp_path: Path) -> Iterator[Cluster]:
    c = Cluster(tmp_path, env={"OSMO_HOST_ID": "server-host"})
    c.start_server()
    yield c
    c.stop()


def _chain(n: int) -> str:
    """n tasks in a chain; each checks its input byte for byte and writes 1 MiB of its own."""
    tasks = []
    for i in range(n):
        check = (f"yes t{i - 1} | head -c {MIB} | cmp - {{{{input:0}}}}/data && "
                 if i else "")
        inputs = f"\n    inputs: [{{task: t{i - 1}}}]" if i else ""
        tasks.append(f"""
  - name: t{i}
    command: [sh, -c, "{check}yes t{i} | head -c {MIB} > {{{{output}}}}/data"]{inputs}""")
    return "workflow:\n  name: disk\n  tasks:" + "".join(tasks) + "\n"


def _attempt_folders(runs: Path) -> list[Path]:
    return [p for p in runs.glob("*/*/*") if p.is_dir()] if runs.exists() else []


def _until(what: str, check: object, timeout: float = 30) -> None:
    deadline = time.monotonic() + timeout
    while not check():  # type: ignore[operator]
        assert time.monotonic() < deadline, what
        time.sleep(0.2)


def test_a_worker_removes_acknowledged_attempts_and_keeps_its_store_under_the_limit(
        cluster: Cluster, tmp_path: Path) -> None:
    cluster.start_worker("w1", "--cpus", "1", "--store-limit", "3Mi", host="worker-host")
    home = tmp_path / "w1" / "worker"
    store = ArtifactStore(home / "artifacts")
    wf = cluster.osmo.submit(write(tmp_path / "chain.yaml", _chain(8)))
    info = cluster.osmo.wait_for(wf, ended, timeout=120)
    assert info["status"] == "COMPLETED", info  # every input arrived whole (cmp)

    # every attempt was acknowledged: its folder is gone from the worker
    _until("attempt folders left on the worker",
           lambda: _attempt_folders(home / "runs") == [])
    # 8 MiB of outputs passed through a store limited to 3 MiB: the oldest were removed
    _until(f"the worker's store still holds {store.size()} bytes",
           lambda: store.size() <= LIMIT)
    assert store.size() >= MIB  # the newest output stays cached

    # the server kept every output: download the first one, which the worker no longer has
    out = tmp_path / "t0"
    cluster.osmo("artifacts", "get", f"{wf}:t0", "-o", str(out), check=True)
    assert (out / "data").read_bytes() == (b"t0\n" * MIB)[:MIB]

    # a task on the worker reading that evicted output gets it fetched again, whole
    again = cluster.osmo.submit(write(tmp_path / "again.yaml", f"""
workflow:
  name: again
  tasks:
  - name: read
    inputs: [{{task: "{wf}:t0"}}]
    command: [sh, -c, "yes t0 | head -c {MIB} | cmp - {{{{input:0}}}}/data"]
"""))
    info = cluster.osmo.wait_for(again, ended, timeout=60)
    assert info["status"] == "COMPLETED", info


def test_a_restarted_worker_clears_what_its_previous_life_left(
        cluster: Cluster, tmp_path: Path) -> None:
    home = tmp_path / "w2" / "worker"
    left = home / "runs" / "wf-1" / "task" / "0"
    left.mkdir(parents=True)
    (left / "output").mkdir()
    (left / "output" / "big").write_bytes(b"x" * MIB)
    cluster.start_worker("w2", "--cpus", "1", host="worker-host")
    _until("a previous life's attempt folder is still there",
           lambda: not (home / "runs" / "wf-1").exists()
           and not list(home.glob("runs.old-*")))


def test_a_bad_store_limit_is_a_usage_error(cluster: Cluster) -> None:
    proc = cluster.start_worker("w3", "--store-limit", "lots", wait=False)
    assert proc.wait(timeout=60) == 2
    assert "--store-limit 'lots'" in cluster.worker_log("w3")
