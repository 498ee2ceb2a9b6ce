"""Session streams over real zenoh sessions on loopback: ordered, encrypted, kept alive."""

from __future__ import annotations

import os
import secrets
import threading
import time
from collections.abc import Iterator
from dataclasses import dataclass

import pytest

from osmo.errors import UsageError
from osmo.transport.streams import CHUNK, Frame, Kind, SessionGrant, Stream
from osmo.transport.zenoh_link import Link


def _grant(key: bytes | None = None) -> SessionGrant:
    return SessionGrant(secrets.token_hex(16), key or secrets.token_bytes(32), "exec", "a-1")


class _Inbox:
    def __init__(self) -> None:
        self.frames: list[Frame] = []
        self.lost = threading.Event()
        self._cond = threading.Condition()

    def put(self, frame: Frame) -> None:
        with self._cond:
            self.frames.append(frame)
            self._cond.notify_all()

    def wait(self, n: int, timeout: float = 10) -> list[Frame]:
        with self._cond:
            assert self._cond.wait_for(lambda: len(self.frames) >= n, timeout), self.frames
            return list(self.frames)


def test_frames_arrive_in_order_and_big_payloads_are_split(links: tuple[Link, Link]) -> None:
    node_link, client_link = links
    grant, inbox = _grant(), _Inbox()
    node = Stream(node_link, grant, "node", inbox.put, inbox.lost.set)
    client = Stream(client_link, grant, "client", lambda _f: None, lambda: None)
    time.sleep(0.3)  # subscriptions reach the router
    payload = os.urandom(3 * CHUNK + 17)
    assert client.send(Kind.DATA, 3, payload)
    assert client.send(Kind.EOF, 3)
    frames = inbox.wait(5)
    assert b"".join(f.data for f in frames if f.kind is Kind.DATA) == payload
    assert [f.kind for f in frames][-1] is Kind.EOF and {f.channel for f in frames} == {3}
    node.close()
    client.close()


def _spied(seen: list[tuple[bytes, bytes | None]], data_len: int,
           deadline: float) -> tuple[bytes, bytes | None]:
    while not (found := [(d, a) for d, a in seen if len(d) == data_len + 16]):
        assert time.monotonic() < deadline, "the spy never saw the frame"
        time.sleep(0.05)
    return found[0]


@dataclass
class Spied:
    """A session (node and client ends) and what a spy on ``stream/**`` saw of it."""

    grant: SessionGrant
    node: Stream
    client: Stream
    inbox: _Inbox
    seen: list[tuple[bytes, bytes | None]]


@pytest.fixture
def spied(links: tuple[Link, Link]) -> Iterator[Spied]:
    node_link, client_link = links
    grant, inbox = _grant(), _Inbox()
    node = Stream(node_link, grant, "node", inbox.put, inbox.lost.set)
    seen: list[tuple[bytes, bytes | None]] = []
    spy = client_link.subscribe_raw(client_link.key("stream", "**"),
                                    lambda _k, data, att: seen.append((data, att)))
    client = Stream(client_link, grant, "client", lambda _f: None, lambda: None)
    time.sleep(0.3)
    yield Spied(grant, node, client, inbox, seen)
    for stream in (node, client):
        stream.close()
    spy.close()


def test_a_spy_reads_only_ciphertext_and_a_replay_is_dropped(links: tuple[Link, Link],
                                                            spied: Spied) -> None:
    """A zenoh peer that sees the keys (wildcard subscription) reads and replays nothing."""
    client_link, inbox, seen = links[1], spied.inbox, spied.seen
    spied.client.send(Kind.DATA, 0, b"echo $API_TOKEN\n")
    assert [f.data for f in inbox.wait(1)] == [b"echo $API_TOKEN\n"]
    genuine = _spied(seen, len(b"echo $API_TOKEN\n"), time.monotonic() + 10)
    assert b"API_TOKEN" not in b"".join(d + (a or b"") for d, a in seen)
    client_link.put(client_link.key("stream", spied.grant.session_id, "up"), *genuine)  # replay
    spied.client.send(Kind.DATA, 0, b"pwd\n")
    time.sleep(0.5)
    assert [f.data for f in inbox.wait(2)] == [b"echo $API_TOKEN\n", b"pwd\n"]
    assert not inbox.lost.is_set(), "a replay is dropped, not an attack on the session"


@pytest.mark.parametrize("attack", ["other-key", "junk", "no-header", "flipped", "reflected"])
def test_a_forged_or_tampered_frame_ends_the_session(links: tuple[Link, Link], spied: Spied,
                                                     attack: str) -> None:
    client_link, grant, inbox, seen = links[1], spied.grant, spied.inbox, spied.seen
    node, client = spied.node, spied.client
    client.send(Kind.DATA, 0, b"ls\n")
    assert [f.data for f in inbox.wait(1)] == [b"ls\n"]
    up = client_link.key("stream", grant.session_id, "up")
    deadline = time.monotonic() + 10
    if attack == "other-key":  # the session id is on the key: anyone can aim at it
        forged = SessionGrant(grant.session_id, secrets.token_bytes(32), "exec", "a-1")
        Stream(client_link, forged, "client", lambda _f: None, lambda: None).send(
            Kind.DATA, 0, b"rm -rf /\n")
    elif attack == "junk":
        client_link.put(up, b"junk" * 8, b"\0" * 13)
    elif attack == "no-header":
        client_link.put(up, b"junk")
    elif attack == "flipped":
        data, att = _spied(seen, 3, deadline)
        client_link.put(up, bytes([data[0] ^ 1]) + data[1:], att)
    else:  # the node's own frame put back up
        node.send(Kind.DATA, 1, b"reflect")
        client_link.put(up, *_spied(seen, len(b"reflect"), deadline))
    assert inbox.lost.wait(10), "the session went on after a frame failed its check"
    client.send(Kind.DATA, 0, b"after\n")
    time.sleep(0.5)
    assert b"rm -rf /\n" not in [f.data for f in inbox.frames]
    assert [f.data for f in inbox.frames] == [b"ls\n"]


def test_a_silent_peer_is_lost(links: tuple[Link, Link]) -> None:
    node_link, client_link = links
    grant, inbox = _grant(), _Inbox()
    node = Stream(node_link, grant, "node", inbox.put, inbox.lost.set, timeout=2.0)
    client = Stream(client_link, grant, "client", lambda _f: None, lambda: None)
    time.sleep(3.0)
    assert not inbox.lost.is_set()  # heartbeats keep it alive
    client.close()
    assert inbox.lost.wait(10)
    node.close()


@pytest.mark.parametrize("bad", [
    {"session_id": "x" * 32}, {"key": "00"}, {"kind": "shell"}, {"ports": [0]},
    {"size": "big"}, {"command": ["x"] * 1000},
])
def test_malformed_grants_are_refused(bad: dict) -> None:
    good = _grant().to_dict()
    assert SessionGrant.from_dict(good).to_dict() == good
    with pytest.raises(UsageError, match="malformed session grant"):
        SessionGrant.from_dict({**good, **bad})
