"""docs/concepts/durability.md, Remote workers → Failures: after a server restart, "a worker not back within
`--reconnect-grace` (30 s) is taken as lost" (its attempts are rescheduled).

The grace is set short for the test that lets it expire; the default of 30 s is checked
where the server's options define it.
"""

from __future__ import annotations

import argparse
import os
import signal
import time
from collections.abc import Iterator
from pathlib import Path

import pytest

from osmo.options import ServerOptions
from tests.conftest import ended, wait_gone, write
from tests.e2e.cluster import Cluster

GRACE = 3.0

HELD = """
workflow:
  name: held
  tasks:
  - name: t
    command: [sh, -c, "while [ ! -e TMP/release-$OSMO_NODE ]; do sleep 0.05; done; echo $OSMO_NODE > {{output}}/node"]
"""


def test_the_default_grace_is_thirty_seconds() -> None:
    parser = argparse.ArgumentParser()
    ServerOptions.add_arguments(parser)
    options = ServerOptions.from_args(parser.parse_args([]))
    assert options == ServerOptions() and options.reconnect_grace == 30.0  # serve()'s too
    assert "--reconnect-grace" not in options.to_argv()  # the background server gets 30 too
    short = ServerOptions.from_args(parser.parse_args(["--reconnect-grace", "3"]))
    assert short.to_argv() == ["--reconnect-grace", "3.0"]


@pytest.fixture
def cluster(tmp_path: Path) -> Iterator[Cluster]:
    c = Cluster(tmp_path, server_args=("--reconnect-grace", str(GRACE)),
                env={"OSMO_HOST_ID": "shared-host"})
    c.start_server()
    yield c
    c.stop()


def test_a_worker_not_back_within_the_grace_is_lost(cluster: Cluster, tmp_path: Path) -> None:
    cluster.start_worker("w1", "--cpus", "1")
    cluster.start_worker("w2", "--cpus", "1")
    wf = cluster.osmo.submit(write(tmp_path / "wf.yaml", HELD.replace("TMP", str(tmp_path))))
    info = cluster.osmo.wait_for(wf, lambda i: i["tasks"][0]["status"] == "RUNNING")
    gone = info["tasks"][0]["node"]
    back = "w2" if gone == "w1" else "w1"
    try:
        cluster.signal(gone, signal.SIGSTOP)  # it will not come back to the next server
        server_pid = cluster.osmo.server_pid()
        assert server_pid is not None
        os.kill(server_pid, signal.SIGKILL)
        wait_gone(server_pid)
        restarted_at = time.time()
        cluster.start_server()
        lost_at, _ = cluster.server_log_line(f"worker {gone} did not come back within")
        assert lost_at - restarted_at >= GRACE, "taken as lost before the grace ran out"
        assert lost_at - restarted_at <= GRACE + 10, "the grace ran far too long"
        info = cluster.osmo.wait_for(wf, lambda i: i["tasks"][0]["retry"] == 1
                                     and i["tasks"][0]["status"] == "RUNNING")
        assert info["tasks"][0]["node"] == back
        (tmp_path / f"release-{back}").touch()
        info = cluster.osmo.wait_for(wf, ended)
    finally:
        (tmp_path / f"release-{gone}").touch()
    assert info["status"] == "COMPLETED", info
    assert Path(info["tasks"][0]["output"], "node").read_text().strip() == back
