"""A worker may speak only for the attempts placed on it; secrets reach only that worker.

The attacks of issue 13, each against a real server: a raw put of a forged exit report on
the old report key, forged exit reports and log lines as authenticated requests (from a
registered fake worker with a valid worker token) for a LOCAL attempt and for another
worker's attempt, a fake worker asking for another worker's secrets, and a peer sniffing
every order on ``to-worker/**``. Each is refused and logged; the real attempts are unaffected.
"""

from __future__ import annotations

import json
import threading
import time
from collections.abc import Iterator
from pathlib import Path

import pytest

from osmo.config import host_id, read_server_info
from osmo.errors import NotAllowed
from osmo.layout import Home
from osmo.transport.rpc import ApiClient
from osmo.transport.zenoh_link import Link
from tests.conftest import Osmo, ended, write
from tests.e2e.cluster import Cluster

FAKE = {"id": "fake", "pool": "default", "address": "127.0.0.1", "capacity": {"cpu": 0}}


def _held(tmp: Path, name: str = "held") -> Path:
    return write(tmp / f"{name}.yaml", f"""
workflow:
  name: {name}
  tasks:
  - name: t
    credentials:
      robot: {{ROBOT: key}}
    command: [sh, -c, "while [ ! -e {tmp}/release ]; do sleep 0.05; done; echo real > {{{{output}}}}/out"]
""")


def _refused(osmo: Osmo) -> list[str]:
    return [ln for ln in (osmo.home / "server.log").read_text().splitlines() if "refused" in ln]


def _attempt_running(osmo: Osmo, wf: str) -> None:
    info = osmo.wait_for(wf, lambda i: i["tasks"][0]["status"] == "RUNNING" or ended(i))
    assert info["tasks"][0]["status"] == "RUNNING", info


def _forge(fake: ApiClient, aid: str, *, wid: str = "fake") -> list[str]:
    """Forged exit report and log line for ``aid``; returns the refusal messages."""
    out = []
    for verb, request in (
            ("worker_report", {"id": wid, "report": {"op": "exited", "attempt_id": aid,
                                                     "exit_code": 0, "output": "/etc"}}),
            ("worker_log", {"id": wid, "attempt_id": aid, "records": json.dumps(
                {"ts": time.time(), "stream": "stdout", "text": "FORGED LINE"}) + "\n"}),
            ("worker_secrets", {"id": wid, "attempt_id": aid})):
        with pytest.raises(NotAllowed) as refused:
            fake.call(verb, request)
        out.append(str(refused.value))
    return out


@pytest.fixture
def local_server(tmp_path: Path) -> Iterator[Osmo]:
    osmo = Osmo(tmp_path / "home")
    osmo("credential", "set", "robot", "--payload", "key=TOP-s3cret-42", check=True)
    yield osmo
    (tmp_path / "release").touch()
    osmo.stop_server()


def test_forged_reports_for_a_local_attempt_are_refused(local_server: Osmo,
                                                        tmp_path: Path) -> None:
    osmo = local_server
    wf = osmo.submit(_held(tmp_path))
    _attempt_running(osmo, wf)
    aid = f"{wf}:t:0"
    info = read_server_info(Home(osmo.home))
    assert info is not None
    link = Link.client([info.endpoint], info.cluster)
    try:
        # the old attack: one put on the report key. Nothing listens there any more.
        link.put(link.key("from-worker", "fake"), json.dumps(
            {"op": "exited", "attempt_id": aid, "exit_code": 0}).encode())
        token = osmo("token", "create", "fake", "--role", "worker", "--pool", "default",
                     check=True).out.strip()
        fake = ApiClient(link, timeout=10, token=token)
        fake.call("worker_register", FAKE)  # a valid worker token, registered
        before = len(_refused(osmo))
        messages = _forge(fake, aid)
        assert all(f"attempt '{aid}' is not placed on worker fake" in m for m in messages)
        with pytest.raises(NotAllowed):  # nor may it speak as a worker it did not register
            fake.call("worker_report", {"id": "w9", "report": {"op": "started",
                                                               "attempt_id": aid}})
        assert len(_refused(osmo)) == before + 4
        assert "refused 'worker_report' from fake (worker)" in _refused(osmo)[before]
    finally:
        link.close()
    time.sleep(0.5)
    assert osmo.query(wf)["tasks"][0]["status"] == "RUNNING"
    (tmp_path / "release").touch()
    done = osmo.wait_for(wf, ended)
    assert done["status"] == "COMPLETED"
    assert Path(done["tasks"][0]["output"], "out").read_text() == "real\n"
    assert "FORGED" not in osmo("logs", wf, check=True).out


