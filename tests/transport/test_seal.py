"""Sealed channels: the handshake, sealing, and what a peer on the bus cannot do.

The first half is the pure logic (``osmo.transport.seal``); the second drives real zenoh
sessions on loopback, with an attacker session that answers and listens on wildcard keys.
"""

from __future__ import annotations

import json
import threading
import time

import pytest
from hypothesis import given
from hypothesis import strategies as st

from osmo.errors import NotAuthenticated
from osmo.transport.rpc import ApiClient, ApiServer
from osmo.transport.seal import (
    HEADER,
    ChannelTable,
    HelloError,
    Purpose,
    ReplayWindow,
    Signer,
    TokenKeys,
    Verifier,
    finish,
    hello,
)
from osmo.transport.zenoh_link import Link, Request
from tests.transport.conftest import OTHER, TOKEN, Gate, Sealed

# ---------------------------------------------------------------------- pure logic


def _open_pair(gate: Gate, token: str = TOKEN):  # type: ignore[no-untyped-def]
    shake = hello(token)
    reply = gate.channels.accept(shake.request())
    done = finish(shake, reply)
    assert done is not None
    return done[0], json.loads(reply)


def test_a_handshake_opens_one_channel_both_ends_seal_on() -> None:
    gate = Gate()
    client, reply = _open_pair(gate)
    assert TOKEN.encode() not in json.dumps(reply).encode() + hello(TOKEN).request()
    att, payload = client.seal(Purpose.REQ, "api/list", b'{"a": 1}')
    opened = gate.channels.open(Purpose.REQ, "api/list", att, payload)
    assert opened is not None
    server, digest, seq, body = opened
    assert body == b'{"a": 1}' and digest in gate.tokens
    ratt, rpayload = server.seal(Purpose.REP, "api/list", b"answer", seq)
    assert client.open(Purpose.REP, "api/list", ratt, rpayload, seq=seq) == (seq, b"answer")
    push = server.seal(Purpose.PUSH, "to-worker/w1", b"order")
    assert client.open(Purpose.PUSH, "to-worker/w1", *push) is not None


def test_a_sealed_message_is_opened_once_and_only_as_sent() -> None:
    gate = Gate()
    client, _ = _open_pair(gate)
    att, payload = client.seal(Purpose.REQ, "api/cancel", b"x")
    tampered = bytes([payload[0] ^ 1]) + payload[1:]
    assert gate.channels.open(Purpose.REQ, "api/cancel", att, tampered) is None
    assert gate.channels.open(Purpose.REQ, "api/submit", att, payload) is None  # moved key
    assert gate.channels.open(Purpose.SR, "api/cancel", att, payload) is None
    assert gate.channels.open(Purpose.REQ, "api/cancel", att, payload) is not None
    assert gate.channels.open(Purpose.REQ, "api/cancel", att, payload) is None  # replayed


def test_a_reply_answers_only_its_own_request() -> None:
    gate = Gate()
    client, _ = _open_pair(gate)
    first = gate.channels.open(Purpose.REQ, "api/a", *client.seal(Purpose.REQ, "api/a", b"1"))
    second = gate.channels.open(Purpose.REQ, "api/a", *client.seal(Purpose.REQ, "api/a", b"2"))
    assert first is not None and second is not None
    ratt, rpay = first[0].seal(Purpose.REP, "api/a", b"for 1", first[2])
    assert client.open(Purpose.REP, "api/a", ratt, rpay, seq=second[2]) is None
    assert client.open(Purpose.REP, "api/a", ratt, rpay, seq=first[2]) is not None


def test_only_the_real_server_can_answer_a_hello() -> None:
    shake = hello(TOKEN)
    impostor = Gate({OTHER: "mallory"})  # knows the wire format, not this token's key
    forged = json.loads(Gate().channels.accept(hello(TOKEN).request()))  # another hello's
    assert finish(shake, json.dumps(forged).encode()) is None
    with pytest.raises(HelloError, match="unknown token"):
        impostor.channels.accept(shake.request())
    real = Gate().channels.accept(shake.request())
    assert finish(shake, real) is not None
    for junk in (b"", b"{}", b"[]", b'{"channel": "zz"}', b"\xff" * 40):
        assert finish(shake, junk) is None


def test_a_channel_of_another_token_opens_nothing_of_this_one() -> None:
    gate = Gate({TOKEN: "alice", OTHER: "bob"})
    alice, _ = _open_pair(gate, TOKEN)
    bob, _ = _open_pair(gate, OTHER)
    att, payload = alice.seal(Purpose.REQ, "api/x", b"alice's")
    forged = HEADER.pack(*HEADER.unpack(att)[:2], bob.id, HEADER.unpack(att)[3])
    assert gate.channels.open(Purpose.REQ, "api/x", forged, payload) is None


def test_channels_are_bounded_per_token_and_revoked_with_it() -> None:
    gate = Gate({TOKEN: "alice", OTHER: "bob"})
    table = ChannelTable(gate.channels._lookup, Signer(), limit=8, per_token=3)
    gate.channels = table
    bobs = [_open_pair(gate, OTHER)[0] for _ in range(2)]
    alices = [_open_pair(gate, TOKEN)[0] for _ in range(5)]  # a flood of one token's hellos
    assert all(table.get(c.id) is not None for c in bobs), "another token's channels stay"
    assert [table.get(c.id) is not None for c in alices] == [False, False, True, True, True]
    table.revoke(next(d for d, n in gate.tokens.items() if n == "bob"))
    assert all(table.get(c.id) is None for c in bobs)


