"""What the server and a remote worker say to each other: keys and JSON messages.

The server's side is ``osmo.server.workers.WorkerHub``, the worker's
``osmo.worker.remote.RemoteWorker``; both speak only through this module's functions.

Keys, under the cluster prefix ``osmo/<cluster>``:

- ``alive/server`` and ``alive/worker/<id>`` — liveliness tokens. A worker's token going
  away (process killed, network cut: noticed within the 1 s lease) is its ``NodeDown``; the
  server's token coming back tells a worker to register again (both hints, see Trust).
- ``api/worker_register`` — a worker's :class:`Hello`, answered with the server's host id
  and artifact folder (a worker on the same host links blobs instead of fetching) and, for a
  node whose attempts outlive it (``Hello.outlives``), ``placed``: the attempts the server
  still places on it (it cancels any other it adopted); the server pulls the worker's
  outputs from ``blob/<id>/<digest>`` with queries sealed on the channel it registered with
  (``SQ``);
  ``api/worker_drain`` — ``{"id": <worker>}``: it takes no more work;
  ``api/worker_swept`` — ``{"id", "instance"}``: it did what a :class:`Sweep` ordered it
  (until then the server holds the order for it; refused for one not ordered to it).
- ``api/worker_beat`` — ``{"id", "warm"}``, every :data:`BEAT_EVERY` seconds: the worker is
  alive, and its warm runners now (:func:`warm_runners`; ``osmo resource list``)
  (refused once the server forgot it: it registers again).
- ``to-worker/<id>`` — the server's orders (:data:`Order`), sealed: :class:`Prepare` (the
  attempt, the workflow's spec the first time, input manifests, whether to ask for the
  attempt's secrets, the task's storage limit), :class:`Run`, :class:`Kill`, :class:`Ack`
  (an exit report was received and its outputs are safe on the server), and
  :class:`OpenSession` (an exec or port-forward session's ticket), :class:`Sweep` (delete
  what a node of the pool, down for good, left in the cluster). Both sides build and read
  them only as these classes (:func:`order_to_dict`, :func:`order_from_dict`). Secrets are
  asked for apart (``worker_secrets``), so an order never holds one.
- ``api/worker_report`` — ``{"id", "report"}``: the worker's reports (:func:`event_to_dict`),
  ``prepared``, ``started``, ``waiting`` (why its cluster holds the attempt: a pod Pending,
  a Slurm job PENDING; ``""`` once it runs; hostile text, cut and cleaned by
  ``osmo.scheduler.types.wait_reason``), ``exited``, ``start_failed``, ``lost`` (handed
  back while draining);
  ``api/worker_log`` — ``{"id", "attempt_id", "records"}``: log records, appended by the
  server to its copy of the log; ``api/worker_secrets`` — ``{"id", "attempt_id"}``: the
  attempt's secrets and data-URL credentials. Like every API request they are sealed on
  the worker token's channel and are accepted only for attempts placed on that worker
  (``osmo.server.worker_access``).

Trust: no message is believed for its key. Orders are sealed on the channel the worker
registered with (``PUSH``, ``osmo.transport.seal``): a worker obeys only what the server
sealed for it, and no other peer can read an order. Reports, log batches and secret requests
are sealed API requests. The liveliness tokens are hints only (a peer can hold a copy of a
worker's token after the worker died): a registered worker also beats every
:data:`BEAT_EVERY` seconds (``api/worker_beat``), and one silent for :data:`LEASE` seconds is
down, token or no token. :data:`PEER_ALLOW` is the router's allow-list, the second wall:
what any remote peer may do at all.

Attempt ids fence everything: a report about an attempt the scheduler has superseded is
ignored, so a worker that returns late can never commit stale work.
"""

from __future__ import annotations

import re
from collections.abc import Mapping
from dataclasses import asdict, dataclass
from typing import Any

from osmo.errors import UsageError
from osmo.names import check_worker_name, shown
from osmo.scheduler.types import (
    LOCAL_NODE,
    PRIORITIES,
    AttemptExited,
    AttemptLost,
    AttemptPrepared,
    AttemptStarted,
    AttemptStartFailed,
    AttemptWaiting,
    Capacity,
    Event,
    Node,
    PrepareAttempt,
    wait_reason,
)
from osmo.spec.stored import StoredSpec
from osmo.transport.blobs import SERVER
from osmo.transport.rpc import MAX_INT, field, str_list, str_map