def test_a_fake_worker_gets_no_secret_and_cannot_speak_for_another(tmp_path: Path) -> None:
    c = Cluster(tmp_path)
    c.start_server()
    link = Link.client([c.endpoint], "local")
    seen: list[bytes] = []
    lock = threading.Lock()

    def sniff(_key: str, data: bytes, _att: bytes | None) -> None:
        with lock:
            seen.append(data)

    sniffer = link.subscribe_raw(link.key("to-worker", "*"), sniff)
    try:
        c.osmo("credential", "set", "robot", "--payload", "key=TOP-s3cret-42", check=True)
        fake = ApiClient(link, timeout=10, token=c.token("fake"))
        fake.call("worker_register", FAKE)
        c.start_worker("w1", host="elsewhere")
        wf = c.osmo.submit(_held(tmp_path))
        _attempt_running(c.osmo, wf)
        aid = f"{wf}:t:0"
        assert c.osmo.query(wf)["tasks"][0]["node"] == "w1"
        messages = _forge(fake, aid)
        assert all("is not placed on worker fake" in m for m in messages)
        with pytest.raises(NotAllowed):  # w1's id with the fake's token
            fake.call("worker_secrets", {"id": "w1", "attempt_id": aid})
        (tmp_path / "release").touch()
        done = c.osmo.wait_for(wf, ended)
        assert done["status"] == "COMPLETED", done
        assert Path(done["tasks"][0]["output"], "out").read_text() == "real\n"
        assert "FORGED" not in c.osmo("logs", wf, check=True).out
        with lock:
            orders = b"\n".join(seen)
        assert len(seen) >= 2, "the sniffer saw the orders"
        assert b'"op"' not in orders, "an order travelled in clear"
        assert b"TOP-s3cret-42" not in orders, "a secret travelled in a published order"
    finally:
        sniffer.close()
        link.close()
        c.stop()


def test_only_a_same_host_worker_learns_where_the_servers_artifacts_are(
        local_server: Osmo) -> None:
    """Issue 26: the registration reply gave any worker token the server's artifacts path."""
    osmo = local_server
    info = read_server_info(Home(osmo.home))
    assert info is not None
    link = Link.client([info.endpoint], info.cluster)
    try:
        token = osmo("token", "create", "far", "--role", "worker", "--pool", "default",
                     check=True).out.strip()
        far = ApiClient(link, timeout=10, token=token)
        reply = far.call("worker_register", dict(FAKE, host_id="another-host"))
        assert str(osmo.home) not in json.dumps(reply) and "host_id" not in reply, reply
        assert "host_id" not in far.call("ping"), "the host id proves 'same host': admins only"
        reply = far.call("worker_register", dict(FAKE, host_id=host_id()))
        assert reply["artifacts"] == str(osmo.home / "artifacts")
    finally:
        link.close()


def test_a_worker_without_a_token_is_told_how_to_get_one(tmp_path: Path) -> None:
    osmo = Osmo(tmp_path / "home")
    osmo.env.pop("OSMO_TOKEN", None)
    r = osmo("worker", "--connect", "tcp/127.0.0.1:9", "--name", "w1", "--home",
             str(tmp_path / "w"), timeout=60)
    assert r.code == 2 and "osmo token create NAME --role worker" in r.err, r
    assert "Traceback" not in r.err
