"""``osmo workflow exec`` and ``osmo workflow port-forward`` end to end.

One server with its local pool and one remote worker (pool ``remote``), as real processes on
loopback; the CLI runs as a real process, through a pseudo-terminal for the TTY tests.
"""

from __future__ import annotations

import concurrent.futures
import hashlib
import json
import os
import select
import signal
import socket
import subprocess
import sys
import threading
import time
import urllib.request
from collections.abc import Iterator
from pathlib import Path

import pytest

from osmo.config import free_port
from osmo.errors import NotAllowed
from osmo.transport.rpc import ApiClient
from osmo.transport.streams import Frame, Kind, SessionGrant, Stream
from osmo.transport.zenoh_link import Link
from tests.conftest import REPO, Osmo, retry_oserror, unique_sleep, wait_no_process, write
from tests.e2e.cluster import Cluster

LOCAL, REMOTE = "local", "remote"


@pytest.fixture(scope="module")
def cluster(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Cluster]:
    c = Cluster(tmp_path_factory.mktemp("interactive"))
    c.server_args = tuple(a for a in c.server_args if a != "--no-local-pool")
    c.start_server()
    c.start_worker("w1", "--cpus", "4", pool=REMOTE)
    yield c
    c.stop()


def _running(osmo: Osmo, spec: Path, pool: str, task: str = "t") -> str:
    """Submit ``spec`` to ``pool``; wait until ``task`` runs; return the workflow id."""
    wf = osmo.submit(spec, "--pool", pool)
    osmo.wait_for(wf, lambda i: any(t["name"] == task and t["status"] == "RUNNING"
                                    for t in i["tasks"]) or i["status"] not in
                  ("PENDING", "RUNNING", "WAITING"))
    return wf


def _sleeper(tmp_path: Path, name: str) -> Path:
    return write(tmp_path / f"{name}.yaml", f"""
workflow:
  name: {name}
  tasks:
  - name: t
    command: [sh, -c, "echo ready > note.txt; exec sleep 600"]
    environment: {{GREETING: hola}}
""")


def _user(cluster: Cluster, name: str, role: str = "user") -> Osmo:
    osmo = Osmo(cluster.osmo.home)
    osmo.env["OSMO_TOKEN"] = cluster.token(name, role)
    return osmo


@pytest.mark.parametrize("pool", [LOCAL, REMOTE])
def test_exec_runs_a_command_in_the_task_with_its_output_and_exit_code(
        cluster: Cluster, tmp_path: Path, pool: str) -> None:
    wf = _running(cluster.osmo, _sleeper(tmp_path, f"ex-{pool}"), pool)
    try:
        r = cluster.osmo("workflow", "exec", wf, "t", "--", "sh", "-c",
                         'cat note.txt; echo "$GREETING $OSMO_TASK"; echo oops >&2; exit 7')
        assert r.code == 7, r.err
        assert r.out == "ready\nhola t\n" and r.err == "oops\n"
        # stdin is relayed, and its end passed on
        proc = subprocess.run([sys.executable, "-m", "osmo", "workflow", "exec", wf, "t", "--",
                               "wc", "-c"], input=b"x" * 300_000, capture_output=True,
                              env=cluster.osmo.env, cwd=REPO, timeout=60)
        assert proc.returncode == 0 and proc.stdout.strip() == b"300000", proc.stderr
        r = cluster.osmo("workflow", "exec", wf, "t", "--", "no-such-command-xyz")
        assert r.code != 0 and "no-such-command-xyz" in r.err
    finally:
        cluster.osmo("cancel", wf)


def _read_until(fd: int, marker: bytes, timeout: float = 30) -> bytes:
    seen = b""
    deadline = time.monotonic() + timeout
    while marker not in seen:
        if time.monotonic() > deadline:
            raise AssertionError(f"never saw {marker!r}; got {seen!r}")
        if select.select([fd], [], [], 0.2)[0]:
            try:
                seen += os.read(fd, 4096)
            except OSError:
                break
    return seen


