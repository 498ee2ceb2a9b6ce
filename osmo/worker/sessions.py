"""The node's side of interactive sessions: exec and port-forward into a running attempt.

The server grants a session (``osmo.server.sessions``) and either opens it here directly
(its own local pool) or orders a remote worker to: the order on ``to-worker/<id>`` carries
only a one-time ticket, which the worker trades for the grant in an authenticated
``worker_session`` request (granted only for an attempt placed on that worker), because
any zenoh peer can read orders. :class:`NodeSessions` then runs the session against the
pool's running attempt:

- the node waits for the client's ``HELLO`` (the client may subscribe after the order);
- exec runs what the attempt's runtime says (``Runtime.exec``; spawned by
  ``osmo.worker.exec_process``): in the attempt's container (``podman exec``), or in its
  working folder with its environment (in a new bubblewrap sandbox over the attempt's own
  view when the attempt is sandboxed);
- port-forward connects each channel the way the attempt's runtime says
  (``Runtime.connector``): to the task's port on the container's address (a container task:
  its own network namespace, as OSMO's pod) or, for a process task, only to a port a process
  of the task listens on, at the address it listens on (``osmo.runtime.process.ports``), from
  inside the node's network namespace when the task is sandboxed
  (``osmo.runtime.process.netns``): never to another process's port on the node nor to a
  listener on the host's own loopback; and only to the ports the grant names.

Every session ends, and its process or sockets with it, when its command exits, when the
client goes silent (``osmo.transport.streams``), when the attempt stops running here, or
when :meth:`NodeSessions.close` runs (the server or worker stops).
"""

from __future__ import annotations

import json
import logging
import threading
from collections.abc import Callable
from typing import Any, Protocol

from osmo.errors import OsmoError
from osmo.runtime.api import ConnectError, Connector
from osmo.transport.forwarding import Channels, Deferred, TcpEnd, UdpConnected
from osmo.transport.streams import TIMEOUT, Frame, Kind, SessionGrant, Stream
from osmo.transport.zenoh_link import Link
from osmo.worker.exec_process import DEFAULT_COMMAND, ExecProcess
from osmo.worker.live import Running

__all__ = ["NodeSessions", "SessionPool"]

log = logging.getLogger("osmo.sessions")

_WATCH_EVERY = 0.5
_MAX_SESSIONS = 256


class SessionPool(Protocol):
    """What a session needs of the pool that runs the attempt (``LocalPool``)."""

    def running(self, attempt_id: str) -> Running | None:
        """The attempt's runtime, launch and handle while it runs here."""


class _Session:
    """One session: its stream, its end conditions (see the module docstring)."""

    def __init__(self, link: Link, grant: SessionGrant, pool: SessionPool,
                 on_done: Callable[[_Session], None]) -> None:
        self.grant, self._pool, self._on_done = grant, pool, on_done
        self._hello = threading.Event()
        self._ended = threading.Event()
        self._lock = threading.Lock()
        self.stream = Stream(link, grant, "node", self._on_frame,
                             lambda: self.end(None, "the client went away"))
        threading.Thread(target=self._run, name="osmo-session", daemon=True).start()

    def _on_frame(self, frame: Frame) -> None:
        if frame.kind is Kind.HELLO:
            self._hello.set()
        elif frame.kind is Kind.CLOSE and frame.channel == 0:
            self.end(None, "the client left")
        elif self._hello.is_set():
            self.on_frame(frame)

    def on_frame(self, frame: Frame) -> None:
        """A frame of the client (after its HELLO)."""

    def _run(self) -> None:
        if not self._hello.wait(TIMEOUT * 2):
            self.end(None, "the client never came")
            return
        running = self._pool.running(self.grant.attempt_id)
        if running is None:
            self.end(None, f"attempt {self.grant.attempt_id} is not running on this node "
                           "(it ended, or has not started yet)")
            return
        threading.Thread(target=self._watch, name="osmo-session-watch", daemon=True).start()
        try:
            self.serve(running)
        except (OsmoError, OSError) as exc:
            self.end(None, f"cannot open the session: {exc}")
        except Exception as exc:  # noqa: BLE001 - a bug ends this session, not the node
            log.exception("session %s", self.grant.session_id[:8])
            self.end(None, f"session failed: {exc!r}")

    def serve(self, running: Running) -> None:
        """Run the session (on its own thread) until it is over; end it."""

    def _watch(self) -> None:
        while not self._ended.wait(_WATCH_EVERY):
            if self._pool.running(self.grant.attempt_id) is None:
                self.end(None, "the task ended")

    def end(self, code: int | None, message: str) -> None:
        """End the session once: stop what it runs, tell the client why."""
        with self._lock:
            if self._ended.is_set():
                return
            self._ended.set()
        self.stop()
        self.stream.send_json(Kind.END, 0, {"code": code, "message": message})
        self.stream.close()
        log.info("session %s (%s of %s) ended: %s", self.grant.session_id[:8], self.grant.kind,
                 self.grant.attempt_id, message or f"exit {code}")
        self._on_done(self)

    def stop(self) -> None:
        """Kill what the session runs (idempotent)."""


