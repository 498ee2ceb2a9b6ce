"""The process that holds a node's network namespace open and makes sockets inside it.

Run by :class:`osmo.runtime.process.netns.NodeNetwork` as a script (``python -I -S netns_keeper.py
FD MODE [ADDRESS...]``), never imported by osmo: it must start fast and import nothing but
the standard library. ``FD`` is its end of a ``SOCK_SEQPACKET`` socket pair. ``MODE`` is
``root`` (osmo runs as root: a new network namespace, which stays the host user namespace's,
then a user namespace for the tasks, which the worker maps) or ``user`` (a user namespace
that maps root to the caller's uid and gid, and a network namespace it owns: what an
unprivileged user may make).

It then brings the loopback interface up, gives it each ADDRESS too (the node's address,
which peers name a task by: ``{{host:NAME}}``, so that a task can listen on it and the
node's other tasks reach it there), says ``ready`` and answers each request
(``tcp4``, ``tcp6``, ``udp4``, ``udp6``) with a new, unconnected socket of that kind,
created inside the namespace and passed back as ``SCM_RIGHTS``: a socket keeps the network
namespace it was made in, so the worker connects it to a task's port as if it were inside.
It exits when the worker's end closes (the worker stopped or died): nothing else holds it.
"""

from __future__ import annotations

import array
import ctypes
import fcntl
import os
import socket
import struct
import sys

_KINDS = {
    b"tcp4": (socket.AF_INET, socket.SOCK_STREAM),
    b"tcp6": (socket.AF_INET6, socket.SOCK_STREAM),
    b"udp4": (socket.AF_INET, socket.SOCK_DGRAM),
    b"udp6": (socket.AF_INET6, socket.SOCK_DGRAM),
}
_SIOCGIFFLAGS, _SIOCSIFFLAGS, _IFF_UP = 0x8913, 0x8914, 0x1
_SIOCSIFADDR, _SIOCSIFNETMASK = 0x8916, 0x891C
_CLONE_NEWUSER, _CLONE_NEWNET = 0x10000000, 0x40000000  # os.unshare is Python 3.12+


def _unshare(flags: int) -> None:
    if ctypes.CDLL(None, use_errno=True).unshare(flags) != 0:
        errno = ctypes.get_errno()
        raise OSError(errno, os.strerror(errno))


def _loopback_addresses(addresses: list[str]) -> None:
    """Add each IPv4 address to the loopback interface (as ``lo:N``, a /32)."""
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        for index, address in enumerate(addresses, 1):
            name = f"lo:{index}".encode().ljust(16, b"\0")
            for request, value in ((_SIOCSIFADDR, address), (_SIOCSIFNETMASK, "255.255.255.255")):
                sockaddr = struct.pack("HH4s8x", socket.AF_INET, 0, socket.inet_aton(value))
                fcntl.ioctl(s, request, name + sockaddr)


def _own_namespaces(mode: str, addresses: list[str]) -> None:
    """Enter a new network namespace (loopback up), then a user namespace over it.

    ``root``: the network namespace is the host user namespace's (tasks gain nothing over
    it), the user namespace is mapped by the worker (``NodeNetwork``). ``user``: both are
    new at once, and the user namespace maps root to the caller's uid and gid.
    """
    if mode == "root":
        _unshare(_CLONE_NEWNET)
        _loopback_up()
        _loopback_addresses(addresses)
        _unshare(_CLONE_NEWUSER)
        return
    uid, gid = os.getuid(), os.getgid()
    _unshare(_CLONE_NEWUSER | _CLONE_NEWNET)
    for name, text in (("setgroups", "deny"), ("uid_map", f"0 {uid} 1"),
                       ("gid_map", f"0 {gid} 1")):
        with open(f"/proc/self/{name}", "w") as f:
            f.write(text)
    _loopback_up()
    _loopback_addresses(addresses)


def _loopback_up() -> None:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        name = b"lo".ljust(16, b"\0")
        flags = struct.unpack("16sH", fcntl.ioctl(s, _SIOCGIFFLAGS, name + b"\0" * 16)[:18])[1]
        fcntl.ioctl(s, _SIOCSIFFLAGS, struct.pack("16sH", name, flags | _IFF_UP) + b"\0" * 14)


def serve(peer: socket.socket) -> None:
    """Answer requests for sockets until the peer closes its end."""
    while True:
        try:
            request = peer.recv(16)
        except InterruptedError:
            continue
        if not request:
            return
        kind = _KINDS.get(request)
        if kind is None:
            peer.send(b"error: unknown socket kind")
            continue
        try:
            made = socket.socket(*kind)
        except OSError as exc:
            peer.send(f"error: {exc.strerror or exc}".encode())
            continue
        with made:
            peer.sendmsg([b"ok"], [(socket.SOL_SOCKET, socket.SCM_RIGHTS,
                                    array.array("i", [made.fileno()]))])


def main(argv: list[str]) -> int:
    """``FD MODE [ADDRESS...]``: make the namespaces, say ``ready`` (or why not), serve."""
    peer = socket.socket(fileno=int(argv[1]))
    try:
        _own_namespaces(argv[2], argv[3:])
    except OSError as exc:
        peer.send(f"error: cannot make a network namespace: {exc}".encode())
        return 1
    peer.send(b"ready")
    serve(peer)
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv))
