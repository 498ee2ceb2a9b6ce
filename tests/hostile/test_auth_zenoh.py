"""A zenoh peer cannot speak as the server: the router's allow-list, the second wall.

Any peer that reaches the router (a worker with its zenoh credentials, or anything on an
``--insecure`` listener) could, without it, put orders on ``to-worker/<id>``, declare a
queryable on ``api/**``, serve the server's blobs, publish workflow events, or hold the
server's liveliness token. The server's router allows remote peers only what workers and
clients use (``osmo.transport.wire.PEER_ALLOW``, default deny); the server's own session,
inside the router, is the only one allowed the rest. The first wall is that nothing is
believed for its key (``tests/hostile/test_auth_wire.py``, with and without this one).
"""

from __future__ import annotations

import json
import threading
import time
from collections.abc import Iterator
from pathlib import Path

import pytest

from osmo.transport.zenoh_link import Link, Request
from tests.conftest import ended, write
from tests.e2e.cluster import Cluster


@pytest.fixture
def cluster(tmp_path: Path) -> Iterator[Cluster]:
    c = Cluster(tmp_path)
    c.start_server()
    try:
        yield c
    finally:
        c.stop()


def test_a_peer_cannot_order_a_worker_to_kill_its_task(cluster: Cluster, tmp_path: Path) -> None:
    cluster.start_worker("w1", host="elsewhere")
    wf = cluster.osmo.submit(write(tmp_path / "held.yaml", """
workflow:
  name: held
  tasks:
  - name: t
    command: [sh, -c, "sleep 3; echo real > {{output}}/out"]
"""))
    info = cluster.osmo.wait_for(wf, lambda i: i["tasks"][0]["status"] == "RUNNING" or ended(i))
    assert info["tasks"][0]["status"] == "RUNNING", info
    attacker = Link.client([cluster.endpoint], "local")
    try:
        order = b'{"op": "kill", "attempt_id": "%s:t:0", "reason": "forged"}' % wf.encode()
        for _ in range(3):
            attacker.put(attacker.key("to-worker", "w1"), order)
            time.sleep(0.1)
    finally:
        attacker.close()
    done = cluster.osmo.wait_for(wf, ended)
    assert done["status"] == "COMPLETED", done
    assert done["tasks"][0]["retry"] == 0, "the forged kill stopped the real attempt"
    assert Path(done["tasks"][0]["output"], "out").read_text() == "real\n"


def _impostor(link: Link, key: str) -> tuple[list[bytes | None], object]:
    heard: list[bytes | None] = []
    lock = threading.Lock()

    def answer(request: Request) -> None:
        with lock:
            heard.append(request.attachment or b"")
        request.reply(b'{"ok": true, "result": {"workflows": []}}')

    return heard, link.serve(key, answer)


def test_a_peer_cannot_serve_the_api_and_harvest_tokens(cluster: Cluster) -> None:
    attacker = Link.client([cluster.endpoint], "local")
    try:
        heard, _sub = _impostor(attacker, attacker.key("api", "**"))
        time.sleep(0.3)
        codes = [cluster.osmo("list", "--format", "json").code for _ in range(3)]
        assert heard == [], f"the impostor heard {len(heard)} API requests (with their tokens)"
        assert codes == [0, 0, 0], "the client took an impostor's answers"
    finally:
        attacker.close()


def test_a_peer_cannot_serve_the_servers_blobs(cluster: Cluster) -> None:
    attacker = Link.client([cluster.endpoint], "local")
    asker = Link.client([cluster.endpoint], "local")
    try:
        heard, _sub = _impostor(attacker, attacker.key("blob", "server", "*"))
        time.sleep(0.3)
        key = asker.key("blob", "server", "0" * 64)
        for _ in range(3):
            list(Link.replies(asker.ask(key, b"", attachment=b"osmo_worker-token", timeout=1.0)))
        assert heard == [], "a worker's blob request (with its token) reached an impostor"
    finally:
        attacker.close()
        asker.close()


def test_a_peer_cannot_publish_events_or_pose_as_the_live_server(cluster: Cluster) -> None:
    attacker = Link.client([cluster.endpoint], "local")
    watcher = Link.client([cluster.endpoint], "local")
    seen: list[dict[str, object]] = []
    try:
        sub = watcher.subscribe_raw(watcher.key("events", "**"),
                                    lambda _k, data, _a: seen.append(json.loads(data)))
        time.sleep(0.3)
        attacker.put(attacker.key("events", "wf-1"), b'{"workflow_id": "wf-1"}')
        fake = attacker.token(attacker.key("alive", "server"))
        time.sleep(0.5)
        assert seen == [], "a peer's forged event reached the clients"
        assert len(watcher.alive(watcher.key("alive", "server"))) == 1, \
            "a second 'server' liveliness token was accepted"
        fake.close()
        sub.close()
    finally:
        attacker.close()
        watcher.close()
