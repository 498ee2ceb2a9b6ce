"""A sandboxed task cannot reach the control plane over the network (end to end, CLI).

The attack: a task connects to what listens on the host's loopback (the server's and the
zenoh router's listeners, a user's database) or to the host's Unix sockets, abstract ones
included. Every address a task could try is tried: the loopback addresses, ``localhost``,
the wildcard addresses, the host's own address, its namespace's addresses, gateways and
name servers. What must keep working: a listener on the host's outbound address (standing
in for any remote service) is reachable.
"""

from __future__ import annotations

import json
import os
import socket
import threading
import uuid
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

from tests.conftest import Osmo, ended, write
from tests.e2e.cluster import Cluster

PROBE = r'''
import json, os, socket, sys, threading
closed_ports = [int(p) for p in sys.argv[1].split(",")]
open_host, open_port = sys.argv[2], int(sys.argv[3])
abstract, paths, out = sys.argv[4], sys.argv[5].split(","), sys.argv[6]
hosts = {"127.0.0.1", "127.0.0.2", "127.1.2.3", "localhost", "::1", "0.0.0.0", "::",
         "10.0.2.2", "10.0.2.3", "10.0.2.100", open_host}
try:  # gateways of its routes
    for line in open("/proc/net/route").read().splitlines()[1:]:
        gw = int(line.split()[2], 16)
        if gw:
            hosts.add(socket.inet_ntoa(gw.to_bytes(4, "little")))
except OSError:
    pass
try:  # its own addresses
    words = open("/proc/net/fib_trie").read().split()
    hosts.update(w for w in words if w.count(".") == 3 and w[0].isdigit() and "/" not in w)
except OSError:
    pass
try:
    hosts.update(line.split()[1] for line in open("/etc/resolv.conf")
                 if line.startswith("nameserver"))
except (OSError, IndexError):
    pass
reached, lock = [], threading.Lock()
def attempt(host, port):
    try:
        with socket.create_connection((host, port), timeout=2):
            with lock:
                reached.append(f"{host}:{port}")
    except OSError:
        pass
threads = [threading.Thread(target=attempt, args=(h, p)) for h in hosts for p in closed_ports]
for t in threads: t.start()
for t in threads: t.join()
for name in [abstract] + paths:
    s = socket.socket(socket.AF_UNIX)
    try:
        s.connect("\0" + name if name == abstract else name)
        reached.append("unix:" + name)
    except OSError:
        pass
    s.close()
try:
    socket.create_connection((open_host, open_port), timeout=10).close()
    outbound = True
except OSError as exc:
    outbound = repr(exc)
json.dump({"reached": sorted(reached), "outbound": outbound, "tried": sorted(hosts)},
          open(out + "/net.json", "w"))
'''


def outbound_address() -> str:
    """This host's address on its outbound interface (how remote peers reach it)."""
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.connect(("10.255.255.255", 1))  # no packet is sent
        return str(s.getsockname()[0])


@contextmanager
def listeners(host_address: str) -> Iterator[dict[str, object]]:
    """Listeners a task must not reach (loopback TCP, abstract and path Unix sockets) and
    one it must reach (on the host's outbound address); each accepts and closes."""
    made: list[socket.socket] = []

    def listen(family: int, address: object) -> socket.socket:
        s = socket.socket(family, socket.SOCK_STREAM)
        s.bind(address)
        s.listen(64)
        made.append(s)
        threading.Thread(target=_accept_all, args=(s,), daemon=True).start()
        return s

    tag = f"osmo-test-{uuid.uuid4().hex[:12]}"
    path = Path(f"/run/{tag}.sock")
    loop = listen(socket.AF_INET, ("127.0.0.1", 0))
    ports = [loop.getsockname()[1]]
    if socket.has_ipv6:
        try:
            ports.append(listen(socket.AF_INET6, ("::1", 0)).getsockname()[1])
        except OSError:
            pass
    listen(socket.AF_UNIX, "\0" + tag)
    listen(socket.AF_UNIX, str(path))
    outside = listen(socket.AF_INET, (host_address, 0))
    try:
        yield {"ports": ports, "abstract": tag, "paths": [str(path)],
               "open": (host_address, outside.getsockname()[1])}
    finally:
        for s in made:
            s.close()
        path.unlink(missing_ok=True)


def _accept_all(s: socket.socket) -> None:
    while True:
        try:
            conn, _ = s.accept()
        except OSError:
            return
        conn.close()


def probe_spec(tmp_path: Path, found: dict[str, object], extra_ports: tuple[int, ...] = ()
               ) -> Path:
    ports = ",".join(str(p) for p in [*found["ports"], *extra_ports])  # type: ignore[misc]
    host, port = found["open"]  # type: ignore[misc]
    paths = ",".join(found["paths"])  # type: ignore[arg-type]
    return write(tmp_path / "probe.yaml", f"""
workflow:
  name: probe
  tasks:
  - name: probe
    command: [python3, /tmp/probe.py, "{ports}", "{host}", "{port}", "{found['abstract']}",
              "{paths}", "{{{{output}}}}"]
    files:
    - path: /tmp/probe.py
      contents: {json.dumps(PROBE)}
""")