class _Exec(_Session):
    """``osmo workflow exec``: one command, its input, output and exit code."""

    proc: ExecProcess | None = None

    def serve(self, running: Running) -> None:
        grant = self.grant
        command = running.runtime.exec(running.launch, grant.command or DEFAULT_COMMAND,
                                       tty=grant.tty, term=grant.term)
        try:
            self.proc = ExecProcess(command, tty=self.grant.tty, size=self.grant.size,
                                    out=lambda ch, data: self.stream.send(Kind.DATA, ch, data))
        except FileNotFoundError:
            self.end(127, f"{command.argv[0]}: command not found")
            return
        if self._ended.is_set():  # ended while it started
            self.proc.kill()
            return
        self.stream.send(Kind.READY)
        code = self.proc.run()  # this thread spawned it: it dies with this thread too
        self.end(code, "")

    def on_frame(self, frame: Frame) -> None:
        proc = self.proc
        if proc is None:
            return
        if frame.kind is Kind.DATA:
            proc.write(frame.data)
        elif frame.kind is Kind.EOF:
            proc.close_input()
        elif frame.kind is Kind.RESIZE:
            rows, cols = json.loads(frame.data)
            proc.resize(int(rows), int(cols))

    def stop(self) -> None:
        if self.proc is not None:
            self.proc.kill()


class _Forward(_Session):
    """``osmo workflow port-forward``: channels to the task's ports."""

    def __init__(self, *args: Any) -> None:
        self._channels = Channels(lambda kind, ch, data: self.stream.send(kind, ch, data))
        self._connect: Connector | None = None  # the attempt's runtime's way to its ports
        super().__init__(*args)

    def serve(self, running: Running) -> None:
        try:
            self._connect = running.runtime.connector(running.launch, running.handle)
        except ConnectError as exc:
            self.end(None, str(exc))
            return
        self.stream.send(Kind.READY)
        self._ended.wait()

    def on_frame(self, frame: Frame) -> None:
        if frame.kind is not Kind.OPEN:
            self._channels.deliver(frame)
            return
        try:
            want = json.loads(frame.data)
            port, udp = int(want["port"]), bool(want.get("udp"))
        except (ValueError, KeyError, TypeError):
            self.stream.send(Kind.CLOSE, frame.channel, b"malformed OPEN")
            return
        if port not in self.grant.ports or udp != self.grant.udp:
            self.stream.send(Kind.CLOSE, frame.channel, b"port not granted to this session")
            return
        pending = Deferred()
        if not self._channels.add(frame.channel, pending):
            self.stream.send(Kind.CLOSE, frame.channel, b"too many connections")
            return
        # off the stream's thread: a port that does not answer stalls only this channel
        threading.Thread(target=self._open, args=(frame.channel, port, udp, pending),
                         name="osmo-forward-connect", daemon=True).start()

    def _open(self, channel: int, port: int, udp: bool, pending: Deferred) -> None:
        connect = self._connect
        if connect is None:  # an OPEN before READY
            if self._channels.drop(channel):
                self.stream.send(Kind.CLOSE, channel, b"the session is not ready")
            return
        try:
            sock = connect(port, udp)
        except ConnectError as exc:
            if self._channels.drop(channel):
                self.stream.send(Kind.CLOSE, channel, str(exc).encode())
            return
        try:
            attached = pending.attach(UdpConnected(sock) if udp else TcpEnd(sock))
        except OSError:
            sock.close()
            if self._channels.drop(channel):
                self.stream.send(Kind.CLOSE, channel, b"")
            return
        if attached:
            self._channels.pump(channel, sock, datagrams=udp)

    def stop(self) -> None:
        self._channels.close()


class NodeSessions:
    """The sessions of one node (server's local pool, or a remote worker).

    Args:
        link: the zenoh link.
        pool: the pool running the attempts.
        ask_grant: trades an order's ticket for its grant (a remote worker's
            ``worker_session`` request); None on the server, which opens sessions directly.
    """

    def __init__(self, link: Link, pool: SessionPool,
                 ask_grant: Callable[[str], dict[str, Any]] | None = None) -> None:
        self._link, self._pool, self._ask = link, pool, ask_grant
        self._lock = threading.Lock()
        self._sessions: dict[str, _Session] = {}
        self._closed = False

    def open(self, grant: SessionGrant) -> None:
        """Start serving ``grant`` (it waits for its client's HELLO)."""
        kind = _Exec if grant.kind == "exec" else _Forward
        with self._lock:
            if self._closed or grant.session_id in self._sessions or \
                    len(self._sessions) >= _MAX_SESSIONS:
                log.warning("session %s refused (closing, duplicate or too many)",
                            grant.session_id[:8])
                return
            self._sessions[grant.session_id] = kind(self._link, grant, self._pool, self._done)
        log.info("session %s: %s into %s", grant.session_id[:8], grant.kind, grant.attempt_id)

    def order(self, ticket: str) -> None:
        """A session order's ``ticket``: fetch its grant (another thread: it asks the server)."""
        ask = self._ask
        if ask is None:
            return
        threading.Thread(target=self._fetch, args=(ask, ticket), name="osmo-session-grant",
                         daemon=True).start()

    def _fetch(self, ask: Callable[[str], dict[str, Any]], ticket: str) -> None:
        try:
            grant = SessionGrant.from_dict(ask(ticket))
        except OsmoError as exc:
            log.warning("session ticket refused: %s", exc)
            return
        self.open(grant)

    def _done(self, session: _Session) -> None:
        with self._lock:
            self._sessions.pop(session.grant.session_id, None)

    def close(self, why: str = "the node is stopping") -> None:
        """End every session (the node stops); no new ones are opened."""
        with self._lock:
            self._closed = True
            sessions = list(self._sessions.values())
        for session in sessions:
            session.end(None, why)


