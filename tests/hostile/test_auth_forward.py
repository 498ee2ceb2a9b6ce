"""Port-forward reaches the task's own ports only, never another process's on the node.

Issue 26 (low): port-forward granted any port on the node's loopback, so the owner of any
running task could reach the server's listener, a database or another user's task on that
node. OSMO forwards to ports of the task's pod, its own network namespace; osmo's process
tasks share the node's network, so a forwarded port must be one a process of the task listens
on, and the connection goes to the address it listens on.
"""

from __future__ import annotations

import socket
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from pathlib import Path

import pytest

from osmo.config import free_port
from tests.conftest import REPO, Osmo, write
from tests.e2e.cluster import Cluster

TASK = """
import os, socket, threading, time
def serve(s, text):
    s.listen()
    while True:
        c, _ = s.accept(); c.sendall(text); c.close()
own = socket.socket(); own.bind(("127.0.0.1", 0))
shared = socket.socket(); shared.bind(("127.0.0.2", {shared}))
threading.Thread(target=serve, args=(own, b"task-own\\n"), daemon=True).start()
threading.Thread(target=serve, args=(shared, b"task-shared\\n"), daemon=True).start()
open("{ready}.tmp", "w").write(str(own.getsockname()[1])); os.rename("{ready}.tmp", "{ready}")
time.sleep(600)
"""


@pytest.fixture
def cluster(tmp_path: Path) -> Iterator[Cluster]:
    c = Cluster(tmp_path)
    c.server_args = tuple(a for a in c.server_args if a != "--no-local-pool")
    c.start_server()
    yield c
    c.stop()


def _outsider(stop: threading.Event) -> socket.socket:
    """A process of the node (this test) listening on loopback."""
    server = socket.socket()
    server.bind(("127.0.0.1", 0))
    server.listen()
    server.settimeout(0.2)

    def serve() -> None:
        while not stop.is_set():
            try:
                conn, _ = server.accept()
            except OSError:
                continue
            conn.sendall(b"NODE-SECRET\n")
            conn.close()

    threading.Thread(target=serve, daemon=True).start()
    return server


def _read(port: int, *, wait: bool) -> bytes:
    """What a connection through the forwarded ``port`` reads (retried while empty if ``wait``)."""
    deadline = time.monotonic() + (30 if wait else 3)
    while True:
        try:
            with socket.create_connection(("127.0.0.1", port), timeout=10) as conn:
                data = conn.recv(100)
        except OSError:
            data = b""
        if data or time.monotonic() > deadline:
            return data
        time.sleep(0.3)


def test_port_forward_reaches_only_ports_the_task_listens_on(cluster: Cluster,
                                                             tmp_path: Path) -> None:
    stop = threading.Event()
    outsider = _outsider(stop)
    shared = outsider.getsockname()[1]  # the task listens on it too, on 127.0.0.2
    ready = tmp_path / "own-port"
    spec = write(tmp_path / "ports.yaml", "workflow:\n  name: ports\n  tasks:\n  - name: t\n"
                 f"    command: [{sys.executable}, -c]\n    args:\n    - |\n" + "".join(
                     f"      {line}\n" for line in TASK.format(shared=shared, ready=ready)
                     .splitlines() if line))
    osmo: Osmo = cluster.osmo
    wf = osmo.submit(spec)
    deadline = time.monotonic() + 60
    while not ready.exists():
        assert time.monotonic() < deadline, osmo("logs", wf).out
        time.sleep(0.1)
    own = int(ready.read_text())
    local = [free_port(0) for _ in range(3)]
    proc = subprocess.Popen(
        [sys.executable, "-m", "osmo", "workflow", "port-forward", wf, "t",
         "--port", f"{local[0]}:{own},{local[1]}:{shared},{local[2]}:{cluster.port}"],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=osmo.env, cwd=REPO,
        start_new_session=True)
    try:
        assert proc.stdout is not None and proc.stdout.readline().startswith("Forwarding")
        got = [_read(port, wait=want) for port, want in
               zip(local, (True, True, False), strict=True)]
    finally:
        proc.kill()
        _, err = proc.communicate(timeout=30)
        stop.set()
        outsider.close()
        osmo("cancel", wf)
    assert got[0] == b"task-own\n", err
    assert got[1] == b"task-shared\n", "reached another process of the node"
    assert got[2] == b"", "reached the server's own listener"
    assert f"no process of the task listens on TCP port {cluster.port}" in err, err
