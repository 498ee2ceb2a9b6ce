"""Which ports a running process task listens on, read from ``/proc``: what port-forward reaches.

OSMO's port-forward reaches any port of the task's pod, which is the task's own network
namespace, never the node's. A process task here shares the node's network (unless its
sandbox gives it one of its own), so the node's loopback also holds other processes' ports:
the server's listener, a database, another user's task. :func:`task_listener` therefore
answers where to connect for a port only when a process of the task holds a socket bound to
it (TCP: listening; UDP: bound), found by matching the socket inodes in the task's
``/proc/<pid>/fd`` with the tables of their network namespace (``/proc/<pid>/net/tcp`` and
``tcp6``, ``udp``, ``udp6``; the node's, or the task's own if its sandbox gives it one: then
the caller must connect from inside that namespace). The answer is the address that socket
is bound to (loopback for a wildcard bind), so a task listening on ``127.0.0.2:5432`` does
not open a way to another process on ``127.0.0.1:5432``.

The task's processes are its main process and its descendants (a sandbox's pid namespace
keeps them all below it); a daemon that left the tree unsandboxed is not the task's any more.
Linux only; reading another uid's ``/proc/<pid>/fd`` needs the worker to be that uid or root,
as it is for the tasks it starts. :func:`listener_connector` is the process runtimes'
``Runtime.connector``.
"""

from __future__ import annotations

import ipaddress
import os
import socket
import sys
from collections.abc import Iterator

from osmo.runtime.api import ConnectError, Connector, SocketMaker, dial

__all__ = ["listener_connector", "task_listener", "task_pids"]

_LISTEN = "0A"  # TCP state in /proc/net/tcp


def task_pids(pid: int) -> set[int]:
    """``pid`` and every process below it (one scan of ``/proc``)."""
    children: dict[int, list[int]] = {}
    for entry in os.listdir("/proc"):
        if entry.isdigit():
            parent = _ppid(int(entry))
            if parent is not None:
                children.setdefault(parent, []).append(int(entry))
    found, todo = set(), [pid]
    while todo:
        current = todo.pop()
        if current not in found:
            found.add(current)
            todo.extend(children.get(current, ()))
    return found


def task_listener(pid: int, port: int, *, udp: bool = False) -> str | None:
    """The address to connect to for ``port`` of the task whose main process is ``pid``.

    None when no process of the task holds a socket bound to ``port`` (listening, for TCP).
    """
    owners = {p: set(_socket_inodes(p)) for p in task_pids(pid)}
    inodes = set().union(*owners.values())
    for owner in _one_per_namespace([p for p, found in owners.items() if found]):
        for table in (("udp", "udp6") if udp else ("tcp", "tcp6")):
            for address, bound, state, inode in _sockets(f"/proc/{owner}/net/{table}"):
                if bound == port and inode in inodes and (udp or state == _LISTEN):
                    return _reachable(address)
    return None


def listener_connector(pid: int, make: SocketMaker = socket.socket) -> Connector:
    """Port-forward's way to the task whose main process is ``pid``: to its own listeners only.

    ``make``: makes the socket to connect, inside the task's network namespace when it has
    one of its own (default: the node's).
    """
    def connect(port: int, udp: bool) -> socket.socket:
        host = task_listener(pid, port, udp=udp)
        if host is None:
            raise ConnectError(f"no process of the task listens on {'UDP' if udp else 'TCP'} "
                               f"port {port}")
        return dial(host, port, udp=udp, make=make)

    return connect


def _one_per_namespace(pids: list[int]) -> list[int]:
    """One of ``pids`` per network namespace (a sandbox may give the task its own)."""
    seen: dict[int, int] = {}
    for pid in pids:
        try:
            seen.setdefault(os.stat(f"/proc/{pid}/ns/net").st_ino, pid)
        except OSError:
            continue
    return list(seen.values())


def _reachable(address: str) -> str:
    """Where to connect to a socket bound to ``address`` (a wildcard: that family's loopback)."""
    ip = ipaddress.ip_address(address)
    if ip.is_unspecified:
        return "::1" if ip.version == 6 else "127.0.0.1"
    mapped = getattr(ip, "ipv4_mapped", None)
    return str(mapped or ip)


def _ppid(pid: int) -> int | None:
    try:
        with open(f"/proc/{pid}/stat", "rb") as f:
            return int(f.read().rsplit(b")", 1)[1].split()[1])
    except (OSError, IndexError, ValueError):
        return None  # gone meanwhile


def _socket_inodes(pid: int) -> Iterator[int]:
    try:
        fds = os.listdir(f"/proc/{pid}/fd")
    except OSError:
        return
    for fd in fds:
        try:
            target = os.readlink(f"/proc/{pid}/fd/{fd}")
        except OSError:
            continue
        if target.startswith("socket:["):
            yield int(target[8:-1])


def _sockets(table: str) -> Iterator[tuple[str, int, str, int]]:
    """``(local address, local port, state, inode)`` of each socket in a /proc/net table."""
    try:
        with open(table) as f:
            lines = f.read().splitlines()[1:]
    except OSError:
        return
    for line in lines:
        fields = line.split()
        if len(fields) < 10:
            continue
        address, _, port = fields[1].partition(":")
        yield _address(address), int(port, 16), fields[3], int(fields[9])


def _address(hex_: str) -> str:
    """A /proc/net address: network-order 32-bit words printed as host-order numbers."""
    words = [bytes.fromhex(hex_[i:i + 8]) for i in range(0, len(hex_), 8)]
    if sys.byteorder == "little":
        words = [word[::-1] for word in words]
    return str(ipaddress.ip_address(b"".join(words)))
