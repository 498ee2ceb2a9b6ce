"""Attacks with the zenoh credentials a data-mode task pod holds (the pod user, issue #28).

With ``auth.enabled`` the chart's router accepts only known users. A kubernetes pool without
``workClaim`` hands its pods' two osmo containers a user of their own (``auth.podUser``), in
the attempt's Secret. Whoever reads it (a task that escaped into the collector) must get
nothing of the control plane: the router lets that user only query a node's pod-data API
(``podio/**``) and receive the replies. These tests run the rendered ``router.json5`` in a
real zenoh router on loopback with the rendered password dictionary, and real sessions
logging in as the server, a worker and a pod.
"""

from __future__ import annotations

import base64
import json
import time
from contextlib import ExitStack
from pathlib import Path
from typing import Any

import pytest
import zenoh

from osmo.config import DEFAULT_CLUSTER
from osmo.errors import UsageError
from osmo.runtime.kubernetes.manifest import CONTAINER, TICKET_DIR, ZENOH_CONFIG, ZENOH_KEY
from osmo.transport.zenoh_link import client_credentials
from tests.conftest import Osmo
from tests.helm.chart import (
    PEM,
    ROUTER,
    auth_secret,
    flag,
    router_config,
    zenoh_login,
    zenoh_router,
)

PREFIX = f"osmo/{DEFAULT_CLUSTER}/"
DATA_POOL = {**ROUTER, "pools": [{"name": "k", "replicas": 1, "kind": "kubernetes",
                                  "kubernetes": {}}]}


@pytest.mark.parametrize("rules", ["rendered", "none"])
def test_the_pod_user_reaches_its_node_and_nothing_of_the_control_plane(
        rules: str, tmp_path: Path) -> None:
    """Without the rules (the control), the same attacks get through."""
    config, secret = router_config(DATA_POOL), auth_secret(DATA_POOL)
    if rules == "none":
        del config["access_control"]
    with ExitStack() as stack, zenoh_router(config, secret["dictionary"],
                                            tmp_path) as endpoint:
        def login(user: str, password: str) -> zenoh.Session:
            session = zenoh_login(endpoint, user, password)
            stack.callback(session.close)
            return session

        server = login(secret["server-user"], secret["server-password"])
        worker = login(secret["user"], secret["password"])
        pod = login(secret["pod-user"], secret["pod-password"])
        rogue = login(secret["pod-user"], secret["pod-password"])  # another pod, same user
        seen: dict[str, list[bytes]] = {"pod": [], "worker": [], "server": []}

        def note(who: str) -> Any:
            return lambda s: seen[who].append(
                f"{s.key_expr}={s.payload.to_bytes().decode()}".encode())

        # what the pod tries to hear: orders, events, results, tokens, every key
        for key in ("to-worker/*", "events/*", "stream/*/*", "**"):
            pod.declare_subscriber(PREFIX + key, note("pod"))
        pod.liveliness().declare_subscriber(PREFIX + "alive/**", note("pod"))
        # what it tries to say: a forged order, a fake API, a fake worker, its log lines
        rogue.declare_queryable(PREFIX + "api/**", lambda q: q.reply(q.key_expr, b"fake"))
        rogue.liveliness().declare_token(PREFIX + "alive/worker/evil")
        worker.declare_subscriber(PREFIX + "to-worker/w1", note("worker"))
        server.declare_subscriber(PREFIX + "stream/**", note("server"))
        server.liveliness().declare_subscriber(PREFIX + "alive/**", note("server"))
        server.declare_queryable(PREFIX + "api/**", lambda q: q.reply(q.key_expr, b"real"))
        worker.declare_queryable(PREFIX + "podio/w1/**", lambda q: q.reply(q.key_expr, b"node"))
        worker.liveliness().declare_token(PREFIX + "alive/worker/w1")
        api_answers: set[bytes] = set()
        pod_answers: set[bytes] = set()
        deadline = time.monotonic() + 20
        while time.monotonic() < deadline:
            pod.put(PREFIX + "to-worker/w1", b"forged")
            pod.put(PREFIX + "stream/wf/task", b"forged")
            server.put(PREFIX + "to-worker/w1", b"order")
            server.put(PREFIX + "events/wf", b"event")
            worker.put(PREFIX + "stream/wf/task", b"line")
            api_answers.update(r.ok.payload.to_bytes() for r in worker.get(
                PREFIX + "api/list", timeout=5) if r.ok is not None)
            pod_answers.update(r.ok.payload.to_bytes() for r in pod.get(
                PREFIX + "api/list", timeout=2) if r.ok is not None)
            pod_answers.update(r.ok.payload.to_bytes() for r in pod.get(
                PREFIX + "podio/w1/hello", timeout=5) if r.ok is not None)
            if (b"node" in pod_answers and b"real" in api_answers
                    and f"{PREFIX}to-worker/w1=order".encode() in seen["worker"]
                    and f"{PREFIX}stream/wf/task=line".encode() in seen["server"]):
                time.sleep(0.5)  # what the pod sent before is in by now
                break
            time.sleep(0.1)
        else:
            raise AssertionError(f"the controls never arrived: {seen} {pod_answers} "
                                 f"{api_answers}")
        sent_by_pod = [m for m in [*seen["worker"], *seen["server"]]
                       if m.endswith(b"=forged") or b"evil" in m]
    heard = [m for m in seen["pod"] if not m.endswith(b"=forged")]
    if rules == "none":
        assert heard and sent_by_pod, (heard, sent_by_pod)
        return
    # no order, event, log line or liveliness token reached it (its own puts it hears
    # locally, without the router)
    assert heard == []
    assert pod_answers == {b"node"}  # its node answered; the API did not
    assert api_answers == {b"real"}  # its fake API was never asked
    assert sent_by_pod == []  # nothing it put or declared reached the server or a worker