@pytest.mark.parametrize("pool", [LOCAL, REMOTE])
def test_exec_with_a_tty_types_interrupts_and_exits(cluster: Cluster, tmp_path: Path,
                                                     pool: str) -> None:
    wf = _running(cluster.osmo, _sleeper(tmp_path, f"tty-{pool}"), pool)
    master, slave = os.openpty()
    proc = subprocess.Popen([sys.executable, "-m", "osmo", "workflow", "exec", wf, "t"],
                            stdin=slave, stdout=slave, stderr=slave, env=cluster.osmo.env,
                            cwd=REPO, start_new_session=True)
    os.close(slave)
    try:
        os.write(master, b"echo A$((40+2))B; stty size\n")
        assert b"24 80" in _read_until(master, b"24 80")  # its terminal, sized as ours
        os.write(master, b"sleep 300; echo slept\n")
        time.sleep(1.0)
        os.write(master, b"\x03")  # Ctrl-C: a byte, a SIGINT to the remote job
        os.write(master, b"echo after-$((1+1))\n")
        assert b"\nslept" not in _read_until(master, b"after-2")  # sleep was interrupted
        os.write(master, b"exit 5\n")
        assert proc.wait(timeout=30) == 5
    finally:
        os.close(master)
        if proc.poll() is None:
            proc.kill()
        cluster.osmo("cancel", wf)


def test_exec_and_forward_refuse_other_users_workers_and_tasks_not_running(
        cluster: Cluster, tmp_path: Path) -> None:
    wf = _running(cluster.osmo, _sleeper(tmp_path, "refuse"), REMOTE)  # the admin's
    done = cluster.osmo.submit(write(tmp_path / "done.yaml", """
workflow:
  name: done
  tasks:
  - name: t
    command: ["true"]
"""), "--pool", LOCAL, "--wait")
    try:
        bob, worker = _user(cluster, "bob"), _user(cluster, "w-token", "worker")
        for verb in (("exec", wf, "t", "--", "id"), ("port-forward", wf, "t", "--port",
                                                       str(free_port(0)))):
            r = bob("workflow", *verb)
            assert r.code == 2 and "not allowed" in r.err and "only they or an admin" in r.err
            r = worker("workflow", *verb)
            assert r.code == 2 and "not allowed" in r.err and "worker" in r.err
        r = cluster.osmo("workflow", "exec", done, "t", "--", "true")
        assert r.code == 2 and "COMPLETED, not RUNNING" in r.err
        r = cluster.osmo("workflow", "exec", wf, "tt", "--", "true")
        assert r.code == 2 and "no task 'tt'" in r.err
        r = cluster.osmo("workflow", "exec", wf, "t", "--group", "g", "--", "true")
        assert r.code == 2 and "no task 't' in group" in r.err
        r = cluster.osmo("workflow", "exec", "nope-1", "t")
        assert r.code == 2 and "no workflow" in r.err
        # bob's own workflow: allowed
        mine = _running(bob, _sleeper(tmp_path, "bobs"), LOCAL)
        r = bob("workflow", "exec", mine, "t", "--", "echo", "mine")
        assert r.code == 0 and r.out == "mine\n", r.err
        bob("cancel", mine)
    finally:
        cluster.osmo("cancel", wf)
    assert "Traceback" not in (cluster.osmo.home / "server.log").read_text()


def test_a_session_order_is_useless_to_another_worker(cluster: Cluster, tmp_path: Path) -> None:
    """A rogue worker that hears a session order gets nothing from it: no grant, no ticket.

    Orders are sealed for their worker (``osmo.transport.seal``), and hold a one-time ticket
    only. The worker the order is for is paused (well within its 1 s lease) so that the
    rogue tries first; the ticket still works for its own worker afterwards.
    """
    rogue_token = cluster.token("rogue", pool="other")
    cluster.start_worker("rogue", "--cpus", "1", pool="other", token=rogue_token)
    wf = _running(cluster.osmo, _sleeper(tmp_path, "rogue"), REMOTE)
    link = Link.client([cluster.endpoint])
    orders: list[bytes] = []
    got = threading.Event()
    sub = link.subscribe_raw(link.key("to-worker", "w1"),
                             lambda _key, order, _att: (orders.append(order), got.set()))
    admin = ApiClient(link, token=(cluster.osmo.home / "auth" / "admin.token").read_text())
    rogue = ApiClient(link, token=rogue_token)
    refusals = []
    try:
        cluster.signal("w1", signal.SIGSTOP)
        try:
            reply = admin.call("exec_open", {"workflow_id": wf, "task": "t",
                                             "command": ["true"]})
            assert got.wait(5)
            for speaks_for in ("rogue", "w1"):  # its own id, or the id it spies on
                try:  # the best it has: the sealed order's bytes as a ticket
                    rogue.call("worker_session", {"id": speaks_for,
                                                  "ticket": orders[0].hex()[:64]})
                except NotAllowed as exc:
                    refusals.append(str(exc))
        finally:
            cluster.signal("w1", signal.SIGCONT)
        assert len(refusals) == 2 and all("not allowed" in r for r in refusals)
        # the order is sealed: not even its ticket reads in clear, nor the session's id or key
        heard = b"".join(orders)
        assert b'"op"' not in heard and b"ticket" not in heard
        assert reply["grant"]["session_id"].encode() not in heard
        assert reply["grant"]["key"].encode() not in heard
        # and the worker it was for still got its grant: the session runs its command
        ends: list[Frame] = []
        stream = Stream(link, SessionGrant.from_dict(reply["grant"]), "client",
                        lambda f: ends.append(f) if f.kind is Kind.END else None, lambda: None)
        deadline = time.monotonic() + 30
        while not ends and time.monotonic() < deadline:
            stream.send(Kind.HELLO)
            time.sleep(0.2)
        stream.close()
        assert ends and json.loads(ends[0].data) == {"code": 0, "message": ""}
    finally:
        sub.close()
        link.close()
        cluster.osmo("cancel", wf)


