"""A node that cannot sandbox its tasks says so loudly, or refuses to start (real processes).

Issue #26 item 5: with ``--sandbox auto`` and no working bubblewrap, a pool used to run its
tasks unsandboxed without a word at start. Now the server and a worker log a WARNING naming
why (``UNSANDBOXED: ...``), ``osmo server start`` prints it, and ``osmo resource list`` shows ``none (why)`` for that
node; ``--sandbox on`` refuses to start (exit 3) with bubblewrap's reason.

bubblewrap is made unavailable for the tested process only: a ``PATH`` without ``bwrap``
(the CLI, the server and the worker run by full path), or a ``PATH`` whose ``bwrap`` fails the
way it does where user namespaces are forbidden.
"""

from __future__ import annotations

import shutil
from collections.abc import Iterator
from pathlib import Path

import pytest

from osmo.errors import UsageError
from osmo.scheduler.types import Capacity, Node
from osmo.transport.wire import Hello
from tests.conftest import Osmo
from tests.e2e.cluster import Cluster

NAMESPACES_REFUSED = ("bwrap: No permissions to create new namespace, likely because the "
                      "kernel does not allow non-privileged user namespaces.")


def failing_bwrap(folder: Path) -> str:
    """A folder holding a ``bwrap`` that fails as where user namespaces are forbidden.

    The sandbox's other helpers (util-linux's ``setpriv`` and ``nsenter``, which enter the
    node's namespaces) are the real ones: only bubblewrap fails.
    """
    folder.mkdir(parents=True, exist_ok=True)
    fake = folder / "bwrap"
    fake.write_text(f"#!/bin/sh\necho '{NAMESPACES_REFUSED}' >&2\nexit 1\n")
    fake.chmod(0o755)
    for helper in ("setpriv", "nsenter", "slirp4netns"):
        found = shutil.which(helper)
        if found is not None:
            (folder / helper).symlink_to(found)
    return str(folder)


# (PATH for the server, what `osmo resource list` says, a fragment of the logged reason)
CASES = {
    "bwrap-missing": (lambda tmp: "/nonexistent", "none (bwrap not found)",
                      "install the 'bubblewrap' package"),
    "namespaces-refused": (lambda tmp: failing_bwrap(tmp / "fakebin"),
                           "none (user namespaces refused)", NAMESPACES_REFUSED),
}


@pytest.mark.parametrize("case", sorted(CASES))
def test_a_server_without_a_sandbox_warns_and_shows_why(case: str, tmp_path: Path) -> None:
    path, shown, reason = CASES[case]
    osmo = Osmo(tmp_path / "home")
    osmo.env["PATH"] = path(tmp_path)
    try:
        r = osmo("server", "start", timeout=60)
        assert r.code == 0, r
        assert "UNSANDBOXED: " in r.err and reason in r.err, r.err
        log = (osmo.home / "server.log").read_text()
        warned = [ln for ln in log.splitlines() if "WARNING" in ln and "UNSANDBOXED" in ln]
        assert len(warned) == 1 and reason in warned[0], log
        nodes = osmo("resource", "list", "--format", "json", check=True).json()
        assert [(n["node"], n["sandbox"], n["sandbox_why"]) for n in nodes] == [
            ("local", "none", shown[len("none ("):-1])]
        table = osmo("resource", "list", check=True).out
        assert shown in table, table
    finally:
        osmo.stop_server()


@pytest.mark.parametrize("case", sorted(CASES))
def test_a_server_with_sandbox_on_refuses_to_start(case: str, tmp_path: Path) -> None:
    path, _, reason = CASES[case]
    osmo = Osmo(tmp_path / "home")
    osmo.env["PATH"] = path(tmp_path)
    r = osmo("server", "start", "--sandbox", "on", timeout=60)
    assert r.code == 3, r
    assert "--sandbox on" in r.err and reason in r.err and "Traceback" not in r.err, r.err
    assert osmo.server_pid() is None


def test_a_sandboxed_server_shows_no_reason(tmp_path: Path) -> None:
    osmo = Osmo(tmp_path / "home")
    try:
        r = osmo("server", "start", "--sandbox", "on", timeout=60)
        assert r.code == 0 and "UNSANDBOXED" not in r.err, r
        nodes = osmo("resource", "list", "--format", "json", check=True).json()
        assert [(n["sandbox"], n["sandbox_why"]) for n in nodes] == [("bwrap", None)]
        off = Osmo(tmp_path / "off")
        r = off("server", "start", "--sandbox", "off", timeout=60)
        try:  # no warning for what the operator chose, but the table still says why
            assert r.code == 0 and "UNSANDBOXED" not in r.err, r
            assert "UNSANDBOXED" not in (off.home / "server.log").read_text()
            assert "none (--sandbox off)" in off("resource", "list", check=True).out
        finally:
            off.stop_server()
    finally:
        osmo.stop_server()


@pytest.fixture
def cluster(tmp_path: Path) -> Iterator[Cluster]:
    with Cluster.started(tmp_path) as started:
        yield started


def test_a_worker_without_a_sandbox_warns_and_the_server_shows_why(cluster: Cluster) -> None:
    cluster.start_worker("w1", env={"PATH": "/nonexistent"})
    cluster.start_worker("w2", "--sandbox", "on")
    nodes = cluster.nodes()
    assert (nodes["w1"]["sandbox"], nodes["w1"]["sandbox_why"]) == ("none", "bwrap not found")
    assert (nodes["w2"]["sandbox"], nodes["w2"]["sandbox_why"]) == ("bwrap", None)
    table = cluster.osmo("resource", "list", check=True).out
    assert "none (bwrap not found)" in table, table
    pools = cluster.osmo("pool", "list", "--format", "json", check=True).json()
    assert [p["sandbox"] for p in pools] == ["none on 1 of 2"]
    log = cluster.worker_log("w1")
    assert "UNSANDBOXED: " in log and "install the 'bubblewrap' package" in log, log
    assert "UNSANDBOXED" not in cluster.worker_log("w2")


def test_a_worker_with_sandbox_on_refuses_to_start(cluster: Cluster) -> None:
    proc = cluster.start_worker("w1", "--sandbox", "on", env={"PATH": "/nonexistent"},
                                wait=False)
    assert proc.wait(timeout=60) == 3
    log = cluster.worker_log("w1")
    assert "--sandbox on" in log and "install the 'bubblewrap' package" in log, log
    assert "Traceback" not in log, log
    assert "w1" not in cluster.nodes()


def test_a_hello_without_the_reason_still_registers() -> None:
    """A worker from before ``sandbox_why``: its hello is read, the reason unknown (None)."""
    node = Node(id="old", pool="default", capacity=Capacity(cpu=1.0), address="127.0.0.1",
                labels={"sandbox": "none"})
    sent = Hello(node, runtime="process").to_dict()
    assert Hello.from_dict(sent) == Hello(node, runtime="process")
    del sent["sandbox_why"]
    assert Hello.from_dict(sent).sandbox_why is None
    why = Hello(node, sandbox_why="bwrap not found")
    assert Hello.from_dict(why.to_dict()).sandbox_why == "bwrap not found"
    with pytest.raises(UsageError, match="sandbox_why"):
        Hello.from_dict({**sent, "sandbox_why": 7})