@given(st.lists(st.integers(min_value=1, max_value=20_000), max_size=200))
def test_a_replay_window_accepts_each_number_once(seqs: list[int]) -> None:
    window = ReplayWindow(size=64)
    top, accepted = 0, set()
    for seq in seqs:
        ok = window.accept(seq)
        expected = seq not in accepted and seq > top - 64
        assert ok == expected
        if ok:
            accepted.add(seq)
            top = max(top, seq)


def test_notices_verify_only_the_servers_signature() -> None:
    signer, other = Signer(), Signer()
    verifier = Verifier(signer.public)
    sig = signer.sign_notice("osmo/local/events/wf-1", b'{"workflow_id": "wf-1"}')
    assert verifier.notice("osmo/local/events/wf-1", b'{"workflow_id": "wf-1"}', sig)
    assert not verifier.notice("osmo/local/events/wf-2", b'{"workflow_id": "wf-1"}', sig)
    assert not verifier.notice("osmo/local/events/wf-1", b'{"workflow_id": "wf-1"}',
                               other.sign_notice("osmo/local/events/wf-1",
                                                 b'{"workflow_id": "wf-1"}'))
    assert not verifier.notice("osmo/local/events/wf-1", b"{}", None)


def test_the_token_keys_are_the_same_from_the_token_and_from_its_digest() -> None:
    from osmo.transport.auth import token_digest

    assert TokenKeys.from_token(TOKEN + "\n") == TokenKeys.from_digest(token_digest(TOKEN))
    assert TokenKeys.from_token(TOKEN).id != TokenKeys.from_token(OTHER).id


# ---------------------------------------------------------------------- on the wire


class Impostor:
    """A peer that answers every query under the cluster prefix and records what it hears."""

    def __init__(self, link: Link) -> None:
        self.heard: list[tuple[str, bytes, bytes | None]] = []
        self._lock = threading.Lock()
        self._sub = link.serve(link.key("**"), self._answer)
        self._seen = link.subscribe_raw(link.key("**"), self._listen)

    def _answer(self, request: Request) -> None:
        with self._lock:
            self.heard.append((request.key, request.payload, request.attachment))
        request.reply(b'{"ok": {"forged": true}}', request.attachment)

    def _listen(self, key: str, data: bytes, att: bytes | None) -> None:
        with self._lock:
            self.heard.append((key, data, att))

    def everything(self) -> bytes:
        with self._lock:
            return b"".join(k.encode() + d + (a or b"") for k, d, a in self.heard)


def test_calls_are_sealed_and_an_impostor_is_neither_believed_nor_told(
        sealed: Sealed, endpoint: str) -> None:
    attacker = Link.client([endpoint])
    try:
        impostor = Impostor(attacker)
        time.sleep(0.3)
        for i in range(3):
            assert sealed.api.call("list", {"n": i, "secret": "s3cr3t"}) == {
                "verb": "list", "echo": {"n": i, "secret": "s3cr3t"}, "who": "alice"}
        deadline = time.monotonic() + 5
        while len(impostor.heard) < 4:  # its copies of the hello and the 3 calls
            assert time.monotonic() < deadline, "the impostor heard too little: no test"
            time.sleep(0.02)
        heard = impostor.everything()
        assert TOKEN.encode() not in heard and b"s3cr3t" not in heard
        assert sealed.calls[0][2].channel, "the handler learns the caller's channel"
    finally:
        attacker.close()


def test_a_replayed_request_is_refused(sealed: Sealed, endpoint: str) -> None:
    attacker = Link.client([endpoint])
    try:
        impostor = Impostor(attacker)
        time.sleep(0.3)
        sealed.api.call("cancel", {"workflow_id": "wf-1"})
        deadline = time.monotonic() + 5
        while not any(h[0].endswith("api/cancel") for h in impostor.heard):
            assert time.monotonic() < deadline, "the impostor never heard the request"
            time.sleep(0.02)
        key, payload, att = next(h for h in impostor.heard if h[0].endswith("api/cancel"))
        replies = list(Link.replies(attacker.ask(key, payload, attachment=att, timeout=3)))
        assert [v for v, _r, _w in sealed.calls] == ["cancel"], "the replay ran"
        assert any(b"NotAuthenticated" in r for r, _a in replies)
    finally:
        attacker.close()


def test_a_client_says_hello_again_after_the_server_restarts(sealed: Sealed,
                                                             links: tuple[Link, Link]) -> None:
    assert sealed.api.call("ping")["who"] == "alice"
    sealed.server.close()
    fresh = Gate({TOKEN: "alice"})
    server = ApiServer(links[0], lambda verb, req, who: who.name, fresh)
    try:
        assert sealed.api.call("ping") == "alice"
    finally:
        server.close()


def test_an_unknown_token_is_refused_at_hello(sealed: Sealed, links: tuple[Link, Link]) -> None:
    stranger = ApiClient(links[1], token="osmo_nobody-knows-me", timeout=5)
    with pytest.raises(NotAuthenticated, match="does not know this token"):
        stranger.call("ping")
    with pytest.raises(NotAuthenticated, match="needs a token"):
        ApiClient(links[1], timeout=5).call("ping")
    assert sealed.calls == []
