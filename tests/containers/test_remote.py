"""A remote ``osmo worker --runtime container`` runs image tasks through the same pool code;
after a ``kill -9`` of the worker, the restarted worker removes what its containers left.

The task is quiet until it ends: a container that writes after its worker died gets SIGPIPE
through the engine CLI's signal proxy and ends by itself; a quiet one outlives the worker,
which is the case the restart must clean up.
"""

from __future__ import annotations

import base64
import json
import signal
import time
import uuid
from collections.abc import Iterator
from pathlib import Path

import pytest

from osmo.runtime.container import ContainerEngine, owner_id
from tests.conftest import ended, write
from tests.containers.registry import fake_registry
from tests.containers.submitting import leftovers, task_lines, tasks
from tests.e2e.cluster import Cluster

SPEC = """
workflow:
  name: remote-box
  tasks:
  - name: boxed
    image: alpine:3.18
    command: [sh, -c, "sleep 4; echo in $(hostname); echo $OSMO_NODE > {{output}}/node"]
"""


@pytest.fixture
def cluster(podman_env: dict[str, str], images: dict[str, str], engine: ContainerEngine,
            tmp_path: Path) -> Iterator[Cluster]:
    c = Cluster(tmp_path, env={"CONTAINERS_CONF": podman_env["CONTAINERS_CONF"]})
    c.start_server()
    yield c
    c.stop()
    labels = {"osmo.owner": owner_id(tmp_path / "w1" / "worker")}
    assert leftovers(engine, labels) == ([], [])


def test_a_remote_worker_runs_a_container_and_cleans_up_after_a_kill_9(
        cluster: Cluster, engine: ContainerEngine, tmp_path: Path) -> None:
    cluster.start_worker("w1", "--runtime", "container", "--cpus", "2")
    node = cluster.nodes()["w1"]
    assert node["runtime"].startswith("container (podman ")
    wf = cluster.osmo.submit(write(tmp_path / "wf.yaml", SPEC))
    labels = {"osmo.owner": owner_id(tmp_path / "w1" / "worker"), "osmo.workflow": wf}
    deadline = time.monotonic() + 60
    while not engine.running(labels):
        assert time.monotonic() < deadline, cluster.worker_log("w1")
        time.sleep(0.1)
    cluster.signal("w1", signal.SIGKILL)
    cluster.workers["w1"].wait(timeout=30)
    time.sleep(0.5)
    assert engine.containers(labels), "its container outlives the worker (nothing else kills)"
    cluster.start_worker("w1", "--runtime", "container", "--cpus", "2")
    deadline = time.monotonic() + 60
    while not (running := engine.running(labels)):
        assert time.monotonic() < deadline, cluster.worker_log("w1")
        time.sleep(0.1)
    ident = running[0]
    info = cluster.osmo.wait_for(wf, ended, timeout=120)
    assert info["status"] == "COMPLETED", json.dumps(info)
    boxed = tasks(cluster.osmo, wf)["boxed"]
    assert boxed["retry"] == 1
    assert Path(boxed["output"], "node").read_text().strip() == "w1"
    assert task_lines(cluster.osmo, wf)["boxed"] == [f"in {ident[:12]}"]  # in its container


def _files_holding(folder: Path, *needles: str) -> list[str]:
    found = []
    for path in folder.rglob("*"):
        try:
            data = path.read_bytes() if path.is_file() and not path.is_symlink() else b""
        except OSError:
            continue
        if any(n.encode() in data for n in needles):
            found.append(str(path))
    return found


def test_a_remote_worker_pulls_with_the_stored_registry_credential_only(
        podman_env: dict[str, str], images: dict[str, str], engine: ContainerEngine,
        tmp_path: Path) -> None:
    """The worker gets the credential of its task's registry, uses it for the pull only."""
    password = f"pw-{uuid.uuid4().hex}"
    basic = base64.b64encode(f"robot:{password}".encode()).decode()
    with fake_registry(password) as private, fake_registry(password) as other:
        conf = private.registries_conf(tmp_path, other)
        scratch = tmp_path / "w1-tmp"
        scratch.mkdir()
        c = Cluster(tmp_path, env={"CONTAINERS_CONF": podman_env["CONTAINERS_CONF"],
                                   "CONTAINERS_REGISTRIES_CONF": str(conf)})
        c.start_server()
        try:
            c.osmo("credential", "set", f"registry://{private.host}", "--payload",
                   "username=robot", "--payload", f"password={password}", check=True)
            c.start_worker("w1", "--runtime", "container", env={"TMPDIR": str(scratch)})
            wf = c.osmo.submit(write(tmp_path / "wf.yaml", f"""
workflow:
  name: private
  tasks:
  - name: mine
    image: {private.host}/team/img:1
    command: ["true"]
  - name: theirs
    image: {other.host}/team/img:1
    command: ["true"]
"""))
            info = c.osmo.wait_for(wf, ended, timeout=120)
            rows = tasks(c.osmo, wf)
            shown = json.dumps(c.osmo.query(wf)) + c.osmo("logs", wf).out
            shown += c.worker_log("w1") + (c.osmo.home / "server.log").read_text()
        finally:
            c.stop()
    assert info["status"] == "FAILED", json.dumps(info)
    for name, registry in (("mine", private), ("theirs", other)):
        assert rows[name]["status"] == "FAILED_START_ERROR", rows[name]
        assert f"image '{registry.host}/team/img:1' not found:" in rows[name]["message"]
        assert "manifest unknown" in rows[name]["message"]  # the registry was asked
    assert private.authorizations and set(private.authorizations) == {f"robot:{password}"}
    assert all(password not in a for a in other.authorizations)  # nor any other registry
    assert private.seen_in_processes == [] and other.seen_in_processes == []  # argv, env
    assert f"pull: Trying to pull {private.host}/team/img:1..." in shown  # the worker's log
    assert password not in shown and basic not in shown
    assert _files_holding(tmp_path / "w1", password, basic) == []
    assert list(scratch.iterdir()) == []  # the private auth folder is gone
