"""No message is believed because of its key: attacks on the bus, wildcards included.

A peer with no token reaches the router on loopback (as any local process can, as the
``nobody`` user too) and publishes, queries, answers and subscribes on any key expression.
Against the landed build it could order a worker to kill or run anything, replay a placed
task's ``prepare`` with another command, hear every API request with its token, and answer
``osmo query`` with a forged table. Every order, reply, report and log line is now sealed end
to end (``osmo.transport.seal``); the router's allow-list is only the second wall.
"""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Iterator
from pathlib import Path

import pytest

from osmo.transport.rpc import ApiClient
from osmo.transport.seal import Purpose, parse_header
from osmo.transport.zenoh_link import Link
from tests.conftest import REPO, ended, write
from tests.e2e.cluster import Cluster


@pytest.fixture(params=["acl", "open-router"])
def cluster(request: pytest.FixtureRequest, tmp_path: Path) -> Iterator[Cluster]:
    """The server's own router (with its allow-list), or an open router the server joins."""
    c = Cluster(tmp_path, open_router=request.param == "open-router")
    c.start_server()
    try:
        yield c
    finally:
        c.stop()


def _attacker(*args: str, nobody: bool = False) -> subprocess.Popen[str]:
    argv = [sys.executable, "-m", "tests.hostile.bus_attacker", *args]
    return subprocess.Popen(argv + (["--as-nobody"] if nobody else []), cwd=REPO,
                            stdout=subprocess.PIPE, text=True)


def _forge(endpoint: str, key: str, order: dict[str, object]) -> None:
    argv = [sys.executable, "-m", "tests.hostile.bus_attacker", "forge", endpoint, key,
            json.dumps(order)]
    subprocess.run(argv, cwd=REPO, check=True, timeout=60)


class Harvest:
    """An attacker process answering and hearing everything for ``seconds``."""

    def __init__(self, endpoint: str, seconds: float, nobody: bool) -> None:
        folder = Path(tempfile.mkdtemp(prefix="osmo-loot-"))  # outside root's 0700 folders
        folder.chmod(0o777)  # the nobody user writes it
        self.out = out = folder / "heard.jsonl"
        self.proc = _attacker("harvest", endpoint, str(seconds), str(out), nobody=nobody)
        assert self.proc.stdout is not None
        assert self.proc.stdout.readline() == "listening\n"
        time.sleep(0.5)  # its declarations reach the router

    def heard(self) -> list[dict[str, str]]:
        assert self.proc.wait(timeout=120) == 0
        assert self.proc.stdout is not None
        self.proc.stdout.close()
        heard = [json.loads(line) for line in self.out.read_text().splitlines()]
        shutil.rmtree(self.out.parent)
        return heard


HELD = """
workflow:
  name: held
  tasks:
  - name: t
    command: [sh, -c, "echo ran >> {runs}; sleep 4; echo real > {{{{output}}}}/out"]
"""


@pytest.mark.parametrize("key", ["to-worker/w1", "*/w1", "**"])
def test_forged_orders_on_any_key_are_not_obeyed(cluster: Cluster, tmp_path: Path,
                                                 key: str) -> None:
    cluster.start_worker("w1", host="elsewhere")
    runs, marker = tmp_path / "runs", tmp_path / "pwned"
    wf = cluster.osmo.submit(write(tmp_path / "held.yaml", HELD.format(runs=runs)))
    info = cluster.osmo.wait_for(wf, lambda i: i["tasks"][0]["status"] == "RUNNING" or ended(i))
    assert info["tasks"][0]["status"] == "RUNNING", info
    aid = f"{wf}:t:0"
    where = f"osmo/local/{key}"
    _forge(cluster.endpoint, where, {"op": "kill", "attempt_id": aid, "reason": "forged"})
    cmd = {"attempt_id": f"{wf}:evil:0", "workflow_id": wf, "task": "t", "retry": 0,
           "node_id": "w1", "inputs": {}, "hosts": {}, "run": True}
    _forge(cluster.endpoint, where, {"op": "prepare", "attempt_id": f"{wf}:evil:0", "cmd": cmd,
                                     "manifests": {}, "secrets": False, "spec": {
                                         "spec": {"workflow": {"name": "x", "tasks": [{
                                             "name": "t", "command": ["touch", str(marker)]}]}},
                                         "filename": "x", "types": {}}})
    _forge(cluster.endpoint, where, {"op": "run", "attempt_id": f"{wf}:evil:0"})
    done = cluster.osmo.wait_for(wf, ended)
    assert done["status"] == "COMPLETED" and done["tasks"][0]["retry"] == 0, done
    assert runs.read_text() == "ran\n", "the task ran twice"
    assert not marker.exists(), "the worker ran a forged command"
    if cluster.router is not None:  # no wall at the router: the worker itself dropped them
        assert "did not seal" in cluster.worker_log("w1")