__all__ = ["BEAT_EVERY", "LEASE", "MAX_PLATFORMS", "PEER_ALLOW", "PEER_DENY", "Ack", "Hello",
           "Kill", "OpenSession", "Order", "Prepare", "Run", "Sweep", "beat_offer",
           "capacity_from_dict", "capacity_to_dict", "event_from_dict", "event_to_dict",
           "offer_to_dict", "order_from_dict", "order_to_dict", "warm_runners", "worker_id"]

#: zenoh access-control message -> keys (under the cluster prefix) a remote peer may use;
#: the server's router denies everything else (``osmo.transport.zenoh_link.Acl``).
PEER_ALLOW: dict[str, tuple[str, ...]] = {
    "query": ("api/*", f"blob/{SERVER}/*", "podio/**"),  # the API; the server's blobs;
    # a Kubernetes node's pod-data API (osmo.runtime.kubernetes.podio), for its pods
    "declare_queryable": ("blob/*/*", "podio/**"),  # a worker's blobs, for the server
    "reply": ("blob/*/*", "podio/**"),
    "declare_subscriber": ("to-worker/*", "events/*", "stream/*/*"),
    "put": ("stream/*/*",),  # exec and port-forward frames
    "liveliness_token": ("alive/worker/*",),
    "declare_liveliness_subscriber": ("alive/**",),
    "liveliness_query": ("alive/**",),
}
#: Taken back out of :data:`PEER_ALLOW`: only the server serves its own blobs.
PEER_DENY: dict[str, tuple[str, ...]] = {"declare_queryable": (f"blob/{SERVER}/*",)}

BEAT_EVERY = 2.0
"""Seconds between a worker's beats."""
LEASE = 10.0
"""Seconds without a beat after which a registered worker is down."""

_TEXT = 4096  # characters of a name, an address or a folder in a worker's message
MAX_PLATFORMS = 256
"""Platforms one worker may register (a cluster node's node labels or partitions)."""
_PLATFORM = re.compile(r"[^\x00-\x20\x7f-\x9f]{1,253}")  # one printable word
_MAX_RUNNERS = 256  # warm runners one beat may list
_RUNNER_FIELDS = {"type": str, "pid": int, "rss": int, "started": int, "running": int}


def warm_runners(data: dict[str, Any]) -> list[dict[str, Any]]:
    """A beat's ``warm``: the worker's warm runners (``osmo.runtime.process.warm``), checked.

    Raises:
        UsageError: not a list of at most 256 runners, each with ``type`` (text), ``pid``,
            ``rss``, ``started`` and ``running`` (numbers from 0).
    """
    found = field(data, "warm", list, default=[])
    if len(found) > _MAX_RUNNERS:
        raise UsageError(f"'warm' lists {len(found)} runners; at most {_MAX_RUNNERS}")
    out = []
    for item in found:
        if not isinstance(item, dict):
            raise UsageError("'warm' must be a list of runners (objects)")
        runner = {key: field(item, key, kind, max_len=200, what=f"'warm.{key}'")
                  for key, kind in _RUNNER_FIELDS.items()}
        if any(isinstance(v, int) and v < 0 for v in runner.values()):
            raise UsageError(f"'warm': a runner's numbers are from 0, not {shown(runner)}")
        out.append(runner)
    return out


def offer_to_dict(capacity: Capacity, platforms: dict[str, Capacity]) -> dict[str, Any]:
    """A beat's ``offer``: what a cluster node offers now (its capacity and platforms)."""
    return {"capacity": capacity_to_dict(capacity),
            "platforms": {name: capacity_to_dict(cap) for name, cap in platforms.items()}}


def beat_offer(data: dict[str, Any]) -> tuple[Capacity, dict[str, Capacity]] | None:
    """A beat's ``offer``, checked as a hello's capacity and platforms (None: none sent).

    Raises:
        UsageError: not an object, or a capacity or platform a hello could not hold.
    """
    offer = field(data, "offer", dict, default=None)
    if offer is None:
        return None
    return capacity_from_dict(field(offer, "capacity", dict, default={})), _platforms(offer)


def event_to_dict(event: Event) -> dict[str, Any]:
    """A worker's report as JSON-safe data."""
    if isinstance(event, AttemptPrepared):
        return {"op": "prepared", "attempt_id": event.attempt_id}
    if isinstance(event, AttemptStarted):
        return {"op": "started", "attempt_id": event.attempt_id}
    if isinstance(event, AttemptWaiting):
        return {"op": "waiting", "attempt_id": event.attempt_id, "reason": event.reason}
    if isinstance(event, AttemptStartFailed):
        return {"op": "start_failed", "attempt_id": event.attempt_id, "message": event.message}
    if isinstance(event, AttemptLost):
        return {"op": "lost", "attempt_id": event.attempt_id, "message": event.message}
    if isinstance(event, AttemptExited):
        out = asdict(event)
        out["op"] = "exited"
        return out
    raise TypeError(f"not a worker report: {event!r}")


