"""The router's allow-list: remote peers may use only the keys listed, wildcards included.

A zenoh peer may name any key expression: ``osmo/local/*/w1`` reaches the subscriber of
``osmo/local/to-worker/w1`` on a router whose rules deny ``to-worker/**`` as written. With
an allow-list and default deny, a message is let through only where an allowed key
expression includes it, so each wildcard form is refused too. Rules a zenoh configuration
file already has are kept beside osmo's.
"""

from __future__ import annotations

import json
import threading
import time
from collections.abc import Iterator
from pathlib import Path

import pytest

from osmo.config import free_port
from osmo.transport.wire import PEER_ALLOW, PEER_DENY
from osmo.transport.zenoh_link import Link, Request


@pytest.fixture
def acl_router(tmp_path: Path) -> Iterator[tuple[Link, str]]:
    endpoint = f"tcp/127.0.0.1:{free_port(0)}"
    router = Link.router([endpoint], "local", allow=PEER_ALLOW, deny=PEER_DENY)
    yield router, endpoint
    router.close()


def _until(check, timeout: float = 10.0) -> bool:  # type: ignore[no-untyped-def]
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if check():
            return True
        time.sleep(0.05)
    return False


WILDCARDS = ["to-worker/w1", "*/w1", "**", "to-worker/*", "*/*", "$*/w1"]


def test_a_peer_cannot_put_an_order_under_any_key_expression(
        acl_router: tuple[Link, str]) -> None:
    router, endpoint = acl_router
    worker, attacker = Link.client([endpoint]), Link.client([endpoint])
    got: list[bytes] = []
    try:
        worker.subscribe_raw(worker.key("to-worker", "w1"), lambda _k, d, _a: got.append(d))
        worker.subscribe_raw(worker.key("stream", "s", "down"), lambda _k, d, _a: got.append(d))
        # the router's own order and a peer's allowed put both arrive: the subscriptions are
        # in place, so a forged order put before them would have arrived too
        assert _until(lambda: (attacker.put(attacker.key("stream", "s", "down"), b"allowed"),
                               router.put(router.key("to-worker", "w1"), b"real"),
                               b"allowed" in got and b"real" in got)[-1])
        for key in WILDCARDS:
            attacker.put(attacker.key(key), b"forged")
        attacker.put(attacker.key("stream", "s", "down"), b"marker")
        assert _until(lambda: b"marker" in got)
        time.sleep(0.2)
        assert b"forged" not in got
    finally:
        worker.close()
        attacker.close()


def test_a_peer_cannot_serve_the_api_or_the_servers_blobs(acl_router: tuple[Link, str]) -> None:
    router, endpoint = acl_router
    client, attacker = Link.client([endpoint]), Link.client([endpoint])
    heard: list[str] = []
    lock = threading.Lock()

    def impostor(request: Request) -> None:
        with lock:
            heard.append(request.key)
        request.reply(b"forged")

    try:
        for key in ("api/**", "*/**", "**", "api/list", "blob/server/*", "blob/**"):
            attacker.serve(attacker.key(key), impostor)
        router.serve(router.key("api", "**"), lambda r: r.reply(b"real"))
        router.serve(router.key("blob", "server", "*"), lambda r: r.reply(b"real blob"))
        assert _until(lambda: b"real" in [p for p, _ in Link.replies(
            client.ask(client.key("api", "list"), b"", timeout=2))])
        replies = [p for key in ("api/list", "blob/server/" + "0" * 64) for p, _ in
                   Link.replies(client.ask(client.key(key), b"", timeout=2))]
        assert sorted(replies) == [b"real", b"real blob"]
        assert heard == []
    finally:
        client.close()
        attacker.close()


def test_wildcard_queries_and_liveliness_are_refused(acl_router: tuple[Link, str]) -> None:
    router, endpoint = acl_router
    attacker = Link.client([endpoint])
    asked: list[str] = []
    try:
        router.serve(router.key("api", "**"), lambda r: (asked.append(r.key), r.reply(b"x")))
        for key in ("api/**", "*/list", "**"):
            assert list(Link.replies(attacker.ask(attacker.key(key), b"", timeout=1))) == []
        fake = attacker.token(attacker.key("alive", "server"))
        time.sleep(0.3)
        assert len(router.alive(router.key("alive", "server"))) == 0
        fake.close()
        assert asked == []
    finally:
        attacker.close()


def test_the_files_own_rules_still_apply(tmp_path: Path) -> None:
    conf = tmp_path / "zenoh.json5"
    conf.write_text(json.dumps({"access_control": {
        "enabled": True, "default_permission": "allow",
        "rules": [{"id": "mine", "messages": ["put"], "flows": ["ingress"],
                   "permission": "deny", "key_exprs": ["osmo/local/stream/private/**"]}],
        "subjects": [{"id": "everyone"}],
        "policies": [{"id": "p", "subjects": ["everyone"], "rules": ["mine"]}]}}))
    endpoint = f"tcp/127.0.0.1:{free_port(0)}"
    router = Link.router([endpoint], "local", config_file=str(conf), allow=PEER_ALLOW,
                         deny=PEER_DENY)
    peer, listener = Link.client([endpoint], "local"), Link.client([endpoint], "local")
    got: list[str] = []
    try:
        listener.subscribe_raw(listener.key("stream", "*", "*"), lambda k, _d, _a: got.append(k))
        assert _until(lambda: (peer.put(peer.key("stream", "open", "y"), b""),
                               "osmo/local/stream/open/y" in got)[-1])
        peer.put(peer.key("stream", "private", "x"), b"")
        peer.put(peer.key("orders", "w1"), b"")
        peer.put(peer.key("stream", "open", "z"), b"")
        assert _until(lambda: "osmo/local/stream/open/z" in got)
        time.sleep(0.2)
        assert "osmo/local/stream/private/x" not in got
    finally:
        for link in (peer, listener, router):
            link.close()


def test_only_access_control_messages_can_be_listed() -> None:
    with pytest.raises(ValueError, match="unknown zenoh messages"):
        Link.router(["tcp/127.0.0.1:1"], "local", allow={"publish": ["x/**"]})