@pytest.mark.parametrize("nobody", [False, True], ids=["peer", "nobody"])
def test_a_harvester_hears_no_token_no_order_and_is_not_believed(
        cluster: Cluster, tmp_path: Path, nobody: bool) -> None:
    cluster.start_worker("w1", host="elsewhere")
    user = cluster.token("alice", "user")
    admin = (cluster.osmo.home / "auth" / "admin.token").read_text().strip()
    runs = tmp_path / "runs"
    wf = cluster.osmo.submit(write(tmp_path / "held.yaml", HELD.format(runs=runs)))
    harvest = Harvest(cluster.endpoint, 6, nobody)
    answers = [cluster.osmo("query", wf, "--format", "json", check=True).json()
               for _ in range(3)]
    alice = cluster.osmo("list", "--format", "json", check=True)
    done = cluster.osmo.wait_for(wf, ended)
    heard = harvest.heard()
    assert [a["id"] for a in answers] == [wf] * 3, "a forged answer was believed"
    assert "forged-1" not in alice.out
    assert done["status"] == "COMPLETED" and runs.read_text() == "ran\n"
    blob = "".join(h["key"] + h["data"] + h["att"] for h in heard)
    kinds = {h["key"].split("/")[2] for h in heard}
    if cluster.router is None:  # the router's wall: nobody but the server serves the API
        assert "api" not in kinds
    else:  # no wall: it heard every request, sealed
        assert "api" in kinds, f"the harvester heard no API request ({kinds}): no test"
    for secret in (admin, user, cluster.tokens["w1"], "echo ran"):
        assert secret not in blob, "the bus carried a token or an order in clear"
    # what it heard it cannot replay: every order and request it saw is sealed
    for h in heard:
        if h["key"].split("/")[2] in ("to-worker", "api") and not h["key"].endswith("/hello"):
            head = parse_header(h["att"].encode("latin-1"))
            assert head is not None and head[0] in (Purpose.REQ, Purpose.PUSH), h["key"]


def test_a_replayed_order_or_request_does_nothing(cluster: Cluster, tmp_path: Path) -> None:
    cluster.start_worker("w1", host="elsewhere")
    runs = tmp_path / "runs"
    harvest = Harvest(cluster.endpoint, 8, False)
    wf = cluster.osmo.submit(write(tmp_path / "held.yaml", HELD.format(runs=runs)))
    cluster.osmo.wait_for(wf, lambda i: i["tasks"][0]["status"] == "RUNNING" or ended(i))
    heard = harvest.heard()
    replay = Link.client([cluster.endpoint], "local")
    try:
        for h in heard:
            if h["kind"] == "put" and "/to-worker/" in h["key"]:
                for key in (h["key"], "osmo/local/*/w1"):
                    replay.put(key, h["data"].encode("latin-1"), h["att"].encode("latin-1"))
            elif h["kind"] == "query" and "/api/" in h["key"]:
                list(Link.replies(replay.ask(h["key"], h["data"].encode("latin-1"),
                                             attachment=h["att"].encode("latin-1"), timeout=2)))
        assert any("/to-worker/" in h["key"] for h in heard), "no order to replay: no test"
    finally:
        replay.close()
    done = cluster.osmo.wait_for(wf, ended)
    assert done["status"] == "COMPLETED" and done["tasks"][0]["retry"] == 0, done
    assert runs.read_text() == "ran\n", "a replayed prepare or run started the task again"
    assert len(cluster.osmo("list", "--format", "json", check=True).json()) == 1  # type: ignore[arg-type]


def test_a_dead_workers_token_held_by_a_peer_does_not_keep_it_alive(cluster: Cluster,
                                                                    tmp_path: Path) -> None:
    """zenoh reports a liveliness key alive while any peer holds a token on it."""
    proc = cluster.start_worker("w1", host="elsewhere")
    squatter = Link.client([cluster.endpoint], "local")
    try:
        copy = squatter.token(squatter.key("alive", "worker", "w1"))
        runs = tmp_path / "runs"
        wf = cluster.osmo.submit(write(tmp_path / "held.yaml", HELD.format(runs=runs)))
        cluster.osmo.wait_for(wf, lambda i: i["tasks"][0]["status"] == "RUNNING" or ended(i))
        killed_at = time.time()
        proc.kill()
        proc.wait()
        noticed_at, _ = cluster.server_log_line("worker w1 is silent", timeout=60)
        assert noticed_at - killed_at < 30, "the dead worker was counted alive too long"
        info = cluster.osmo.query(wf)
        assert info["tasks"][0]["status"] != "RUNNING" or info["tasks"][0]["retry"] >= 1, info
        copy.close()
    finally:
        squatter.close()


