"""Fixtures for the transport tests: real zenoh sessions on loopback."""

from __future__ import annotations

from collections.abc import Iterator

import pytest

from osmo.config import free_port
from osmo.transport.zenoh_link import Link


@pytest.fixture
def links() -> Iterator[tuple[Link, Link]]:
    """A router session and a client session connected to it (router first)."""
    port = free_port(0)
    server = Link.router([f"tcp/127.0.0.1:{port}"])
    client = Link.client([f"tcp/127.0.0.1:{port}"])
    yield server, client
    client.close()
    server.close()