def test_the_pod_user_is_a_user_of_its_own() -> None:
    secret = auth_secret(DATA_POOL)
    assert secret["pod-user"] == "osmo-pod"
    assert len(secret["pod-password"]) >= 32  # generated
    assert secret["pod-password"] not in (secret["password"], secret["server-password"])
    assert f"osmo-pod:{secret['pod-password']}" in secret["dictionary"].splitlines()
    given = auth_secret({**DATA_POOL, "auth": {**ROUTER["auth"], "podPassword": "pp"}})
    assert given["pod-password"] == "pp" and "osmo-pod:pp" in given["dictionary"]


SERIAL = Path(__file__).parent.parent / "containers" / "osmo_tutorials" / "serial_workflow.yaml"
PASSWORD = "pod-s3cret-4f9a"


def _pod_config(folder: Path, **tls: str) -> Path:
    config = folder / "pod.json5"
    config.write_text(json.dumps({"transport": {
        "auth": {"usrpwd": {"user": "osmo-pod", "password": PASSWORD,
                            "dictionary_file": str(folder / "dictionary")}},
        **({"link": {"tls": tls}} if tls else {})},
        "listen": {"endpoints": ["tcp/127.0.0.1:1"]},
        "access_control": {"enabled": True, "default_permission": "allow"}}))
    return config


def test_a_dry_run_shows_where_the_pods_router_user_goes_never_its_password(
        tmp_path: Path) -> None:
    pool = tmp_path / "pool.json"
    pool.write_text(json.dumps({"data": {"image": "osmo:test",
                                         "zenohConfig": str(_pod_config(tmp_path))}}))
    r = Osmo(tmp_path / "home")("submit", str(SERIAL), "--dry-run", "--runtime", "kubernetes",
                                "--kubernetes-config", str(pool))
    assert r.code == 0, r.err
    assert PASSWORD not in r.out + r.err
    assert base64.b64encode(PASSWORD.encode()).decode()[:12] not in r.out
    items = json.loads(r.out)["items"]
    for pod in (i for i in items if i["kind"] == "Pod"):
        spec = pod["spec"]
        fetch = spec["initContainers"][0]
        assert flag(fetch["command"], "--zenoh-config") == [f"{TICKET_DIR}/{ZENOH_CONFIG}"]
        tickets = next(v for v in spec["volumes"] if v["name"] == "osmo-tickets")
        assert {"key": ZENOH_KEY + ZENOH_CONFIG, "path": ZENOH_CONFIG} in tickets[
            "secret"]["items"]
        task = next(c for c in spec["containers"] if c["name"] == CONTAINER)
        assert "osmo-tickets" not in json.dumps(task) and ZENOH_KEY not in json.dumps(task)
    for secret in (i for i in items if i["kind"] == "Secret"):
        shown = base64.b64decode(secret["data"][ZENOH_KEY + ZENOH_CONFIG]).decode()
        assert shown == f"<the user of {tmp_path / 'pod.json5'}>"


def test_a_pod_is_handed_only_what_a_client_shows_the_router(tmp_path: Path) -> None:
    """The user, password and TLS certificates: never the dictionary, listeners or rules."""
    (tmp_path / "ca.pem").write_text(PEM)
    config, files = client_credentials(str(_pod_config(tmp_path, root_ca_certificate=str(
        tmp_path / "ca.pem"))), "/var/run/x")
    assert json.loads(config) == {"transport": {
        "auth": {"usrpwd": {"user": "osmo-pod", "password": PASSWORD}},
        "link": {"tls": {"root_ca_certificate": "/var/run/x/ca.crt"}}}}
    assert files == {"ca.crt": PEM}
    with pytest.raises(UsageError, match="missing.pem"):
        client_credentials(str(_pod_config(tmp_path, connect_private_key=str(
            tmp_path / "missing.pem"))), "/var/run/x")
