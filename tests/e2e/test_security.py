"""Authentication and TLS through zenoh's own config, and task secrets on remote workers."""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import pytest

from osmo.config import free_port
from tests.conftest import Osmo, ended, write
from tests.docs.blocks import first_block, section
from tests.e2e.certs import make_certs
from tests.e2e.cluster import Cluster

SPEC = """
workflow:
  name: secure
  tasks:
  - name: t
    command: [sh, -c, "echo $OSMO_NODE > {{output}}/node"]
"""


@pytest.fixture
def password_cluster(tmp_path: Path) -> Iterator[Cluster]:
    (tmp_path / "users.txt").write_text("osmo:s3cret-pw\n")
    server_conf = write(tmp_path / "server.json5", '{transport: {auth: {usrpwd: {user: "osmo", '
                        f'password: "s3cret-pw", dictionary_file: "{tmp_path}/users.txt"}}}}}}}}\n')
    c = Cluster(tmp_path, server_args=("--zenoh-config", str(server_conf)))
    c.start_server()
    yield c
    c.stop()


def test_user_password_auth_refuses_strangers(password_cluster: Cluster, tmp_path: Path) -> None:
    c = password_cluster
    good = write(tmp_path / "worker.json5", '{transport: {auth: {usrpwd: {user: "osmo", '
                 'password: "s3cret-pw"}}}}\n')
    bad = write(tmp_path / "bad.json5", '{transport: {auth: {usrpwd: {user: "osmo", '
                'password: "guess"}}}}\n')
    # a worker with no or wrong credentials is refused with a clear message
    for conf in (None, bad):
        args = ("--zenoh-config", str(conf)) if conf else ()
        proc = c.start_worker(f"intruder-{'none' if conf is None else 'bad'}", *args, wait=False)
        assert proc.wait(timeout=60) == 3
        log = c.worker_log(f"intruder-{'none' if conf is None else 'bad'}")
        assert "cannot connect to an osmo server" in log and "Traceback" not in log
    # so is a client
    laptop = Osmo(tmp_path / "laptop")
    r = laptop("--server", c.endpoint, "list")
    assert r.code == 3 and "--zenoh-config / OSMO_ZENOH_CONFIG" in r.err
    # with the password, the worker joins and runs work; the client sees it
    c.start_worker("w1", "--zenoh-config", str(good))
    laptop.env.update(OSMO_ZENOH_CONFIG=str(good), OSMO_TOKEN=c.token("laptop", "user"))
    wf = laptop("--server", c.endpoint, "submit", str(write(tmp_path / "wf.yaml", SPEC)),
                "--wait")
    assert wf.code == 0, wf.err
    # the server's own host reaches it with the server's config (recorded in server.json)
    assert c.osmo("list", check=True).out.count("secure") == 1
    assert set(c.nodes()) == {"w1"}


def test_mutual_tls(tmp_path: Path) -> None:
    certs = make_certs(tmp_path / "certs")
    tls_port = free_port(0)
    tls = {"root_ca_certificate": f"{certs}/ca.pem"}
    server_conf = write(tmp_path / "server.json5", "{transport: {link: {tls: {"
                        f'listen_certificate: "{certs}/server.pem", '
                        f'listen_private_key: "{certs}/server.key", '
                        f'root_ca_certificate: "{tls["root_ca_certificate"]}", '
                        "enable_mtls: true}}}}\n")
    client_conf = write(tmp_path / "client.json5", "{transport: {link: {tls: {"
                        f'root_ca_certificate: "{certs}/ca.pem", '
                        f'connect_certificate: "{certs}/client.pem", '
                        f'connect_private_key: "{certs}/client.key", enable_mtls: true}}}}}}}}\n')
    no_cert = write(tmp_path / "nocert.json5", "{transport: {link: {tls: {"
                    f'root_ca_certificate: "{certs}/ca.pem"}}}}}}}}\n')
    c = Cluster(tmp_path, server_args=("--listen", f"tls/localhost:{tls_port}",
                                       "--zenoh-config", str(server_conf)))
    c.start_server()
    try:
        tls_ep = f"tls/localhost:{tls_port}"
        proc = c.start_worker("no-cert", "--zenoh-config", str(no_cert), connect=tls_ep,
                              wait=False)
        assert proc.wait(timeout=60) == 3
        assert "cannot connect" in c.worker_log("no-cert")
        c.start_worker("w1", "--zenoh-config", str(client_conf), connect=tls_ep)
        info = c.osmo.wait_for(c.osmo.submit(write(tmp_path / "wf.yaml", SPEC)), ended)
        assert info["status"] == "COMPLETED"
        assert Path(info["tasks"][0]["output"], "node").read_text().strip() == "w1"
    finally:
        c.stop()


