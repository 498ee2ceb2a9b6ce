"""``osmo workflow exec`` and ``osmo workflow port-forward``: the client's end of a session.

The server grants the session (``osmo.server.sessions``); this module drives its stream
(``osmo.transport.streams``): it says ``HELLO`` until the node answers ``READY`` (or
``END`` with the reason it could not open), then relays.

- exec with a TTY (stdin and stdout are terminals): the terminal goes raw for the session
  (restored after, whatever happens), every key — Ctrl-C too — travels as a byte, and a
  resize (SIGWINCH) is sent along. Without one, stdin, stdout and stderr are relayed and
  the end of stdin is passed on. The exit code is the remote command's.
- port-forward listens on ``--host`` (127.0.0.1 by default) for each local port and opens a
  channel per accepted connection (TCP) or per sender (``--udp``) until Ctrl-C or the end
  of the task, then says why it stopped.

Exit codes: the command's (exec); 0 after Ctrl-C or the end of the task (port-forward);
2 for a refused or mistaken request; 3 when the node cannot be reached or went silent.
"""

from __future__ import annotations

import argparse
import itertools
import json
import os
import re
import signal
import socket
import sys
import termios
import threading
import tty
from collections.abc import Callable
from typing import Any

from osmo.cli.render import print_error, safe
from osmo.errors import InfrastructureError, UsageError
from osmo.sdk.client import Client
from osmo.transport.forwarding import Channels, TcpEnd, UdpPeer
from osmo.transport.streams import TIMEOUT, Frame, Kind, SessionGrant, Stream
from osmo.transport.zenoh_link import Link

__all__ = ["add_parsers", "parse_ports", "run_exec", "run_forward"]

_HELLO_EVERY = 0.2
_READY_TIMEOUT = 20.0
_PORTS = re.compile(r"(\d+)(?:-(\d+))?(?::(\d+)(?:-(\d+))?)?")


def add_parsers(sub: argparse._SubParsersAction) -> None:  # type: ignore[type-arg]
    """``exec`` and ``port-forward`` (top level and under ``osmo workflow``)."""
    p = sub.add_parser("exec", help="run a command (default: a shell) in a running task")
    p.add_argument("workflow_id")
    p.add_argument("task")
    p.add_argument("--group", help="the task's group (checked)")
    p.add_argument("command", nargs="*", metavar="-- CMD",
                   help="the command and its arguments, after -- (default /bin/sh)")
    p = sub.add_parser("port-forward", help="forward local ports to a running task's ports")
    p.add_argument("workflow_id")
    p.add_argument("task")
    p.add_argument("--port", required=True, metavar="L[:R][,L2-L3:R2-R3]",
                   help="local port(s) and the task's port(s) they reach (R defaults to L)")
    p.add_argument("--udp", action="store_true", help="forward UDP datagrams instead of TCP")
    p.add_argument("--host", default="127.0.0.1", help="local address to listen on")
    p.add_argument("--group", help="the task's group (checked)")


def parse_ports(text: str) -> list[tuple[int, int]]:
    """``L[:R][,L2-L3:R2-R3]`` → ``[(local, remote), ...]``.

    Raises:
        UsageError: a malformed list, a port out of 1-65535, ranges of unequal length.
    """
    pairs: list[tuple[int, int]] = []
    for part in text.split(","):
        found = _PORTS.fullmatch(part.strip())
        if found is None:
            raise UsageError(f"--port {safe(text)}: write L[:R][,L2-L3:R2-R3]")
        lo, hi, rlo, rhi = found.groups()
        local = range(int(lo), int(hi or lo) + 1)
        first = int(rlo) if rlo else int(lo)
        remote = range(first, int(rhi) + 1) if rhi else range(first, first + len(local))
        if len(local) != len(remote) or not local:
            raise UsageError(f"--port {safe(part)}: the local and remote ranges differ in "
                             "length")
        pairs += zip(local, remote, strict=True)
    if not all(0 < p < 65536 for pair in pairs for p in pair):
        raise UsageError(f"--port {safe(text)}: ports are 1-65535")
    if len({lp for lp, _ in pairs}) != len(pairs) or len(pairs) > 1024:
        raise UsageError(f"--port {safe(text)}: a local port twice, or more than 1024")
    return pairs


