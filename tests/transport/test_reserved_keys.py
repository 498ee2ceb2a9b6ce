"""The router's access control: reserved keys are refused from remote peers.

Rules a zenoh configuration file already has are kept beside them.
"""

from __future__ import annotations

import json
import time
from pathlib import Path

import pytest

from osmo.config import free_port
from osmo.transport.zenoh_link import Link


def test_a_reserved_put_is_dropped_and_the_files_own_rules_still_apply(tmp_path: Path) -> None:
    conf = tmp_path / "zenoh.json5"
    conf.write_text(json.dumps({"access_control": {
        "enabled": True, "default_permission": "allow",
        "rules": [{"id": "mine", "messages": ["put"], "flows": ["ingress"],
                   "permission": "deny", "key_exprs": ["osmo/local/private/**"]}],
        "subjects": [{"id": "everyone"}],
        "policies": [{"id": "p", "subjects": ["everyone"], "rules": ["mine"]}]}}))
    endpoint = f"tcp/127.0.0.1:{free_port(0)}"
    router = Link.router([endpoint], "local", config_file=str(conf),
                         reserved={"put": ["orders/**"]})
    peer = Link.client([endpoint], "local")
    listener = Link.client([endpoint], "local")
    got: list[tuple[str, bytes]] = []
    try:
        listener.subscribe_raw(listener.key("**"), lambda key, data, _a: got.append((key, data)))
        time.sleep(0.3)
        for key in ("orders/w1", "private/x", "open/y"):
            peer.put(peer.key(key), b"from a peer")
        router.put(router.key("orders", "w1"), b"from the server")
        deadline = time.monotonic() + 5
        while len(got) < 2 and time.monotonic() < deadline:
            time.sleep(0.05)
        time.sleep(0.3)
        assert sorted(got) == [("osmo/local/open/y", b"from a peer"),
                               ("osmo/local/orders/w1", b"from the server")]
    finally:
        for link in (peer, listener, router):
            link.close()


def test_only_access_control_messages_can_be_reserved() -> None:
    with pytest.raises(ValueError, match="cannot reserve"):
        Link.router(["tcp/127.0.0.1:1"], "local", reserved={"publish": ["x/**"]})
