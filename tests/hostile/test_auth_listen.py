"""Where the server listens, said and checked truthfully (issue 26, lows).

- ``osmo server --help`` stated ``tcp/127.0.0.1:7447`` as the default listener; a server given
  no ``--listen`` listens on its home's Unix socket only.
- Any host that merely started with ``127.`` or ``localhost`` counted as loopback, so
  ``--listen tcp/127.attacker.example:7447`` or ``tcp/localhost.attacker.example:7447`` went
  out without authentication and without ``--insecure``. The address is parsed now.
"""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from osmo.config import free_port, lock_is_held
from osmo.layout import Home
from osmo.transport.listeners import network_listeners
from tests.conftest import Osmo


def test_the_help_states_the_default_listener_the_server_uses(tmp_path: Path) -> None:
    osmo = Osmo(tmp_path / "home")
    for argv in (("server", "--help"), ("server", "start", "--help")):
        help_text = " ".join(osmo(*argv, check=True).out.split())
        assert "tcp/127.0.0.1:7447, or a free port" not in help_text, argv
        assert "default: none, only the home's Unix socket (OSMO_HOME/server.sock)" in help_text
    try:
        osmo("server", "start", check=True)
        info = json.loads((osmo.home / "server.json").read_text())
        assert [e.split("/")[0] for e in info["endpoints"]] == ["unixsock-stream"], info
    finally:
        osmo.stop_server()


@pytest.mark.parametrize(("endpoint", "exposed"), [
    ("tcp/127.0.0.1:7447", False), ("tcp/127.9.8.7:7447", False), ("tcp/[::1]:7447", False),
    ("tcp/localhost:7447", False), ("tls/localhost:7448", False),
    ("unixsock-stream//tmp/x.sock", False),
    ("tcp/127.attacker.example:7447", True), ("tcp/localhost.attacker.example:7447", True),
    ("tcp/127.0.0.1.nip.io:7447", True), ("tcp/0.0.0.0:7447", True), ("tcp/[::]:7447", True),
    ("tcp/10.1.2.3:7447", True), ("tcp/myhost:7447", True), ("tcp/[::ffff:10.0.0.1]:7447", True),
])
def test_loopback_is_an_address_not_a_prefix(endpoint: str, exposed: bool) -> None:
    assert network_listeners([endpoint]) == ([endpoint] if exposed else [])


def test_a_look_alike_loopback_name_needs_authentication(tmp_path: Path) -> None:
    osmo = Osmo(tmp_path / "home")
    for host in ("127.attacker.example", "localhost.attacker.example"):
        endpoint = f"tcp/{host}:{free_port(0)}"
        r = osmo("server", "start", "--listen", endpoint)
        assert r.code == 2, r
        assert f"refusing to listen on {endpoint} without authentication" in r.err
        assert "Traceback" not in r.err
    assert not lock_is_held(Home(osmo.home))