class _Session:
    """The client's end: handshake, the node's frames, and how it ended."""

    def __init__(self, grant: SessionGrant, link: Link,
                 on_frame: Callable[[Frame], None]) -> None:
        self._on_frame = on_frame
        self.ready = threading.Event()
        self.done = threading.Event()
        self.code: int | None = None
        self.message = ""
        self.stream = Stream(link, grant, "client", self._frame, self._lost)

    def _frame(self, frame: Frame) -> None:
        if frame.kind is Kind.READY:
            self.ready.set()
        elif frame.kind is Kind.END:
            ended = json.loads(frame.data or b"{}")
            code = ended.get("code")
            self.code = code if isinstance(code, int) else None
            self.message = str(ended.get("message") or "")
            self.done.set()
        else:
            self._on_frame(frame)

    def _lost(self) -> None:
        self.message = f"lost the session: no word from the task's node for {TIMEOUT:g}s"
        self.done.set()

    def open(self) -> None:
        """Say HELLO until the node is ready.

        Raises:
            InfrastructureError: it ended first, or did not answer.
        """
        for _ in range(int(_READY_TIMEOUT / _HELLO_EVERY)):
            self.stream.send(Kind.HELLO)
            if self.ready.wait(_HELLO_EVERY) or self.done.is_set():
                break
        if not self.ready.is_set():
            self.stream.close()
            raise InfrastructureError(self.message or "the task's node did not open the "
                                      f"session within {_READY_TIMEOUT:g}s (is its worker up?)")

    def close(self) -> None:
        """Tell the node the client leaves, and stop the stream."""
        self.stream.send(Kind.CLOSE, 0)
        self.stream.close()


def _write_all(fd: int, data: bytes) -> None:
    view = memoryview(data)
    while view:
        try:
            view = view[os.write(fd, view):]
        except BlockingIOError:
            continue
        except OSError:
            return


def _pump_stdin(session: _Session, *, eof: bool) -> None:
    while True:
        try:
            data = os.read(0, 65536)
        except OSError:
            data = b""
        if not data:
            if eof:
                session.stream.send(Kind.EOF)
            return
        if not session.stream.send(Kind.DATA, 0, data):
            return


def _exec_request(args: argparse.Namespace, tty_mode: bool) -> dict[str, Any]:
    command = list(args.command)
    rows, cols = (24, 80)
    if tty_mode:
        rows, cols = _terminal_size()
    return {"workflow_id": args.workflow_id, "task": args.task, "group": args.group,
            "command": command, "tty": tty_mode, "size": [rows, cols],
            "term": os.environ.get("TERM", "xterm")[:64]}


def run_exec(args: argparse.Namespace) -> int:
    """``osmo workflow exec ID TASK [--group G] [-- CMD...]``."""
    tty_mode = os.isatty(0) and os.isatty(1)

    def deliver(frame: Frame) -> None:
        if frame.kind is Kind.DATA and frame.channel in (1, 2):
            _write_all(frame.channel, frame.data)

    with Client(args.server) as client:
        grant, link = client.open_session("exec_open", **_exec_request(args, tty_mode))
        session = _Session(grant, link, deliver)
        session.open()
        saved = termios.tcgetattr(0) if tty_mode else None
        try:
            if saved is not None:
                tty.setraw(0, termios.TCSANOW)  # keep what was typed already
                signal.signal(signal.SIGWINCH, lambda *_: _send_size(session))
            threading.Thread(target=_pump_stdin, args=(session,),
                             kwargs={"eof": not tty_mode}, daemon=True).start()
            while not session.done.wait(0.5):
                pass
        finally:
            if saved is not None:
                termios.tcsetattr(0, termios.TCSADRAIN, saved)
                signal.signal(signal.SIGWINCH, signal.SIG_DFL)
            session.close()
    if session.message:
        print_error(session.message)
    return session.code if session.code is not None else 3