def test_the_session_ends_and_its_process_dies_when_the_client_is_killed(
        cluster: Cluster, tmp_path: Path) -> None:
    wf = _running(cluster.osmo, _sleeper(tmp_path, "kill9"), REMOTE)
    marker = unique_sleep()
    proc = subprocess.Popen([sys.executable, "-m", "osmo", "workflow", "exec", wf, "t", "--",
                             "sleep", marker], stdin=subprocess.DEVNULL, env=cluster.osmo.env,
                            cwd=REPO, start_new_session=True)
    try:
        deadline = time.monotonic() + 30
        while not _has_process(marker):
            assert time.monotonic() < deadline and proc.poll() is None, "exec never started"
            time.sleep(0.1)
        os.kill(proc.pid, signal.SIGKILL)
        proc.wait(timeout=10)
        wait_no_process(marker, timeout=30)  # the node noticed the client is gone
        # the task itself goes on
        assert cluster.osmo.query(wf)["status"] == "RUNNING"
    finally:
        if proc.poll() is None:
            proc.kill()
        cluster.osmo("cancel", wf)


def test_sessions_end_when_their_worker_stops(cluster: Cluster, tmp_path: Path) -> None:
    cluster.start_worker("w2", "--cpus", "1", pool="edge")
    wf = _running(cluster.osmo, _sleeper(tmp_path, "stopping"), "edge")
    marker = unique_sleep()
    proc = subprocess.Popen([sys.executable, "-m", "osmo", "workflow", "exec", wf, "t", "--",
                             "sleep", marker], stdin=subprocess.DEVNULL, stderr=subprocess.PIPE,
                            text=True, env=cluster.osmo.env, cwd=REPO, start_new_session=True)
    try:
        deadline = time.monotonic() + 30
        while not _has_process(marker):
            assert time.monotonic() < deadline and proc.poll() is None, "exec never started"
            time.sleep(0.1)
        cluster.signal("w2", signal.SIGINT)  # stop now (SIGTERM would drain)
        _, err = proc.communicate(timeout=30)
        assert proc.returncode == 3 and "the worker is stopping" in err
        wait_no_process(marker, timeout=30)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.communicate()
        cluster.osmo("cancel", wf)


def _has_process(arg: str) -> bool:
    for name in os.listdir("/proc"):
        try:
            if name.isdigit() and arg.encode() in Path(
                    f"/proc/{name}/cmdline").read_bytes().split(b"\0"):
                return True
        except OSError:
            pass
    return False


def _interactive_signals() -> None:
    """In the child: SIGINT as a terminal gives it (a runner that started the suite as a
    background job, ``cmd &`` in a script, passes SIGINT down ignored, and Python keeps it)."""
    signal.signal(signal.SIGINT, signal.SIG_DFL)


def _forward(osmo: Osmo, wf: str, *args: str) -> subprocess.Popen[str]:
    proc = subprocess.Popen([sys.executable, "-m", "osmo", "workflow", "port-forward", wf, "t",
                             *args], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            env=osmo.env, cwd=REPO, start_new_session=True,
                            preexec_fn=_interactive_signals)
    assert proc.stdout is not None
    line = proc.stdout.readline()
    assert line.startswith("Forwarding from"), (line, proc.stderr and proc.stderr.read())
    return proc