def event_from_dict(data: dict[str, Any]) -> Event:
    """The inverse of :func:`event_to_dict`.

    Raises:
        ValueError: an unknown ``op``.
    """
    op, aid = data.get("op"), str(data.get("attempt_id"))
    if op == "prepared":
        return AttemptPrepared(aid)
    if op == "started":
        return AttemptStarted(aid)
    if op == "waiting":
        return AttemptWaiting(aid, wait_reason(data.get("reason") or ""))
    if op == "start_failed":
        return AttemptStartFailed(aid, str(data.get("message", "")))
    if op == "lost":
        return AttemptLost(aid, str(data.get("message", "worker lost")))
    if op == "exited":
        command = data.get("command")
        return AttemptExited(aid, int(data["exit_code"]), data.get("output"),
                             str(data.get("message") or ""), data.get("manifest"),
                             bool(data.get("cached")),
                             tuple(command) if command is not None else None,
                             _image_id(data.get("image_id")))
    raise ValueError(f"unknown report {op!r}")


def _image_id(value: object) -> str | None:
    """An image id a worker reported (``sha256:<hex>``); anything else is dropped."""
    if isinstance(value, str) and re.fullmatch(r"sha256:[0-9a-f]{64}", value):
        return value
    return None


def capacity_to_dict(capacity: Capacity) -> dict[str, Any]:
    """A worker's capacity as it advertises it."""
    return {"cpu": capacity.cpu, "gpu": capacity.gpu, "memory": capacity.memory,
            "storage": capacity.storage}


def capacity_from_dict(data: dict[str, Any]) -> Capacity:
    """The inverse of :func:`capacity_to_dict`; absent amounts are zero.

    Raises:
        UsageError: an amount that is not a number of the right kind, or is negative.
    """
    cpu = data.get("cpu", 0)
    if isinstance(cpu, bool) or not isinstance(cpu, int | float) or not 0 <= cpu <= MAX_INT:
        raise UsageError(f"'capacity.cpu' must be a number from 0, not {shown(cpu)}")
    amounts = {key: field(data, key, int, default=0, what=f"'capacity.{key}'")
               for key in ("gpu", "memory", "storage")}
    negative = [key for key, value in amounts.items() if value < 0]
    if negative:
        raise UsageError(f"'capacity.{negative[0]}' must not be negative")
    return Capacity(cpu=float(cpu), **amounts)


def worker_id(request: dict[str, Any]) -> str:
    """The worker a request comes from (its ``id``), checked as a worker name.

    Raises:
        UsageError: not a string, or not a name a worker may have.
    """
    return check_worker_name(field(request, "id", str, max_len=_TEXT),
                             reserved=(LOCAL_NODE, SERVER))


