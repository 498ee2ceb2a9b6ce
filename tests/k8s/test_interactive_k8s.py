"""``osmo workflow exec`` and ``port-forward`` into a pod, on the wire: through the real CLI,
a server and ``osmo worker --runtime kubernetes``, whose node reaches the pod only through
the API's ``pods/exec`` and ``pods/portforward`` WebSockets (served by the stand-in, run by
``podman exec`` and a connection to the pod's port); the session is relayed over zenoh as on
every node. The exec test with stdin and cancel is ``test_tutorials_k8s.py``'s.
"""

from __future__ import annotations

import hashlib
import socket
import subprocess
import sys
import time
import urllib.request
from collections.abc import Iterator
from pathlib import Path

import pytest

from osmo.config import free_port
from tests.conftest import REPO, Osmo, retry_oserror, write
from tests.containers.conftest import images, podman_env  # noqa: F401 - fixtures
from tests.k8s.nodes import KubeCluster, started
from tests.k8s.store import PODS


@pytest.fixture(scope="module")
def kube(tmp_path_factory: pytest.TempPathFactory, podman_env: dict[str, str],  # noqa: F811
         images: dict[str, str]) -> Iterator[KubeCluster]:  # noqa: F811
    for cluster in started(tmp_path_factory.mktemp("k8s-interactive"), podman_env):
        cluster.start_worker("kube-1", groupNetwork="host")
        yield cluster


def _phase(kube: KubeCluster, wf: str) -> str | None:
    """The phase of the (one) pod of workflow ``wf`` in the stand-in (None: no pod)."""
    for _, obj in kube.server.store.objects([PODS]):
        if obj["metadata"].get("labels", {}).get("osmo.dev/workflow") == wf:
            return str((obj.get("status") or {}).get("phase"))
    return None


def _running(kube: KubeCluster, spec: Path) -> str:
    """Submit ``spec``; wait until its pod runs; the workflow id."""
    wf = kube.osmo.submit(spec)
    deadline = time.monotonic() + 120
    while _phase(kube, wf) != "Running":
        assert time.monotonic() < deadline, kube.osmo.query(wf)
        time.sleep(0.2)
    return wf


def _forward(osmo: Osmo, wf: str, ports: str) -> subprocess.Popen[str]:
    proc = subprocess.Popen([sys.executable, "-m", "osmo", "workflow", "port-forward", wf, "t",
                             "--port", ports], stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            text=True, env=osmo.env, cwd=REPO)
    assert proc.stdout is not None
    line = proc.stdout.readline()
    assert line.startswith("Forwarding from"), (line, proc.stderr and proc.stderr.read())
    return proc


def _echo(port: int, payload: bytes, *, half_close: bool) -> bytes:
    """Send ``payload`` to an echo server at ``port``; what comes back (up to its size)."""
    with socket.create_connection(("127.0.0.1", port), timeout=60) as sock:
        sock.sendall(payload)
        if half_close:
            sock.shutdown(socket.SHUT_WR)
        got = b""
        while len(got) < len(payload):
            data = sock.recv(65536)
            if not data:
                raise ConnectionResetError(f"closed after {len(got)} bytes")
            got += data
        return got


WEB = """
workflow:
  name: web
  tasks:
  - name: t
    image: alpine:3.18
    command: [sh, -c, "cd {{{{output}}}} && mkdir www && head -c 300000 /dev/urandom > www/blob && httpd -f -p 127.0.0.1:{http} -h www & exec nc -ll -p {echo} -e cat"]
"""


def test_port_forward_reaches_the_pods_ports_through_the_api(kube: KubeCluster,
                                                            tmp_path: Path) -> None:
    """Bytes both ways to two servers in the task's container (busybox ``httpd`` and an
    ``nc`` echo), each connection a ``pods/portforward`` WebSocket of its own."""
    http, echo, local_http, local_echo = (free_port(0) for _ in range(4))
    wf = _running(kube, write(tmp_path / "web.yaml", WEB.format(http=http, echo=echo)))
    before = kube.server.calls[("get", "pods/portforward")]
    proc = _forward(kube.osmo, wf, f"{local_http}:{http},{local_echo}:{echo}")
    try:
        body = retry_oserror(lambda: urllib.request.urlopen(
            f"http://127.0.0.1:{local_http}/blob", timeout=60).read(), timeout=60)
        want = kube.osmo("workflow", "exec", wf, "t", "--", "sha256sum",
                         "/osmo/data/output/www/blob")
        assert want.code == 0, want
        assert hashlib.sha256(body).hexdigest() == want.out.split()[0]
        payload = bytes(range(256)) * 1000
        assert retry_oserror(lambda: _echo(local_echo, payload, half_close=False),
                             timeout=60) == payload
        # the API's port-forward has no half-close: the answer still comes back
        assert _echo(local_echo, b"last words\n", half_close=True) == b"last words\n"
    finally:
        proc.kill()
        proc.communicate(timeout=30)
        kube.osmo("cancel", wf)
    assert kube.server.calls[("get", "pods/portforward")] - before >= 3, kube.server.calls


SLEEPER = """
workflow:
  name: {name}
  tasks:
  - name: {task}
    image: alpine:3.18
    command: ["sh", "-c", "exec sleep 300"]
    environment: {{WHO: {name}}}
"""


def test_exec_and_port_forward_reach_only_their_own_running_pod(kube: KubeCluster,
                                                               tmp_path: Path) -> None:
    """Hostile: a session names a workflow and task, and reaches that attempt's pod only:
    another workflow's task is not found, a finished attempt is refused, and a port nothing
    listens on ends its connection (the session goes on serving)."""
    done = kube.osmo.submit(write(tmp_path / "done.yaml", SLEEPER.format(
        name="done", task="t").replace("exec sleep 300", "true")), "--wait")
    mine = _running(kube, write(tmp_path / "mine.yaml", SLEEPER.format(name="mine", task="t")))
    other = _running(kube, write(tmp_path / "other.yaml",
                                 SLEEPER.format(name="other", task="secret")))
    try:
        r = kube.osmo("workflow", "exec", mine, "t", "--", "sh", "-c", 'echo "$WHO"')
        assert (r.code, r.out) == (0, "mine\n"), r
        r = kube.osmo("workflow", "exec", other, "secret", "--", "sh", "-c", 'echo "$WHO"')
        assert (r.code, r.out) == (0, "other\n"), r
        r = kube.osmo("workflow", "exec", mine, "secret", "--", "true")
        assert r.code == 2 and "no task 'secret'" in r.err, r
        for verb in (("exec", done, "t", "--", "true"),
                     ("port-forward", done, "t", "--port", str(free_port(0)))):
            r = kube.osmo("workflow", *verb)
            assert r.code == 2 and "COMPLETED, not RUNNING" in r.err, r
        local = free_port(0)
        proc = _forward(kube.osmo, mine, f"{local}:{free_port(0)}")
        try:
            for _ in range(2):  # nothing listens: each connection ends, none hangs
                with socket.create_connection(("127.0.0.1", local), timeout=60) as sock:
                    sock.settimeout(60)
                    try:
                        assert sock.recv(1) == b""
                    except ConnectionResetError:
                        pass
            assert proc.poll() is None
        finally:
            proc.kill()
            proc.communicate(timeout=30)
    finally:
        kube.osmo("cancel", mine)
        kube.osmo("cancel", other)
    assert "Traceback" not in (kube.osmo.home / "server.log").read_text()