def check(result: dict[str, object], *, outbound: bool = True) -> None:
    assert result["reached"] == [], f"a task reached the host's listeners: {result}"
    assert result["outbound"] is True or not outbound, f"no outbound connectivity: {result}"
    assert "127.0.0.1" in result["tried"] and len(result["tried"]) >= 10, result  # type: ignore[operator]


def test_a_task_reaches_nothing_on_the_hosts_loopback_but_reaches_out(
        osmo: Osmo, tmp_path: Path) -> None:
    with listeners(outbound_address()) as found:
        wf = osmo.submit(probe_spec(tmp_path, found))
        info = osmo.wait_for(wf, ended, timeout=180)
    assert info["status"] == "COMPLETED", osmo("logs", wf).out
    check(json.loads((Path(info["tasks"][0]["output"]) / "net.json").read_text()))


def test_a_workers_task_cannot_reach_the_router_on_the_hosts_loopback(tmp_path: Path) -> None:
    """A remote worker's task: the zenoh router listens on tcp/127.0.0.1:PORT."""
    cluster = Cluster(tmp_path)
    try:
        cluster.start_server()
        cluster.start_worker("w1")
        with listeners(outbound_address()) as found:
            wf = cluster.osmo.submit(probe_spec(tmp_path, found, (cluster.port,)))
            info = cluster.osmo.wait_for(wf, ended, timeout=180)
        assert info["status"] == "COMPLETED", cluster.osmo("logs", wf).out
        got = tmp_path / "got"
        cluster.osmo("artifacts", "get", f"{wf}:probe", "-o", str(got), check=True)
        result = json.loads((got / "net.json").read_text())
        check(result, outbound=False)  # (the worker's own address is its tasks' here)
        assert f"127.0.0.1:{cluster.port}" not in result["reached"]
    finally:
        cluster.stop()


SERVE = """
import socket, sys
s = socket.socket()
s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
s.bind((sys.argv[1], int(sys.argv[2])))
s.listen()
conn, _ = s.accept()
conn.sendall(b"hello")
conn.close()
"""

ASK = """
import socket, sys, time
for _ in range(600):
    try:
        conn = socket.create_connection((sys.argv[1], int(sys.argv[2])))
        break
    except OSError:
        time.sleep(0.1)
open(sys.argv[3] + "/got", "wb").write(conn.recv(5))
"""


def _pair(tmp_path: Path, port: int) -> Path:
    """A group whose client asks its server, at ``{{host:server}}`` on ``port``, for 5 bytes."""
    return write(tmp_path / "group.yaml", f"""
workflow:
  name: pair
  groups:
  - name: g
    tasks:
    - name: server
      command: [python3, /tmp/serve.py, "{{{{host:server}}}}", "{port}"]
      files: [{{path: /tmp/serve.py, contents: {json.dumps(SERVE)}}}]
    - name: client
      lead: true
      command: [python3, /tmp/ask.py, "{{{{host:server}}}}", "{port}", "{{{{output}}}}"]
      files: [{{path: /tmp/ask.py, contents: {json.dumps(ASK)}}}]
""")


def test_tasks_of_a_group_reach_each_other_on_the_nodes_network(osmo: Osmo,
                                                                tmp_path: Path) -> None:
    """``{{host:NAME}}`` of the local pool is 127.0.0.1: the node's own loopback, which every
    task of the node shares (not the host's)."""
    spec = _pair(tmp_path, 20000 + os.getpid() % 20000)
    info = osmo.wait_for(osmo.submit(spec), ended, timeout=120)
    assert info["status"] == "COMPLETED", info
    client = [t for t in info["tasks"] if t["name"] == "client"][0]
    assert (Path(client["output"]) / "got").read_bytes() == b"hello"


def test_tasks_of_a_group_reach_each_other_on_a_workers_address(tmp_path: Path) -> None:
    """On a remote worker ``{{host:NAME}}`` is the worker's address: its tasks listen on it
    and reach each other there, inside the worker's task network."""
    cluster = Cluster(tmp_path)
    try:
        cluster.start_server()
        cluster.start_worker("w1")
        spec = _pair(tmp_path, 20000 + (os.getpid() + 7) % 20000)
        wf = cluster.osmo.submit(spec)
        info = cluster.osmo.wait_for(wf, ended, timeout=120)
        assert info["status"] == "COMPLETED", cluster.osmo("logs", wf).out
        got = tmp_path / "got"
        cluster.osmo("artifacts", "get", f"{wf}:client", "-o", str(got), check=True)
        assert (got / "got").read_bytes() == b"hello"
    finally:
        cluster.stop()
