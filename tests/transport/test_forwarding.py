"""A channel's end while the node still connects (``Deferred``), with real socket pairs."""

from __future__ import annotations

import socket

import pytest

from osmo.transport.forwarding import _PENDING_BYTES, Deferred, TcpEnd


def test_what_arrives_before_the_connection_is_handed_over_in_order_with_its_eof() -> None:
    pending = Deferred()
    pending.write(b"GET / ")
    pending.write(b"HTTP/1.0\r\n\r\n")
    pending.eof()
    near, far = socket.socketpair()
    with near, far:
        assert pending.attach(TcpEnd(near))
        with pytest.raises(OSError):
            pending.write(b"late")  # after the eof: the socket's write half is shut
        assert far.recv(100) == b"GET / HTTP/1.0\r\n\r\n"
        assert far.recv(100) == b""


def test_writes_after_attach_go_straight_through() -> None:
    pending = Deferred()
    near, far = socket.socketpair()
    with near, far:
        assert pending.attach(TcpEnd(near))
        pending.write(b"abc")
        assert far.recv(10) == b"abc"


def test_a_channel_closed_while_connecting_refuses_and_closes_the_connection() -> None:
    pending = Deferred()
    pending.close()
    near, far = socket.socketpair()
    with near, far:
        assert not pending.attach(TcpEnd(near))
        assert far.recv(10) == b""  # closed by the refusal


def test_a_client_that_floods_a_port_still_connecting_is_cut_off() -> None:
    pending = Deferred()
    pending.write(bytes(_PENDING_BYTES))
    with pytest.raises(OSError, match="before the task's port answered"):
        pending.write(b"x")