def test_only_the_servers_notices_wake_a_client(cluster: Cluster, tmp_path: Path) -> None:
    """A notice is a hint to re-read; a client takes only those the server signed."""
    link = Link.client([cluster.endpoint], "local")
    admin = ApiClient(link, token=(cluster.osmo.home / "auth" / "admin.token").read_text())
    admin.channel()
    seen: list[tuple[bytes, bool]] = []
    lock = threading.Lock()

    def on_notice(key: str, payload: bytes, signature: bytes | None) -> None:
        assert admin.verifier is not None
        with lock:
            seen.append((payload, admin.verifier.notice(key, payload, signature)))

    sub = link.subscribe_raw(link.key("events", "*"), on_notice)
    try:
        cluster.start_worker("w1", host="elsewhere")
        wf = cluster.osmo.submit(write(tmp_path / "held.yaml",
                                       HELD.format(runs=tmp_path / "runs")))
        forged = {"workflow_id": wf, "forged": True, "ended": True}  # an end, made up
        for key in (f"osmo/local/events/{wf}", f"osmo/local/*/{wf}", "osmo/local/events/*"):
            _forge(cluster.endpoint, key, forged)
        cluster.osmo.wait_for(wf, ended)
        time.sleep(0.3)
    finally:
        sub.close()
        link.close()
    with lock:
        real = [ok for payload, ok in seen if b"forged" not in payload]
        fake = [ok for payload, ok in seen if b"forged" in payload]
    assert real and all(real), "the server's own notices must verify"
    assert not any(fake), "a forged notice verified"
    if cluster.router is not None:
        assert fake, "no forged notice reached the client: no test"


HARVEST_TASK = """
workflow:
  name: harvest
  tasks:
  - name: h
    command: [{python}, /tmp/harvest.py, {endpoint}, "{{{{output}}}}/heard"]
    files:
    - path: /tmp/harvest.py
      contents: |
        import os, sys, time, zenoh
        conf = zenoh.Config()
        conf.insert_json5("mode", '"client"')
        conf.insert_json5("connect/endpoints", '["' + sys.argv[1] + '"]')
        conf.insert_json5("scouting/multicast/enabled", "false")
        conf.insert_json5("connect/timeout_ms", "3000")
        heard = []
        try:
            session = zenoh.open(conf)
        except Exception as exc:
            open(sys.argv[2], "w").write("unreachable: " + str(exc)[:200])
            sys.exit(0)
        def hear(x):
            heard.append(repr((str(x.key_expr), x.payload.to_bytes(), x.attachment and x.attachment.to_bytes())))
        for key in ("**", "osmo/local/*/**", "osmo/local/to-worker/*", "osmo/local/events/*",
                    "osmo/local/api/*", "osmo/local/stream/*/*"):
            session.declare_subscriber(key, hear)
            session.declare_queryable(key, lambda q: (hear(q), q.reply(q.key_expr, b"{{}}")))
        time.sleep(6)
        open(sys.argv[2], "w").write("reached\\n" + "\\n".join(heard))
        os._exit(0)  # not the session's close: a peer it still answers may hold it
"""


@pytest.mark.parametrize("sandbox", ["on", "off"])
def test_a_task_harvests_nothing_from_the_bus(tmp_path: Path, sandbox: str) -> None:
    """Against the landed build a sandboxed task heard every token and minted an admin one.

    Sandboxed, it cannot even reach the router (its own network namespace); unsandboxed it
    can, and hears only sealed bytes while the owner, a user and a worker talk.
    """
    cluster = Cluster(tmp_path, server_args=("--sandbox", sandbox))
    cluster.server_args = tuple(a for a in cluster.server_args if a != "--no-local-pool")
    cluster.start_server()
    try:
        user = cluster.token("alice", "user")
        admin = (cluster.osmo.home / "auth" / "admin.token").read_text().strip()
        cluster.start_worker("w1", host="elsewhere", pool="remote")
        wf = cluster.osmo.submit(write(tmp_path / "harvest.yaml", HARVEST_TASK.format(
            python=sys.executable, endpoint=cluster.endpoint)))
        cluster.osmo.wait_for(wf, lambda i: i["tasks"][0]["status"] == "RUNNING" or ended(i))
        # traffic while it listens: orders to the worker, admin and user requests, notices
        cluster.osmo.submit(write(tmp_path / "held.yaml", HELD.format(runs=tmp_path / "runs")),
                            "--pool", "remote")
        for _ in range(5):
            cluster.osmo("list", "--format", "json", check=True)
            cluster.osmo("--token", user, "list", "--format", "json", check=True)
            time.sleep(0.5)
        done = cluster.osmo.wait_for(wf, ended, timeout=120)
        assert done["status"] == "COMPLETED", done
        heard = Path(done["tasks"][0]["output"], "heard").read_text(errors="replace")
        if sandbox == "on":
            assert heard.startswith("unreachable"), heard[:500]
        else:
            assert heard.startswith("reached"), heard[:500]
            assert "osmo/local/" in heard, "it heard nothing at all: no test"
        for secret in (admin, user, cluster.tokens["w1"]):
            assert secret not in heard
    finally:
        cluster.stop()