def _terminal_size() -> tuple[int, int]:
    """The terminal's rows and columns (24x80 when it does not say: a fresh pty is 0x0)."""
    try:
        size = os.get_terminal_size(1)
    except OSError:
        return 24, 80
    return size.lines or 24, size.columns or 80


def _send_size(session: _Session) -> None:
    session.stream.send_json(Kind.RESIZE, 0, list(_terminal_size()))


class _Forwarder:
    """The client's listeners and channels of one port-forward session."""

    def __init__(self, session_of: Callable[[], _Session], udp: bool) -> None:
        self._session_of, self._udp = session_of, udp
        self.channels = Channels(lambda kind, ch, data: self._session_of().stream.send(
            kind, ch, data))
        self._ids = itertools.count(1)
        self._ports: dict[int, int] = {}  # channel -> remote port (for messages)

    def deliver(self, frame: Frame) -> None:
        if frame.kind is Kind.CLOSE and frame.data:
            print_error(f"port {self._ports.get(frame.channel, '?')}: "
                        f"{frame.data.decode(errors='replace')}")
        self.channels.deliver(frame)

    def _open(self, remote: int) -> int:
        channel = next(self._ids)
        self._ports[channel] = remote
        self._session_of().stream.send_json(Kind.OPEN, channel,
                                            {"port": remote, "udp": self._udp})
        return channel

    def serve_tcp(self, listener: socket.socket, remote: int) -> None:
        while True:
            try:
                sock, _ = listener.accept()
            except OSError:
                return
            channel = self._open(remote)
            if self.channels.add(channel, TcpEnd(sock)):
                self.channels.pump(channel, sock)

    def serve_udp(self, sock: socket.socket, remote: int) -> None:
        senders: dict[tuple[str, int], int] = {}
        while True:
            try:
                data, addr = sock.recvfrom(65535)
            except OSError:
                return
            channel = senders.get(addr)
            if channel is None:
                channel = senders[addr] = self._open(remote)
                self.channels.add(channel, UdpPeer(sock, addr))
            self._session_of().stream.send(Kind.DATA, channel, data)


def _listen(host: str, port: int, udp: bool) -> socket.socket:
    family = socket.AF_INET6 if ":" in host else socket.AF_INET
    sock = socket.socket(family, socket.SOCK_DGRAM if udp else socket.SOCK_STREAM)
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
    try:
        sock.bind((host, port))
        if not udp:
            sock.listen(128)
    except OSError as exc:
        sock.close()
        raise UsageError(f"cannot listen on {safe(host)}:{port}: {exc.strerror or exc}") from None
    return sock


def run_forward(args: argparse.Namespace) -> int:
    """``osmo workflow port-forward ID TASK --port L[:R],... [--udp] [--host ADDR]``."""
    pairs = parse_ports(args.port)
    listeners = [(_listen(args.host, local, args.udp), remote) for local, remote in pairs]
    holder: list[_Session] = []
    forwarder = _Forwarder(lambda: holder[0], args.udp)
    try:
        with Client(args.server) as client:
            grant, link = client.open_session(
                "forward_open", workflow_id=args.workflow_id, task=args.task,
                group=args.group, ports=sorted({r for _, r in pairs}), udp=args.udp)
            holder.append(_Session(grant, link, forwarder.deliver))
            holder[0].open()
            serve = forwarder.serve_udp if args.udp else forwarder.serve_tcp
            for (sock, remote), (local, _) in zip(listeners, pairs, strict=True):
                threading.Thread(target=serve, args=(sock, remote), daemon=True).start()
                print(f"Forwarding from {args.host}:{local} -> {remote}"
                      f"{' (udp)' if args.udp else ''}", flush=True)
            try:
                while not holder[0].done.wait(0.5):
                    pass
            except KeyboardInterrupt:
                print("port-forward stopped", file=sys.stderr)
                return 0
            finally:
                holder[0].close()
                forwarder.channels.close()
    finally:
        for sock, _ in listeners:
            sock.close()
    if holder[0].message.startswith("lost"):
        print_error(f"port-forward stopped: {holder[0].message}")
        return 3
    print(f"port-forward stopped: {safe(holder[0].message)}", file=sys.stderr)
    return 0
