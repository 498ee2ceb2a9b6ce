"""The server's side of interactive sessions: who may open one, and where it runs.

Verbs:

- ``exec_open`` (``osmo workflow exec``) and ``forward_open`` (``osmo workflow
  port-forward``): an admin, or the user who submitted the workflow (a worker token is
  refused by the role policy), names a workflow, a task (and optionally its group); the
  task must be RUNNING. The reply holds the session's grant — a 128-bit random id and a
  256-bit key (``osmo.transport.streams``) — and is the only place the client learns them.
- ``worker_session`` (worker verb): a remote worker trades the one-time ticket of a
  ``session`` order for the grant; only the worker the attempt is placed on gets it, once,
  within :data:`TICKET_TTL` seconds. Orders travel as puts any zenoh peer can read, which is
  why they carry a ticket and never a session id or key.

A session on the server's own pool is opened directly (``osmo.worker.sessions``).
"""

from __future__ import annotations

import logging
import secrets
import threading
import time
from typing import Any

from osmo.errors import NotFoundError, UsageError
from osmo.names import check_name, check_workflow_id, did_you_mean, shown
from osmo.scheduler.types import LOCAL_NODE
from osmo.server.auth import check_owner, refuse
from osmo.server.workers import WorkerHub
from osmo.store.sqlite import Store
from osmo.transport.auth import Identity
from osmo.transport.rpc import field, str_list
from osmo.transport.streams import MAX_COMMAND, MAX_PORTS, SessionGrant
from osmo.transport.wire import OpenSession
from osmo.worker.sessions import NodeSessions

__all__ = ["TICKET_TTL", "Sessions"]

log = logging.getLogger("osmo.sessions")

TICKET_TTL = 30.0
"""Seconds a worker has to fetch a session order's grant."""
_MAX_TICKETS = 1024
_MAX_WORD = 4096  # characters of one exec command word


class Sessions:
    """Grants sessions (see the module docstring).

    Args:
        store: the state store (workflows, tasks, attempts).
        hub: the remote workers (orders, and who an attempt is placed on).
        local: the server's own pool's sessions (None without a local pool).
    """

    def __init__(self, store: Store, hub: WorkerHub, local: NodeSessions | None) -> None:
        self._store, self._hub, self._local = store, hub, local
        self._lock = threading.Lock()
        self._tickets: dict[str, tuple[str, SessionGrant, float]] = {}

    def exec_open(self, request: dict[str, Any], who: Identity) -> dict[str, Any]:
        """Open an exec session: ``command`` (words; empty: a shell), ``tty``, ``size``."""
        command = str_list(request, "command")
        if len(command) > MAX_COMMAND or any(len(w) > _MAX_WORD or "\0" in w for w in command):
            raise UsageError("the command has too many or too long words (or a NUL byte)")
        size = field(request, "size", list, default=[24, 80])
        if len(size) != 2 or not all(type(x) is int and 0 < x < 10_000 for x in size):
            raise UsageError("'size' must be [rows, cols]")
        return self._open(request, who, "exec_open", kind="exec", command=tuple(command),
                          tty=field(request, "tty", bool, default=False),
                          term=field(request, "term", str, default="xterm", max_len=64),
                          size=(size[0], size[1]))

    def forward_open(self, request: dict[str, Any], who: Identity) -> dict[str, Any]:
        """Open a port-forward session to the task ports ``ports`` (TCP, or ``udp``)."""
        ports = field(request, "ports", list)
        if not ports or len(ports) > MAX_PORTS or not all(
                type(p) is int and 0 < p < 65536 for p in ports):
            raise UsageError(f"'ports' must be 1 to {MAX_PORTS} port numbers (1-65535)")
        return self._open(request, who, "forward_open", kind="forward",
                          ports=tuple(sorted(set(ports))),
                          udp=field(request, "udp", bool, default=False))

    def _open(self, request: dict[str, Any], who: Identity, verb: str,
              **details: Any) -> dict[str, Any]:
        attempt_id, node = self._running_attempt(request, who, verb)
        grant = SessionGrant(secrets.token_hex(16), secrets.token_bytes(32),
                             attempt_id=attempt_id, **details)
        if node == LOCAL_NODE:
            if self._local is None:
                raise UsageError("this server has no local pool")
            self._local.open(grant)
        else:
            ticket = secrets.token_hex(16)
            with self._lock:
                now = time.monotonic()
                self._tickets = {t: v for t, v in self._tickets.items() if v[2] > now}
                if len(self._tickets) >= _MAX_TICKETS:
                    raise UsageError("too many sessions are being opened; try again")
                self._tickets[ticket] = (node, grant, now + TICKET_TTL)
            self._hub.tell(node, OpenSession(ticket))
        log.info("%s: %s session on %s for %s", who, grant.kind, node, attempt_id)
        return {"grant": grant.to_dict(), "node": node}

    def worker_session(self, request: dict[str, Any], who: Identity) -> dict[str, Any]:
        """The grant of a ``session`` order's ticket, for the worker it was sent to.

        Raises:
            NotAllowed: an unknown, used or expired ticket, or one for another worker.
        """
        ticket = field(request, "ticket", str, max_len=64)
        wid = self._hub.speaker("worker_session", request, who)
        with self._lock:  # taken only by its worker: a peer that read it cannot spend it
            found = self._tickets.get(ticket)
            if found is not None and found[0] == wid:
                del self._tickets[ticket]
        if found is None or found[2] < time.monotonic() or found[0] != wid:
            raise refuse("worker_session", who, "unknown, used or expired session ticket, "
                                                "or one for another worker")
        self._hub.check_placed("worker_session", wid, found[1].attempt_id, who)
        return found[1].to_dict()

    def _running_attempt(self, request: dict[str, Any], who: Identity,
                         verb: str) -> tuple[str, str]:
        """``(attempt id, node)`` of the running task a request names, if ``who`` owns it."""
        wf_id = check_workflow_id(request.get("workflow_id"))
        row = self._store.workflow(wf_id)
        if row is None:
            raise NotFoundError(f"no workflow '{wf_id}'")
        check_owner(row.id, row.options.submitted_by, who, verb)
        task = check_name(field(request, "task", str, max_len=256), "task name")
        group = field(request, "group", str, default=None, max_len=256)
        if group is not None and task not in _group_tasks(row.spec.data, group):
            raise NotFoundError(f"no task '{task}' in group {shown(group)} of {row.id}")
        states = {t["name"]: t for t in self._store.tasks(row.id)}
        if task not in states:
            raise NotFoundError(f"no task '{task}' in {row.id}{did_you_mean(task, states)}")
        status, retry = states[task].get("status"), int(states[task].get("retry", 0))
        if status != "RUNNING":
            raise UsageError(f"task '{task}' of {row.id} is {status}, not RUNNING; exec and "
                             "port-forward need a running task")
        for attempt in self._store.attempts(row.id, task):
            if attempt.retry == retry and attempt.node_id:
                return attempt.id, attempt.node_id
        raise UsageError(f"task '{task}' of {row.id} is not placed on a node yet; try again")


def _group_tasks(spec: dict[str, Any], group: str) -> set[str]:
    for g in spec.get("workflow", {}).get("groups", []) or []:
        if g.get("name") == group:
            return {t.get("name") for t in g.get("tasks", [])}
    return set()
