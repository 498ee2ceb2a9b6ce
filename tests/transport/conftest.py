"""Fixtures for the transport tests: real zenoh sessions on loopback, real sealed channels."""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass
from typing import Any

import pytest

from osmo.config import free_port
from osmo.errors import NotAuthenticated
from osmo.transport.auth import Identity, Role, token_digest
from osmo.transport.rpc import ApiClient, ApiServer
from osmo.transport.seal import ChannelTable, Signer, TokenKeys
from osmo.transport.zenoh_link import Link

TOKEN = "osmo_the-test-token"
OTHER = "osmo_another-token"


class Gate:
    """The server's side of authentication over a fixed set of tokens (``rpc.Gate``)."""

    def __init__(self, tokens: dict[str, str] | None = None) -> None:
        self.tokens = {token_digest(t): name for t, name in
                       (tokens or {TOKEN: "alice"}).items()}
        ids = {TokenKeys.from_digest(d).id: d for d in self.tokens}
        self.channels = ChannelTable(ids.get, Signer())

    def identity(self, digest: str, channel: bytes = b"") -> Identity:
        if digest not in self.tokens:
            raise NotAuthenticated("revoked")
        return Identity(self.tokens[digest], Role.ADMIN, channel)


@pytest.fixture
def endpoint() -> str:
    """The loopback endpoint the ``links`` router listens on."""
    return f"tcp/127.0.0.1:{free_port(0)}"


@pytest.fixture
def links(endpoint: str) -> Iterator[tuple[Link, Link]]:
    """A router session and a client session connected to it (router first)."""
    server = Link.router([endpoint])
    client = Link.client([endpoint])
    yield server, client
    client.close()
    server.close()


@dataclass
class Sealed:
    """A server answering the API on ``links[0]`` and a client of ``TOKEN`` on ``links[1]``."""

    gate: Gate
    server: ApiServer
    api: ApiClient
    calls: list[tuple[str, dict[str, Any], Identity]]


@pytest.fixture
def sealed(links: tuple[Link, Link]) -> Iterator[Sealed]:
    gate = Gate({TOKEN: "alice", OTHER: "bob"})
    calls: list[tuple[str, dict[str, Any], Identity]] = []

    def handler(verb: str, request: dict[str, Any], who: Identity) -> Any:
        calls.append((verb, request, who))
        return {"verb": verb, "echo": request, "who": who.name}

    server = ApiServer(links[0], handler, gate)
    yield Sealed(gate, server, ApiClient(links[1], token=TOKEN, timeout=5), calls)
    server.close()