def test_task_credentials_reach_a_remote_task_masked(tmp_path: Path) -> None:
    c = Cluster(tmp_path)
    c.start_server()
    try:
        c.start_worker("w1", host="elsewhere")
        c.osmo("credential", "set", "robot-key", "--payload", "token=tok-8f3a9c21xyz",
               check=True)
        spec = write(tmp_path / "wf.yaml", """
workflow:
  name: creds
  tasks:
  - name: t
    credentials:
      robot-key: {ROBOT_TOKEN: token}
    command: [sh, -c, "echo using $ROBOT_TOKEN; printf %s $ROBOT_TOKEN | sha256sum | cut -c1-16 > {{output}}/h"]
""")
        info = c.osmo.wait_for(c.osmo.submit(spec), ended)
        assert info["status"] == "COMPLETED", info
        import hashlib

        expected = hashlib.sha256(b"tok-8f3a9c21xyz").hexdigest()[:16]
        assert Path(info["tasks"][0]["output"], "h").read_text().strip() == expected
        logs = c.osmo("logs", info["id"], check=True).out
        assert "using ****" in logs and "tok-8f3a9c21xyz" not in logs
        worker_files = subprocess.run(["grep", "-rl", "tok-8f3a9c21xyz", str(tmp_path / "w1")],
                                      capture_output=True, text=True)
        assert worker_files.stdout == "", "the secret must not be left on the worker's disk"
    finally:
        c.stop()


def test_docs_mutual_tls_walkthrough(tmp_path: Path) -> None:
    """docs/how-to/secure-listener.md → "Mutual TLS, worked through": its openssl commands and
    config files run exactly as written (taken from the page, so the two cannot drift);
    its two osmo commands run with free ports on loopback. The worker resolves
    ``osmo.example.org`` to 127.0.0.1 through its own /etc/hosts (bubblewrap), as a worker
    on another machine would through DNS."""
    if shutil.which("bwrap") is None:  # a failure in a full run (OSMO_NO_SKIPS)
        pytest.skip("bubblewrap is needed to resolve osmo.example.org for the worker "
                    "(./dev test installs it: apt-get install bubblewrap)")
    walkthrough = first_block(section("docs/how-to/secure-listener.md",
                                      "## Mutual TLS, worked through"), "sh")
    lines = walkthrough.splitlines(keepends=True)
    first_osmo = next(i for i, line in enumerate(lines) if line.startswith("osmo "))
    setup, commands = "".join(lines[:first_osmo]), [ln.split() for ln in lines[first_osmo:]]
    assert [c[:2] for c in commands] == [["osmo", "server"], ["osmo", "token"],
                                         ["osmo", "worker"]]
    assert commands[1][-2:] == [">", "gpu-1.token"]
    folder = tmp_path / "keys"
    folder.mkdir()
    subprocess.run(["bash", "-euo", "pipefail", "-c", setup], cwd=folder, check=True,
                   capture_output=True)
    assert {p.name for p in folder.iterdir()} >= {
        "ca.pem", "server.pem", "server.key", "worker.pem", "worker.key", "server.json5",
        "worker.json5"}
    tls_port, tcp_port = free_port(0), free_port(0)

    def ports(argv: list[str]) -> list[str]:
        return [a.replace("0.0.0.0:7448", f"127.0.0.1:{tls_port}")
                 .replace("osmo.example.org:7448", f"osmo.example.org:{tls_port}")
                 .replace("127.0.0.1:7447", f"127.0.0.1:{tcp_port}") for a in argv]

    server = Osmo(tmp_path / "server")
    server(*ports(commands[0])[1:], check=True, cwd=folder)
    worker: subprocess.Popen[bytes] | None = None
    try:  # the server is stopped whatever fails from here on (by PID)
        (folder / "gpu-1.token").write_text(server(*commands[1][1:-2], check=True).out)
        hosts = write(tmp_path / "hosts", "127.0.0.1 localhost osmo.example.org\n")
        env = dict(server.env, OSMO_HOME=str(tmp_path / "worker"))
        with open(tmp_path / "worker.log", "wb") as log:
            worker = subprocess.Popen(
                ["bwrap", "--dev-bind", "/", "/", "--ro-bind", str(hosts), "/etc/hosts",
                 "--chdir", str(folder), "--die-with-parent", "--",
                 sys.executable, "-m", "osmo", *ports(commands[2])[1:]],
                env=env, stdout=log, stderr=log)
        deadline = time.monotonic() + 60
        while not any(n["pool"] == "gpu" and n["status"] == "online" for n in json.loads(
                server("workers", "--format", "json", check=True).out)):
            assert worker.poll() is None, (tmp_path / "worker.log").read_text()
            assert time.monotonic() < deadline, "the walkthrough's worker never came online"
            time.sleep(0.1)
        # commands on the server's host use the loopback listener (and server.json's config)
        r = server("submit", str(write(tmp_path / "wf.yaml", SPEC)), "--pool", "gpu", "--wait")
        assert r.code == 0, r.out + r.err
    finally:
        if worker is not None:
            worker.kill()
            worker.wait()
        server.stop_server()