@dataclass(frozen=True)
class Hello:
    """A worker's registration: who it is, and what it holds.

    It says hello again after a server restart.

    Attributes:
        node: its name, pool, capacity, platform, address and labels, and every platform it
            serves with each one's capacity (``platforms``: a Kubernetes node's from its
            nodes' labels, a Slurm node's from its partitions; a worker from before that
            field sends ``platform`` only, which then has its whole capacity).
        pid: its process id (shown by ``osmo resource list``).
        host_id, artifacts: its host and its artifact folder (a server on the same host
            links blobs from there instead of fetching them).
        draining: it takes no more work.
        active: the attempts it still runs.
        finished: its exit reports the server has not acknowledged yet.
        runtime: how it runs image tasks: ``container (podman 4.3.1)`` or ``process``.
        sandbox_why: why it runs process tasks unsandboxed, in a few words (``bwrap not
            found``); None: sandboxed, or a worker from before this field.
        outlives: its attempts outlive its process (a cluster's jobs or pods): when it goes
            down the server holds them for a grace and it adopts them when it comes back.
        instance: the label its cluster objects carry (a Kubernetes node's
            ``osmo.dev/instance``; None: it makes none). When it is down for good, the
            server orders another node of its pool to delete them (:class:`Sweep`).
    """

    node: Node
    pid: int | None = None
    host_id: str | None = None
    artifacts: str | None = None
    draining: bool = False
    active: tuple[str, ...] = ()
    finished: tuple[dict[str, Any], ...] = ()
    runtime: str | None = None
    sandbox_why: str | None = None
    outlives: bool = False
    instance: str | None = None

    def to_dict(self) -> dict[str, Any]:
        """The hello as JSON-safe data."""
        node = self.node
        return {"id": node.id, "pool": node.pool, "platform": node.platform,
                "capacity": capacity_to_dict(node.capacity), "labels": dict(node.labels),
                "platforms": {name: capacity_to_dict(cap)
                              for name, cap in node.platforms.items()},
                "address": node.address, "host_id": self.host_id, "artifacts": self.artifacts,
                "pid": self.pid, "draining": self.draining, "active": list(self.active),
                "finished": list(self.finished), "runtime": self.runtime,
                "sandbox_why": self.sandbox_why, "outlives": self.outlives,
                "instance": self.instance}

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> Hello:
        """The inverse of :meth:`to_dict`, every field checked.

        Raises:
            UsageError: a field missing, of the wrong type or out of range.
        """
        node = Node(id=worker_id(data), pool=field(data, "pool", str, max_len=_TEXT),
                    capacity=capacity_from_dict(field(data, "capacity", dict, default={})),
                    platform=field(data, "platform", str, default=None, max_len=_TEXT),
                    address=field(data, "address", str, max_len=_TEXT),
                    labels=str_map(data, "labels"), platforms=_platforms(data))
        finished = field(data, "finished", list, default=[])
        if not all(isinstance(report, dict) for report in finished):
            raise UsageError("'finished' must be a list of reports (objects)")
        return cls(node, pid=field(data, "pid", int, default=None),
                   host_id=field(data, "host_id", str, default=None, max_len=_TEXT),
                   artifacts=field(data, "artifacts", str, default=None, max_len=_TEXT),
                   draining=field(data, "draining", bool, default=False),
                   active=tuple(str_list(data, "active")), finished=tuple(finished),
                   runtime=field(data, "runtime", str, default=None, max_len=_TEXT),
                   sandbox_why=field(data, "sandbox_why", str, default=None, max_len=_TEXT),
                   outlives=field(data, "outlives", bool, default=False),
                   instance=field(data, "instance", str, default=None, max_len=63))


def _platforms(data: dict[str, Any]) -> dict[str, Capacity]:
    """A hello's ``platforms``: name → capacity, each checked (absent: none).

    Raises:
        UsageError: not an object of at most :data:`MAX_PLATFORMS` printable names (no
            spaces) to capacities.
    """
    found = field(data, "platforms", dict, default={})
    if len(found) > MAX_PLATFORMS:
        raise UsageError(f"'platforms' holds {len(found)} platforms; at most "
                         f"{MAX_PLATFORMS} may be registered")
    out: dict[str, Capacity] = {}
    for name, amounts in found.items():
        if not _PLATFORM.fullmatch(name):
            raise UsageError(f"'platforms' names a platform {shown(name)}: a platform is "
                             "1 to 253 printable characters, no spaces")
        if not isinstance(amounts, dict):
            raise UsageError(f"'platforms.{name}' must be a capacity (an object)")
        out[name] = capacity_from_dict(amounts)
    return out


# ---------------------------------------------------------------------- orders


@dataclass(frozen=True)
class Prepare:
    """Prepare an attempt placed on the worker (its inputs fetched, its folder made).

    Attributes:
        cmd: the placement.
        manifests: input reference → the JSON of its manifest (what to fetch by digest).
        secrets: whether the attempt has secrets or data-URL credentials to ask for
            (``worker_secrets``); an order never carries one.
        max_output_bytes: the task's storage limit (None: none).
        spec: the workflow's spec, the first time the worker hears of the workflow.
        exec_timeout: the workflow's ``exec_timeout`` in seconds (None: none, or a server
            from before this field); osmo's own timeout is the server's, this is the
            upper bound a cluster job may ask its scheduler for (Slurm's ``--time``).
        priority: the workflow's priority, ``HIGH``, ``NORMAL`` or ``LOW`` (None: a server
            from before this field).
    """

    cmd: PrepareAttempt
    manifests: Mapping[str, str]
    secrets: bool = False
    max_output_bytes: int | None = None
    spec: StoredSpec | None = None
    exec_timeout: float | None = None
    priority: str | None = None

    @property
    def attempt_id(self) -> str:
        """The attempt it prepares."""
        return self.cmd.attempt_id


@dataclass(frozen=True)
class Run:
    """Start a prepared attempt (its group's barrier released)."""

    attempt_id: str


@dataclass(frozen=True)
class Kill:
    """Stop an attempt, saying why."""

    attempt_id: str
    reason: str


@dataclass(frozen=True)
class Ack:
    """An exit report was received and the attempt's outputs are safe on the server."""

    attempt_id: str