def _stop(proc: subprocess.Popen[str]) -> None:
    if proc.poll() is None:
        proc.kill()
    proc.communicate(timeout=30)  # and close its pipes


def test_port_forward_serves_concurrent_fetches_from_a_remote_task(
        cluster: Cluster, tmp_path: Path) -> None:
    port, local = free_port(0), free_port(0)
    spec = write(tmp_path / "web.yaml", f"""
workflow:
  name: web
  tasks:
  - name: t
    command: [sh, -c, "head -c 2500000 /dev/urandom > blob.bin && sha256sum blob.bin > sum.txt && exec {sys.executable} -m http.server {port} --bind 127.0.0.1"]
""")
    wf = _running(cluster.osmo, spec, REMOTE)
    proc = _forward(cluster.osmo, wf, "--port", f"{local}:{port}")
    try:
        url = f"http://127.0.0.1:{local}"
        want = retry_oserror(lambda: urllib.request.urlopen(f"{url}/sum.txt", timeout=30).read())
        with concurrent.futures.ThreadPoolExecutor(20) as pool:
            got = list(pool.map(lambda _: urllib.request.urlopen(f"{url}/blob.bin",
                                                                 timeout=60).read(), range(20)))
        digests = {hashlib.sha256(body).hexdigest() for body in got}
        assert digests == {want.split()[0].decode()}
        assert {len(body) for body in got} == {2_500_000}
        cluster.osmo("cancel", wf)  # the task ends: port-forward says so and exits
        _, err = proc.communicate(timeout=30)
        assert proc.returncode == 0 and "port-forward stopped: the task ended" in err
    finally:
        _stop(proc)
        cluster.osmo("cancel", wf)


@pytest.mark.parametrize("pool", [LOCAL, REMOTE])
def test_port_forward_reaches_a_task_listening_on_every_address(
        cluster: Cluster, tmp_path: Path, pool: str) -> None:
    """A server bound to IPv6's wildcard (dual-stack, ``--bind ::``): the node connects to
    ``::1`` inside the sandboxed tasks' network (it made an IPv4 socket for it and failed)."""
    port, local = free_port(0), free_port(0)
    spec = write(tmp_path / f"any-{pool}.yaml", f"""
workflow:
  name: any-{pool}
  tasks:
  - name: t
    command: [sh, -c, "echo served > page.txt && exec {sys.executable} -m http.server {port} --bind ::"]
""")
    wf = _running(cluster.osmo, spec, pool)
    proc = _forward(cluster.osmo, wf, "--port", f"{local}:{port}")
    try:
        page = retry_oserror(lambda: urllib.request.urlopen(f"http://127.0.0.1:{local}/page.txt",
                                                     timeout=30).read())
        assert page == b"served\n"
    finally:
        _stop(proc)
        cluster.osmo("cancel", wf)


def test_port_forward_udp_echo_and_ctrl_c(cluster: Cluster, tmp_path: Path) -> None:
    port, local = free_port(0), free_port(0)
    spec = write(tmp_path / "udp.yaml", f"""
workflow:
  name: udp
  tasks:
  - name: t
    command: [{sys.executable}, -c]
    args:
    - |
      import socket
      s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
      s.bind(("127.0.0.1", {port}))
      while True:
          data, addr = s.recvfrom(65535)
          s.sendto(data[::-1], addr)
""")
    wf = _running(cluster.osmo, spec, LOCAL)
    proc = _forward(cluster.osmo, wf, "--port", f"{local}:{port}", "--udp")
    try:
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as sock:
            sock.settimeout(1.0)

            def echo_once(data: bytes) -> bytes:
                sock.sendto(data, ("127.0.0.1", local))
                return sock.recvfrom(65535)[0]

            assert retry_oserror(lambda: echo_once(b"hello")) == b"olleh"
            big = os.urandom(40_000)
            assert retry_oserror(lambda: echo_once(big)) == big[::-1]
        os.kill(proc.pid, signal.SIGINT)
        _, err = proc.communicate(timeout=30)
        assert proc.returncode == 0 and "port-forward stopped" in err
    finally:
        _stop(proc)
        cluster.osmo("cancel", wf)


