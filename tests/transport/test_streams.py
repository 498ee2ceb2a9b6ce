"""Session streams over real zenoh sessions on loopback: ordered, signed, kept alive."""

from __future__ import annotations

import os
import secrets
import threading
import time

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


def test_forged_replayed_and_reflected_frames_are_dropped(links: tuple[Link, Link]) -> None:
    """A zenoh peer that sees the keys (wildcard subscription) still cannot inject."""
    node_link, client_link = links
    grant, inbox = _grant(), _Inbox()
    node = Stream(node_link, grant, "node", inbox.put, inbox.lost.set)
    seen: list[tuple[bytes, bytes | None]] = []
    spy = client_link.subscribe_raw(client_link.key("stream", "**"),
                                    lambda _k, data, att: seen.append((data, att)))
    forger = Stream(client_link, _grant(), "client", lambda _f: None, lambda: None)
    client = Stream(client_link, grant, "client", lambda _f: None, lambda: None)
    time.sleep(0.3)
    up = client_link.key("stream", grant.session_id, "up")
    # another key, same session id: not accepted
    forged = SessionGrant(grant.session_id, secrets.token_bytes(32), "exec", "a-1")
    Stream(client_link, forged, "client", lambda _f: None, lambda: None).send(Kind.DATA, 0,
                                                                               b"rm -rf /\n")
    client.send(Kind.DATA, 0, b"ls\n")
    first = inbox.wait(1)
    assert [f.data for f in first] == [b"ls\n"]
    # replay what the spy saw of the genuine frame, and garbage
    deadline = time.monotonic() + 10
    while not (genuine := [(d, a) for d, a in seen if d == b"ls\n"]):
        assert time.monotonic() < deadline, "the spy never saw the frame"
        time.sleep(0.05)
    client_link.put(up, *genuine[0])
    client_link.put(up, b"junk", b"\0" * 29)
    client_link.put(up, b"junk")
    # the node's own frames reflected back up are refused too
    node.send(Kind.DATA, 1, b"reflect")
    while not (reflected := [(d, a) for d, a in seen if d == b"reflect"]):
        assert time.monotonic() < deadline, "the spy never saw the node's frame"
        time.sleep(0.05)
    client_link.put(up, *reflected[0])
    client.send(Kind.DATA, 0, b"pwd\n")
    time.sleep(0.5)
    assert [f.data for f in inbox.wait(2)] == [b"ls\n", b"pwd\n"]
    for stream in (node, client, forger):
        stream.close()
    spy.close()


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