@dataclass(frozen=True)
class OpenSession:
    """Fetch the grant of an exec or port-forward session (``worker_session``) with ``ticket``.

    Orders can be read by any peer on the router, so a ticket, never the grant itself.
    """

    ticket: str


@dataclass(frozen=True)
class Sweep:
    """Delete what a node of this pool left in the cluster: it is down for good.

    ``instance`` is the label its objects carry (its hello's ``instance``); the server
    orders it only once that node's grace ended, and never for an instance a registered
    or away node holds.
    """

    instance: str


Order = Prepare | Run | Kill | Ack | OpenSession | Sweep
"""An order of the server to a worker (``to-worker/<id>``)."""

_OPS: dict[type[Any], str] = {Prepare: "prepare", Run: "run", Kill: "kill", Ack: "ack",
                              OpenSession: "session", Sweep: "sweep"}


def order_to_dict(order: Order) -> dict[str, Any]:
    """An order as JSON-safe data (``op`` names it)."""
    if isinstance(order, Prepare):
        out: dict[str, Any] = {"attempt_id": order.attempt_id, "cmd": asdict(order.cmd),
                               "manifests": dict(order.manifests), "secrets": order.secrets,
                               "max_output_bytes": order.max_output_bytes,
                               "exec_timeout": order.exec_timeout, "priority": order.priority}
        if order.spec is not None:
            out["spec"] = order.spec.to_dict()
    else:
        out = asdict(order)
    return {"op": _OPS[type(order)], **out}


def order_from_dict(data: object) -> Order:
    """The inverse of :func:`order_to_dict`, every field checked.

    Raises:
        ValueError: not an order this version knows, or a field missing or of the wrong type.
    """
    if not isinstance(data, dict):
        raise ValueError("an order is a JSON object")
    op = data.get("op")
    try:
        if op == "prepare":
            return _prepare_from_dict(data)
        if op == "session":
            return OpenSession(field(data, "ticket", str, max_len=_TEXT))
        if op == "sweep":
            return Sweep(field(data, "instance", str, max_len=63))
        aid = field(data, "attempt_id", str, max_len=_TEXT)
        if op == "run":
            return Run(aid)
        if op == "kill":
            return Kill(aid, field(data, "reason", str, default="", max_len=_TEXT))
        if op == "ack":
            return Ack(aid)
    except UsageError as exc:
        raise ValueError(f"order {shown(op)}: {exc}") from None
    raise ValueError(f"unknown order {shown(op)}")


def _prepare_from_dict(data: dict[str, Any]) -> Prepare:
    cmd = field(data, "cmd", dict)
    manifests = field(data, "manifests", dict)
    if not all(isinstance(v, str) for v in manifests.values()):
        raise UsageError("'manifests' maps inputs to manifests (JSON text)")
    spec = field(data, "spec", dict, default=None)
    try:
        placed = PrepareAttempt(
            attempt_id=str(cmd["attempt_id"]), workflow_id=str(cmd["workflow_id"]),
            task=str(cmd["task"]), retry=int(cmd["retry"]), node_id=str(cmd["node_id"]),
            inputs={str(k): str(v) for k, v in cmd["inputs"].items()},
            hosts={str(k): str(v) for k, v in cmd["hosts"].items()}, run=bool(cmd["run"]))
        stored = None if spec is None else StoredSpec.from_dict(spec)
    except (KeyError, TypeError, AttributeError, ValueError) as exc:
        raise UsageError(f"'cmd' or 'spec' is not a placement and its spec ({exc!r})") from None
    return Prepare(placed, manifests, secrets=field(data, "secrets", bool, default=False),
                   max_output_bytes=field(data, "max_output_bytes", int, default=None),
                   spec=stored, exec_timeout=_seconds(data.get("exec_timeout")),
                   priority=_priority(data.get("priority")))


def _seconds(value: object) -> float | None:
    """A positive finite number of seconds, or None (absent, or from an older server)."""
    if value is None:
        return None
    if isinstance(value, bool) or not isinstance(value, int | float) or not (
            0 < value < float("inf")):
        raise UsageError(f"'exec_timeout' must be a positive number of seconds, not "
                         f"{shown(value)}")
    return float(value)


def _priority(value: object) -> str | None:
    """``HIGH``, ``NORMAL`` or ``LOW``, or None (absent, or from an older server)."""
    if value is None:
        return None
    if value not in PRIORITIES:
        raise UsageError(f"'priority' must be one of {', '.join(PRIORITIES)}, not "
                         f"{shown(value)}")
    return str(value)