def test_the_node_connects_only_to_the_ports_a_session_was_granted(
        cluster: Cluster, tmp_path: Path) -> None:
    """A client speaking the stream itself still reaches only its granted port, over TCP."""
    wf = _running(cluster.osmo, _sleeper(tmp_path, "granted"), LOCAL)
    link = Link.client([cluster.endpoint])
    admin = ApiClient(link, token=(cluster.osmo.home / "auth" / "admin.token").read_text())
    frames: list[Frame] = []
    try:
        reply = admin.call("forward_open", {"workflow_id": wf, "task": "t", "ports": [22]})
        stream = Stream(link, SessionGrant.from_dict(reply["grant"]), "client",
                        frames.append, lambda: None)
        deadline = time.monotonic() + 30
        while not any(f.kind is Kind.READY for f in frames):
            assert time.monotonic() < deadline, frames
            stream.send(Kind.HELLO)
            time.sleep(0.2)
        stream.send_json(Kind.OPEN, 1, {"port": 23})
        stream.send_json(Kind.OPEN, 2, {"port": 22, "udp": True})
        stream.send(Kind.OPEN, 3, b"{not json")
        while len([f for f in frames if f.kind is Kind.CLOSE]) < 3:
            assert time.monotonic() < deadline, frames
            time.sleep(0.1)
        closes = {f.channel: f.data for f in frames if f.kind is Kind.CLOSE}
        assert closes == {1: b"port not granted to this session",
                          2: b"port not granted to this session", 3: b"malformed OPEN"}
        stream.send(Kind.CLOSE, 0)
        stream.close()
    finally:
        link.close()
        cluster.osmo("cancel", wf)


def test_port_forward_arguments(cluster: Cluster) -> None:
    for bad in ("x", "80-81:90-95", "0", "70000", "5:6,5:7", "9-8"):
        r = cluster.osmo("workflow", "port-forward", "wf-1", "t", "--port", bad)
        assert r.code == 2 and "--port" in r.err, (bad, r.err)
    from osmo.cli.interactive import parse_ports

    assert parse_ports("8888") == [(8888, 8888)]
    assert parse_ports("9000:80,7000-7001:6000-6001") == [(9000, 80), (7000, 6000),
                                                         (7001, 6001)]
    assert json.dumps(parse_ports("1-2")) == "[[1, 1], [2, 2]]"
    assert parse_ports("80-81:90") == [(80, 90), (81, 91)]  # R starts the remote range


def test_a_port_that_does_not_answer_stalls_only_its_own_connection(
        cluster: Cluster, tmp_path: Path) -> None:
    """The node connects to the task off the stream: a clogged port never holds up the others.

    The task's port ``clogged`` listens with a full accept queue, so a connection to it hangs
    until the node's connect timeout; meanwhile a connection to ``echo`` on the same session
    must work, and the clogged one must still be waiting when it does.
    """
    echo, clogged = free_port(0), free_port(0)
    local_echo, local_clogged = free_port(0), free_port(0)
    spec = write(tmp_path / "clog.yaml", f"""
workflow:
  name: clog
  tasks:
  - name: t
    command: [{sys.executable}, -c]
    args:
    - |
      import socket, threading
      jam = socket.socket(); jam.bind(("127.0.0.1", {clogged})); jam.listen(0)
      fill = []
      for _ in range(3):
          c = socket.socket(); c.setblocking(False); c.connect_ex(("127.0.0.1", {clogged}))
          fill.append(c)
      srv = socket.create_server(("127.0.0.1", {echo}))
      def serve(conn):
          while data := conn.recv(65536):
              conn.sendall(data)
      while True:
          threading.Thread(target=serve, args=(srv.accept()[0],), daemon=True).start()
""")
    wf = _running(cluster.osmo, spec, REMOTE)
    proc = _forward(cluster.osmo, wf, "--port", f"{local_echo}:{echo},{local_clogged}:{clogged}")
    try:
        def echo_once() -> bytes:
            with socket.create_connection(("127.0.0.1", local_echo), timeout=30) as sock:
                sock.sendall(b"ping")
                return sock.recv(4)

        assert retry_oserror(echo_once) == b"ping"  # the session is up
        with socket.create_connection(("127.0.0.1", local_clogged), timeout=30) as stuck:
            time.sleep(0.5)  # its OPEN reaches the node, which starts connecting
            assert echo_once() == b"ping"
            readable, _, _ = select.select([stuck], [], [], 0)
            assert not readable, "the clogged connection ended before the echo answered"
            stuck.settimeout(30)  # the node gives up on it: closed, with nothing sent
            assert stuck.recv(1) == b""
    finally:
        _stop(proc)
        cluster.osmo("cancel", wf)
