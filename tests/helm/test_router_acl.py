"""The chart's standalone router allows every peer but the server only the keys peers use.

With ``router.enabled`` the server is one more client of the router, so the router itself
must hold the allow-list the server's own router holds (``osmo.transport.wire``
``PEER_ALLOW`` and ``PEER_DENY``, default deny). It tells the server apart by its zenoh user
(``auth.serverUser``). The
attack test runs the rendered ``router.json5`` in a real zenoh router on loopback, with the
rendered Secret's password dictionary, and real sessions logging in as the server, a worker
and a rogue peer holding the workers' credentials.
"""

from __future__ import annotations

import threading
import time
from contextlib import ExitStack
from pathlib import Path

import pytest
import zenoh

from osmo.config import DEFAULT_CLUSTER
from osmo.transport.wire import PEER_ALLOW, PEER_DENY
from tests.helm.chart import (
    FULLNAME,
    ROUTER,
    auth_secret,
    container,
    render,
    router_config,
    zenoh_login,
    zenoh_router,
)

PREFIX = f"osmo/{DEFAULT_CLUSTER}/"


def test_the_router_allows_peers_exactly_the_wire_allow_list() -> None:
    acl = router_config(ROUTER)["access_control"]
    assert acl["enabled"] is True and acl["default_permission"] == "deny"
    rules = {rule["id"]: rule for rule in acl["rules"]}
    policies = {p["id"]: p for p in acl["policies"]}
    assert acl["subjects"] == [{"id": "osmo-peers", "usernames": ["osmo"]},
                               {"id": "osmo-server", "usernames": ["osmo-server"]}]
    peer = [rules[r] for r in policies["osmo-peers"]["rules"]]
    ingress = [r for r in peer if r["flows"] == ["ingress"]]

    def keys(permission: str) -> dict[str, tuple[str, ...]]:
        return {r["messages"][0]: tuple(k.removeprefix(PREFIX) for k in r["key_exprs"])
                for r in ingress if r["permission"] == permission}

    assert keys("allow") == PEER_ALLOW
    assert keys("deny") == PEER_DENY
    assert all(len(r["messages"]) == 1 for r in ingress)
    server = [rules[r] for r in policies["osmo-server"]["rules"]]
    assert {k for r in server for k in r["key_exprs"]} == {f"{PREFIX}**"}


def test_the_server_logs_in_to_the_router_as_its_own_user() -> None:
    secret = auth_secret(ROUTER)
    assert secret["server-user"] == "osmo-server"
    assert len(secret["server-password"]) >= 32  # generated
    assert secret["dictionary"].splitlines() == ["osmo:pw", f"osmo-server:{secret['server-password']}"]
    given = auth_secret({**ROUTER, "auth": {**ROUTER["auth"], "serverPassword": "sp"}})
    assert given["server-password"] == "sp" and "osmo-server:sp" in given["dictionary"]
    out = render(ROUTER)
    init = out.get("StatefulSet", f"{FULLNAME}-server")["spec"]["template"]["spec"]["initContainers"][0]
    assert init["command"][3:5] == ["/etc/osmo/auth/server-user", "/etc/osmo/auth/server-password"]
    # without the router there is no server user: the server is the listener itself
    assert "server-user" not in auth_secret({"auth": {"enabled": True, "password": "pw"}})
    assert container(out.get("StatefulSet", f"{FULLNAME}-server"), "server")["args"][:2] == ["server", "run"]


@pytest.mark.parametrize("rules", ["rendered", "none"])
def test_a_peer_with_the_workers_credentials_cannot_speak_as_the_server(
        rules: str, tmp_path: Path) -> None:
    """A forged order and a fake API never reach anyone; without the rules (control) they do."""
    config, secret = router_config(ROUTER), auth_secret(ROUTER)
    if rules == "none":
        del config["access_control"]
    with ExitStack() as stack, zenoh_router(config, secret["dictionary"], tmp_path) as endpoint:
        def login(user: str, password: str) -> zenoh.Session:
            session = zenoh_login(endpoint, user, password)
            stack.callback(session.close)
            return session

        server = login(secret["server-user"], secret["server-password"])
        worker, rogue = login("osmo", "pw"), login("osmo", "pw")
        got: list[bytes] = []
        marker = threading.Event()
        order = f"{PREFIX}to-worker/w1"
        worker.declare_subscriber(order, lambda s: got.append(s.payload.to_bytes()))
        worker.declare_subscriber(f"{PREFIX}from-worker/marker", lambda s: marker.set())
        server.declare_queryable(f"{PREFIX}api/**", lambda q: q.reply(q.key_expr, b"real"))
        rogue.declare_queryable(f"{PREFIX}api/**", lambda q: q.reply(q.key_expr, b"fake"))
        answers: set[bytes] = set()
        # declarations take a moment to propagate through the router: send until the control
        # attack lands, or (with the rules) until the rogue's own allowed put and the server's
        # order and answer have all arrived, so a forgery sent before them would have too
        deadline = time.monotonic() + 15
        while time.monotonic() < deadline:
            rogue.put(order, b"kill everything")
            rogue.put(f"{PREFIX}from-worker/marker", b"")  # same session: after the forgery
            server.put(order, b"real order")
            answers.update(r.ok.payload.to_bytes() for r in worker.get(
                f"{PREFIX}api/list", timeout=5) if r.ok is not None)
            if b"kill everything" in got and b"fake" in answers:
                break
            if rules == "rendered" and marker.is_set() and b"real order" in got \
                    and b"real" in answers:
                time.sleep(0.3)  # what the rogue sent with the marker is in by now
                break
            time.sleep(0.1)

    if rules == "rendered":
        assert set(got) == {b"real order"}
        assert answers == {b"real"}
    else:  # the control: the same attack succeeds on a router without the rules
        assert b"kill everything" in got
        assert b"fake" in answers
