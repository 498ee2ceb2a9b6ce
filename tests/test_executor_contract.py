"""One contract, every executor (``osmo.executor.Executor``): the conformance kit
``osmo.testing.check_executor`` runs over the local pool and over the remote-worker hub
with a real ``osmo worker`` process on loopback (another host id, so outputs travel as
blobs over zenoh). A container runtime or a Kubernetes executor joins the parameter list.
"""

from __future__ import annotations

import os
import queue
import signal
import subprocess
import sys
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import pytest

from osmo.artifacts import ArtifactStore
from osmo.config import free_port
from osmo.executor import Executor
from osmo.layout import Home
from osmo.scheduler.types import LOCAL_NODE, Changes, NodeUp
from osmo.server.auth import Authenticator, Router
from osmo.server.workers import WorkerHub
from osmo.spec import spec_to_dict
from osmo.spec.model import WorkflowSpec
from osmo.spec.stored import StoredSpec
from osmo.store.sqlite import NewWorkflowRow, Store
from osmo.store.submission import Submission
from osmo.testing import check_executor
from osmo.transport.auth import new_token, token_digest
from osmo.transport.rpc import ApiServer
from osmo.transport.seal import Signer
from osmo.transport.zenoh_link import Link
from osmo.worker.pool import LocalPool
from tests.conftest import REPO


@dataclass
class Harness:
    """A started executor, where its events arrive, the node it runs, how to admit a
    workflow's spec before its attempts are prepared."""

    executor: Executor
    events: queue.Queue[Any]
    node_id: str
    admit: Callable[[str, WorkflowSpec], None] = lambda _wf, _spec: None


def _local_pool(tmp_path: Path) -> Iterator[Harness]:
    events: queue.Queue[Any] = queue.Queue()
    home = Home(tmp_path / "home")
    pool = LocalPool(home=home, emit=events.put, kill_grace=1.0,
                     artifacts=ArtifactStore(home.artifacts))
    yield Harness(pool, events, LOCAL_NODE)
    pool.close()


def _worker_hub(tmp_path: Path) -> Iterator[Harness]:
    events: queue.Queue[Any] = queue.Queue()
    home = Home(tmp_path / "server")
    home.root.mkdir(parents=True)
    endpoint = f"tcp/127.0.0.1:{free_port(0)}"
    link = Link.router([endpoint], "contract")
    store = Store(home.state_db)
    authenticate = Authenticator(store, Signer())
    token = new_token()
    store.add_token("w1", "worker", token_digest(token), time.time(), ["default"])
    hub = WorkerHub(link=link, emit=events.put, store=store,
                    artifacts=ArtifactStore(home.artifacts), home=home,
                    url_credential=lambda _url: None, attempts_on=lambda _node: [],
                    gate=authenticate)
    api = ApiServer(link, Router({"workers": hub}), authenticate, inline=WorkerHub.INLINE)
    env = dict(os.environ, OSMO_HOME=str(tmp_path / "w1"), OSMO_HOST_ID="another-host",
               OSMO_TOKEN=token)
    with open(tmp_path / "w1.log", "ab") as log:
        worker = subprocess.Popen(
            [sys.executable, "-m", "osmo", "worker", "--connect", endpoint, "--cluster",
             "contract", "--name", "w1", "--cpus", "8"],
            env=env, stdout=log, stderr=log, cwd=REPO, start_new_session=True)

    def admit(workflow_id: str, spec: WorkflowSpec) -> None:
        store.commit(Changes(), new_workflows=[NewWorkflowRow(
            workflow_id, spec.name, 1, time.time(), StoredSpec(spec_to_dict(spec)),
            Submission())])

    try:
        _wait_for_node(events, "w1", tmp_path / "w1.log")
        yield Harness(hub, events, "w1", admit)
    finally:
        os.kill(worker.pid, signal.SIGKILL)
        worker.wait(timeout=30)
        api.close()
        hub.close()
        link.close()
        store.close()


def _wait_for_node(events: queue.Queue[Any], node_id: str, log: Path) -> None:
    deadline = time.monotonic() + 60
    while time.monotonic() < deadline:
        try:
            event = events.get(timeout=max(0.0, deadline - time.monotonic()))
        except queue.Empty:
            break
        if isinstance(event, NodeUp) and event.node.id == node_id:
            return
    raise AssertionError(f"worker {node_id} never came up:\n{log.read_text(errors='replace')}")


IMPLEMENTATIONS = {"local pool": _local_pool, "worker hub": _worker_hub}


@pytest.fixture(params=sorted(IMPLEMENTATIONS))
def harness(request: pytest.FixtureRequest, tmp_path: Path) -> Iterator[Harness]:
    yield from IMPLEMENTATIONS[request.param](tmp_path)


def test_the_executor_keeps_the_contract(harness: Harness) -> None:
    check_executor(harness.executor, harness.events, harness.node_id, admit=harness.admit)


def test_it_owns_only_its_nodes(harness: Harness) -> None:
    others = {LOCAL_NODE: ["w1", "gpu-7"], "w1": [LOCAL_NODE]}[harness.node_id]
    assert harness.executor.owns(harness.node_id)
    assert not any(harness.executor.owns(node) for node in others)


class _Broken:
    """A local pool with one promise broken, to see the kit catch it."""

    def __init__(self, pool: LocalPool, *, ignore_kills: bool = False) -> None:
        self.pool, self.ignore_kills = pool, ignore_kills

    def owns(self, node_id: str) -> bool:
        return self.pool.owns(node_id)

    def prepare(self, cmd: Any, task: Any, *, max_output_bytes: int | None = None) -> None:
        self.pool.prepare(cmd, task, max_output_bytes=max_output_bytes)

    def run(self, cmd: Any) -> None:
        self.pool.run(cmd)

    def kill(self, cmd: Any) -> None:
        if not self.ignore_kills:
            self.pool.kill(cmd)

    def close(self) -> None:
        self.pool.close()


def test_the_kit_catches_a_second_final_report(tmp_path: Path) -> None:
    events: queue.Queue[Any] = queue.Queue()

    def emit(event: Any) -> None:
        events.put(event)
        if type(event).__name__ == "AttemptExited" and event.attempt_id.endswith(":exit3:0"):
            events.put(event)  # reported twice

    pool = LocalPool(home=Home(tmp_path), emit=emit)
    try:
        with pytest.raises(AssertionError, match=r"exit3:0: 2 final reports"):
            check_executor(pool, events, LOCAL_NODE)
    finally:
        pool.close()


def test_the_kit_catches_ignored_kills_and_foreign_nodes(tmp_path: Path) -> None:
    events: queue.Queue[Any] = queue.Queue()
    broken = _Broken(LocalPool(home=Home(tmp_path), emit=events.put), ignore_kills=True)
    try:
        with pytest.raises(AssertionError) as err:
            check_executor(broken, events, "elsewhere", timeout=3)
    finally:
        broken.close()
    assert "it does not own 'elsewhere'" in str(err.value)
    assert "sleeper: no final report within 3s" in str(err.value)
