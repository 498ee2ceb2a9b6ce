"""Remote workers on the server side: membership, orders, reports, logs and outputs.

:class:`WorkerHub` is the executor (``osmo.executor.Executor``) of every remote node: it
turns the engine's commands into orders to workers and worker traffic into events (see
``osmo.transport.wire`` for the keys and messages):

- A worker is a scheduler node once it has registered *and* its liveliness token is seen;
  the token going away is ``NodeDown`` (its attempts are rescheduled), and so is a worker
  whose beats stop for ``wire.LEASE`` seconds (a peer can hold a copy of a dead worker's
  token; it cannot beat for it). A draining worker is re-announced with no capacity, so
  nothing new is placed on it.
- Every order is sealed on the channel the worker last spoke on (``osmo.transport.seal``),
  and the server pulls a worker's outputs on it too: no other peer can read, forge or
  replay one.
- ``prepare`` sends the attempt with the input manifests it needs (the task's workflow spec
  only the first time a worker hears of that workflow). Secrets never travel in an order:
  the worker asks ``worker_secrets``.
- An exit report's outputs are fetched, verified and linked into the server's ``runs/``
  tree before the engine sees the exit, then the worker gets its ``ack``
  (``osmo.server.worker_outputs``); a transfer that fails makes the attempt lost.
- Reports, log batches and secret requests are authenticated API requests, accepted only
  for attempts placed on the worker the caller's token registered
  (``osmo.server.worker_access``). A worker registers only in a pool its token names, so
  it is placed (and given secrets) only for workflows of that pool.
- After a server restart, attempts restored on remote nodes are given ``grace`` seconds for
  their worker to register again (reporting what is still running and what finished
  meanwhile); a node that does not come back is taken down.
- A node whose attempts outlive its process (``Hello.outlives``: a Slurm login host's jobs, an
  in-cluster node's pods) is not taken down when its token goes or its beats stop: it is
  *away*, announced with no capacity, its attempts held, for ``adopt_grace`` seconds. Its id
  stays its token's meanwhile (no other token may register it). Back in time with the same
  id, it reports what it adopted (its registration's ``active``) and is told what the server
  still places on it (the reply's ``placed``); kills sent while it was away are sent again.
  Past the grace it is down: its attempts are lost and rescheduled, and it cancels its
  leftover jobs or pods when it comes back. A node that never comes back leaves its pods and
  their objects: another live node of its pool is ordered to delete them
  (``osmo.server.sweeps``, ``wire.Sweep``).
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable
from dataclasses import replace
from pathlib import Path
from typing import Any

from osmo.artifacts import ArtifactStore, Manifest
from osmo.errors import OsmoError, UsageError
from osmo.layout import Home
from osmo.options import DEFAULT_ADOPT_GRACE, DEFAULT_LOG_LIMIT
from osmo.scheduler.types import (
    LOCAL_NODE,
    AttemptExited,
    AttemptLost,
    AttemptStartFailed,
    Capacity,
    Event,
    KillAttempt,
    Node,
    NodeDown,
    NodeUp,
    PrepareAttempt,
    RunAttempt,
)
from osmo.server.auth import check_pool, refuse
from osmo.server.remote_logs import RemoteLogs
from osmo.server.sweeps import Sweeps
from osmo.server.worker_access import WorkerAccess, has_secrets, task_secrets
from osmo.server.worker_outputs import OutputIntake
from osmo.spec.model import ResourceSpec, TaskSpec
from osmo.spec.stored import StoredSpec
from osmo.store.sqlite import Store
from osmo.transport.auth import Identity
from osmo.transport.blobs import SERVER, BlobServer, SameHost, host_id
from osmo.transport.rpc import Gate, ServerAsker, ask_back, field, gate_opener
from osmo.transport.seal import Purpose, seal_json
from osmo.transport.wire import (
    LEASE,
    Ack,
    Hello,
    Kill,
    Order,
    Prepare,
    Run,
    Sweep,
    beat_offer,
    event_from_dict,
    order_to_dict,
    warm_runners,
)
from osmo.transport.zenoh_link import Link, Subscription

__all__ = ["WorkerHub"]

log = logging.getLogger("osmo.server.workers")
_MAX_RECORDS = 4 << 20  # characters of one log batch
_KEPT_TIMEOUTS = 256  # workflows whose exec_timeout is kept for their next orders

class WorkerHub:
    """Remote workers, as seen by the server (see the module docstring).

    Args:
        link: the server's session.
        emit: receives every event (thread-safe and cheap: it queues it for the engine).
        store: the state store (read only here: specs, manifests, credentials).
        artifacts: the server's artifact store.
        home: the server's home (attempt logs and outputs live under ``runs/``).
        url_credential: ``url -> credential`` for data URLs.
        attempts_on: the ids of the attempts the scheduler placed on a node (asked of the
            engine when a worker registers again).
        gate: the server's channels and token identities (``osmo.transport.rpc.Gate``).
        lease: seconds a registered worker may stay silent (no beat) before it is down.
        log_limit: bytes each remote attempt's log keeps at most as stored here.
        adopt_grace: seconds a node whose attempts outlive it may be away before they are
            lost (see the module docstring).
    """

    INLINE = frozenset({"worker_report", "worker_log"})
    """Verbs answered in arrival order on the zenoh thread (``ApiServer(inline=...)``)."""

    def __init__(self, *, link: Link, emit: Callable[[Event], None], store: Store,
                 artifacts: ArtifactStore, home: Home,
                 url_credential: Callable[[str], dict[str, str] | None],
                 attempts_on: Callable[[str], list[str]], gate: Gate,
                 lease: float = LEASE, log_limit: int = DEFAULT_LOG_LIMIT,
                 adopt_grace: float = DEFAULT_ADOPT_GRACE) -> None:
        self._link, self._emit, self._store = link, emit, store
        self._artifacts, self._home = artifacts, home
        self._url_credential, self._attempts_on = url_credential, attempts_on
        self._gate, self._lease, self._adopt_grace = gate, lease, adopt_grace
        self._lock = threading.Lock()
        self._nodes: dict[str, Node] = {}  # registered workers
        self._info: dict[str, dict[str, Any]] = {}
        self._alive: set[str] = set()
        self._heard: dict[str, tuple[bytes, float]] = {}  # worker id -> (channel, when)
        self._draining: set[str] = set()
        self._outlives: set[str] = set()  # nodes whose attempts outlive their process
        self._away: dict[str, tuple[int, Node]] = {}  # such a node, gone: (its absence's
        # number, what it registered as)
        self._absences = 0
        self._held_kills: dict[str, list[Kill]] = {}  # kills for a node while it is away
        self._sweeps = Sweeps(store)  # what nodes down for good left in their cluster
        self._same_host: dict[str, SameHost | None] = {}
        self._sent_specs: dict[str, set[str]] = {}
        self._timeouts: dict[str, float | None] = {}  # workflow -> exec_timeout (a few kept)
        self._logs = RemoteLogs(home, log_limit)
        self._access = WorkerAccess(self._holds)
        self._outputs = OutputIntake(artifacts=artifacts, home=home, emit=emit,
                                     send=self._send, asker=self._asker,
                                     same_host=self._same_host_of)
        self._host = host_id()
        self._subs: list[Subscription] = [
            link.watch(link.key("alive", "worker", "*"), self._on_token),
        ]
        self._blobs = BlobServer(link, SERVER, artifacts, gate_opener(gate),
                                 self._access.may_read)
        self._server_token = link.token(link.key("alive", SERVER))
        self._closed = threading.Event()
        self._watchdog = threading.Thread(target=self._watch_beats, name="osmo-worker-lease",
                                          daemon=True)
        self._watchdog.start()

    # ------------------------------------------------------------------ membership

    def register(self, request: dict[str, Any], who: Identity) -> dict[str, Any]:
        """A worker says hello (``osmo.transport.wire.Hello``).

        On its first start, or again after a server restart. The caller's token is bound to
        this worker id (see the module docstring). The reply names the server's artifact
        folder only to a worker on the same host (its hello carries this host's id, which only
        a process on this host, or an admin's ``ping``, can know), which links blobs from it
        and hides it from its tasks.

        Raises:
            UsageError: a field of the wrong type or out of range (nothing is changed).
            NotAllowed: the token may not serve the pool (``osmo.server.auth.check_pool``),
                or the id is another token's live worker.
        """
        hello = Hello.from_dict(request)
        node, wid = hello.node, hello.node.id
        check_pool(self._store, who, node.pool)
        self._access.bind(who, wid)
        self._hear(wid, who)
        with self._lock:
            self._nodes[wid] = node
            self._info[wid] = {"pid": hello.pid, "address": node.address,
                               "host_id": hello.host_id, "runtime": hello.runtime,
                               "sandbox_why": hello.sandbox_why}
            same = hello.host_id == self._host and hello.artifacts
            self._same_host[wid] = SameHost(Path(hello.artifacts or "")) if same else None
            self._sent_specs[wid] = set()
            if hello.draining:
                self._draining.add(wid)
            if hello.outlives:
                self._outlives.add(wid)
            else:
                self._outlives.discard(wid)
            back = self._away.pop(wid, None) is not None
            alive = wid in self._alive
            kills = self._held_kills.pop(wid, [])
        self._sweeps.registered(wid, node.pool, hello.instance)  # writes to the store
        self._sweeps.release(wid)  # what its previous run did not say it swept: again
        if back:
            log.info("worker %s is back: it adopts %d attempt(s)", wid, len(hello.active))
        placed = self._reconcile(wid, set(hello.active), list(hello.finished))
        if alive:
            self._emit(NodeUp(self._announced(wid)))
        for kill in kills:
            self._send(wid, kill)
        if alive:
            self._sweep(wid)
        log.info("worker %s registered (pool %s, %s)", wid, node.pool, node.capacity)
        reply: dict[str, Any] = {}
        if hello.outlives:
            reply["placed"] = sorted(placed)
        if hello.host_id == self._host:  # only a same-host worker learns where the store is
            reply.update(host_id=self._host, artifacts=str(self._artifacts.root))
        return reply

    def beat(self, request: dict[str, Any], who: Identity) -> dict[str, Any]:
        """A registered worker is alive (refused once this server forgot it: it registers again).

        Its beat also lists its warm runners (``wire.warm_runners``), kept for ``osmo resource
        list``, and a cluster node's may carry what its cluster offers now
        (``wire.beat_offer``): the node is announced again with that capacity and those
        platforms (the scheduler keeps what its attempts hold).

        Raises:
            NotAllowed: ``who`` did not register this worker, or the server no longer counts
                it (restarted, or it was silent past the lease).
        """
        wid = self._speaker("worker_beat", request, who)
        with self._lock:
            known = wid in self._nodes
        if not known:
            raise refuse("worker_beat", who, f"worker {wid} is not registered; register again")
        warm, offer = warm_runners(request), beat_offer(request)
        with self._lock:
            if wid in self._info:
                self._info[wid]["warm"] = warm
            node = self._nodes.get(wid)
            changed = None
            if offer is not None and node is not None and (node.capacity,
                                                           node.platforms) != offer:
                changed = self._nodes[wid] = replace(node, capacity=offer[0],
                                                     platforms=offer[1])
            alive = wid in self._alive
        if changed is not None:
            log.info("worker %s offers %s now (platforms: %s)", wid, changed.capacity,
                     ", ".join(changed.platforms) or "none")
            if alive:
                self._emit(NodeUp(self._announced(wid)))
        return {}

    def _speaker(self, verb: str, request: dict[str, Any], who: Identity) -> str:
        """The worker ``who`` speaks for (``WorkerAccess.speaker``), heard now on its channel."""
        wid = self._access.speaker(verb, request, who)
        self._hear(wid, who)
        return wid

    def _hear(self, wid: str, who: Identity) -> None:
        with self._lock:
            self._heard[wid] = (who.channel, time.monotonic())

    def _holds(self, wid: str) -> bool:
        """Its id is taken: it is alive, or away with its attempts held."""
        with self._lock:
            away = wid in self._away
        return away or self._is_alive(wid)

    def _is_alive(self, wid: str) -> bool:
        """Its liveliness token is seen and it was heard from within the lease."""
        with self._lock:
            heard = self._heard.get(wid)
            return (wid in self._alive and heard is not None
                    and time.monotonic() - heard[1] <= self._lease)

    def _watch_beats(self) -> None:
        """Take down registered workers silent for longer than the lease (token or not)."""
        while not self._closed.wait(min(1.0, self._lease / 4)):
            now = time.monotonic()
            with self._lock:
                silent = [wid for wid in self._nodes
                          if now - self._heard.get(wid, (b"", now))[1] > self._lease]
                gone = [(wid, self._nodes.pop(wid)) for wid in silent]
                for wid in silent:
                    self._draining.discard(wid)
            for wid, instance in self._sweeps.overdue(self._adopt_grace):
                if self._is_alive(wid):  # one that left had its orders moved on
                    log.info("worker %s has not said it swept node instance %s: again", wid,
                             instance)
                    self._send(wid, Sweep(instance))
            for wid, node in gone:
                self._resweep(wid)
                if self._went_away(wid, node):
                    continue
                log.warning("worker %s is silent (no beat for %.0fs): down", wid, self._lease)
                self._emit(NodeDown(wid))

    def _went_away(self, wid: str, node: Node) -> bool:
        """A node that went: away (True) if its attempts outlive it, else down (False).

        Away, it is announced with no capacity; if it is not back within the grace it is
        down then.
        """
        with self._lock:
            if wid not in self._outlives:
                return False
            self._absences += 1
            absence = self._absences
            self._away[wid] = (absence, node)
        log.warning("worker %s is gone; its attempts outlive it: held %.0fs for it to come "
                    "back", wid, self._adopt_grace)
        self._emit(NodeUp(replace(node, capacity=Capacity())))

        def check() -> None:
            with self._lock:
                late = self._away.get(wid, (None,))[0] == absence
                if late:
                    del self._away[wid]
                    self._held_kills.pop(wid, None)
            if late:
                log.warning("worker %s did not come back within %.0fs: down", wid,
                            self._adopt_grace)
                self._access.forget(wid)
                self._emit(NodeDown(wid))
                self._sweeps.down(wid)
                self._sweep_pool(node.pool)

        timer = threading.Timer(self._adopt_grace, check)
        timer.daemon = True
        timer.start()
        return True

    def _sweep(self, wid: str) -> None:
        """Order ``wid`` to delete what nodes of its pool, down for good, left.

        Only an alive node that makes cluster objects (``osmo.server.sweeps``).
        """
        with self._lock:
            node = self._nodes.get(wid)
        if node is None or not self._sweeps.sweeper(wid) or not self._is_alive(wid):
            return
        for instance in self._sweeps.due(node.pool, wid):
            log.info("worker %s deletes what node instance %s left (down for good)", wid,
                     instance)
            self._send(wid, Sweep(instance))

    def _resweep(self, wid: str) -> None:
        """``wid`` left: what it did not say it swept goes to another live node of its pool."""
        for pool in self._sweeps.release(wid):
            self._sweep_pool(pool)

    def swept(self, request: dict[str, Any], who: Identity) -> dict[str, Any]:
        """A worker says it deleted what a node instance left (``wire.Sweep``).

        Raises:
            UsageError: no instance named.
            NotAllowed: the caller speaks for another worker, or that instance was not
                ordered to it (it stays to be swept).
        """
        wid = self._speaker("worker_swept", request, who)
        instance = request.get("instance")
        if not isinstance(instance, str) or not instance:
            raise UsageError("worker_swept: 'instance' must be a non-empty string")
        if not self._sweeps.swept(wid, instance):
            raise refuse("worker_swept", who, f"instance {instance[:80]!r} was not ordered "
                                              f"swept by worker {wid}")
        log.info("worker %s swept what node instance %s left", wid, instance)
        return {}

    def _sweep_pool(self, pool: str) -> None:
        """One live node of ``pool`` that can sweep does (none: the next one registered)."""
        with self._lock:
            nodes = sorted(wid for wid, node in self._nodes.items() if node.pool == pool)
        for wid in nodes:
            if self._sweeps.sweeper(wid) and self._is_alive(wid):
                self._sweep(wid)
                return

    def _asker(self, wid: str) -> ServerAsker | None:
        """Asks worker ``wid``'s blob server on the channel it last spoke on."""
        with self._lock:
            heard = self._heard.get(wid)
        return ask_back(self._link, self._gate, heard[0]) if heard is not None else None

    def report(self, request: dict[str, Any], who: Identity) -> dict[str, Any]:
        """One report of a worker (``osmo.transport.wire.event_to_dict``) about its attempt."""
        wid = self._speaker("worker_report", request, who)
        report = field(request, "report", dict)
        self._access.placed_on("worker_report", wid, str(report.get("attempt_id")), who)
        self._handle(wid, report)
        return {}

    def log(self, request: dict[str, Any], who: Identity) -> dict[str, Any]:
        """A batch of an attempt's log records, appended to the server's copy of its log."""
        wid = self._speaker("worker_log", request, who)
        aid = field(request, "attempt_id", str, max_len=4096)
        self._access.placed_on("worker_log", wid, aid, who)
        self._logs.append(aid, field(request, "records", str, max_len=_MAX_RECORDS).encode())
        return {}

    def secrets(self, request: dict[str, Any], who: Identity) -> dict[str, Any]:
        """The secrets and data-URL credentials of an attempt placed on the asking worker.

        Raises:
            NotAllowed: the attempt is not placed on it.
        """
        wid = self._speaker("worker_secrets", request, who)
        aid = field(request, "attempt_id", str, max_len=4096)
        task = self._access.placed_on("worker_secrets", wid, aid, who)
        if task is None:
            raise refuse("worker_secrets", who, f"attempt {aid!r} was prepared before the "
                                                "server restarted; its secrets were sent then")
        return task_secrets(task, self._store.credential, self._url_credential,
                            containers=self._contained(wid))

    def drain(self, request: dict[str, Any], who: Identity) -> dict[str, Any]:
        """A worker stops taking work: announce it with no capacity."""
        wid = self._speaker("worker_drain", request, who)
        with self._lock:
            known = wid in self._nodes
            self._draining.add(wid)
        if known:
            self._emit(NodeUp(self._announced(wid)))
        return {"draining": wid}

    def _announced(self, wid: str) -> Node:
        with self._lock:
            node = self._nodes[wid]
            return replace(node, capacity=Capacity()) if wid in self._draining else node

    def _reconcile(self, wid: str, active: set[str], finished: list[dict[str, Any]]
                   ) -> set[str]:
        """After a (re-)registration, replay finished reports and lose forgotten attempts.

        Attempts the scheduler placed there that the worker knows nothing of are lost.

        Returns:
            the attempts the scheduler still places on ``wid``.
        """
        known = set(self._attempts_on(wid))
        done = {str(r.get("attempt_id")) for r in finished}
        self._access.restored(wid, known)
        for report in finished:
            if str(report.get("attempt_id")) in known:
                self._handle(wid, report)
            else:  # superseded (fenced) or never its own; acked so it stops resending it
                log.warning("refused a finished report of worker %s: attempt %r is not "
                            "placed on it", wid, report.get("attempt_id"))
                self._send(wid, Ack(str(report.get("attempt_id"))))
        for aid in sorted(known - active - done):
            self._emit(AttemptLost(aid, f"worker {wid} no longer runs this attempt"))
        return known

    def expect(self, node_ids: set[str], grace: float) -> None:
        """Restored attempts sit on ``node_ids``: take down those not back within ``grace``.

        So are the cluster nodes of the server's previous life (``Sweeps.restored``): what
        they left is swept then.
        """
        labelled = self._sweeps.restored()

        def check() -> None:
            with self._lock:
                here = set(self._nodes) | set(self._away)
                pools = {wid: node.pool for wid, node in self._nodes.items()}
            for wid in sorted(node_ids - here):
                log.warning("worker %s did not come back within %.0fs", wid, grace)
                self._emit(NodeDown(wid))
            for wid in sorted(labelled - here):
                self._sweeps.down(wid)
            for pool in sorted(set(pools.values())):
                self._sweep_pool(pool)

        if node_ids or labelled:
            timer = threading.Timer(grace, check)
            timer.daemon = True
            timer.start()

    def _on_token(self, key: str, alive: bool) -> None:
        wid = key.rsplit("/", 1)[1]
        node: Node | None = None
        with self._lock:
            if alive:
                self._alive.add(wid)
                registered = wid in self._nodes
            else:
                self._alive.discard(wid)
                node = self._nodes.pop(wid, None)
                registered = node is not None
                self._draining.discard(wid)
        if alive:
            if registered:
                self._emit(NodeUp(self._announced(wid)))
                self._sweep(wid)
            return
        if node is None:
            return
        self._resweep(wid)
        if not self._went_away(wid, node):
            log.warning("worker %s is gone", wid)
            self._access.forget(wid)
            self._emit(NodeDown(wid))

    def workers(self) -> list[dict[str, Any]]:
        """Registered workers with their status (for ``osmo resource list``).

        A node whose attempts outlive it is listed while it is away (``away``: its attempts
        are held for it until its grace ends).
        """
        with self._lock:
            nodes = {**{wid: n for wid, (_, n) in self._away.items()}, **self._nodes}
            return [{"id": wid, "pool": n.pool, "platform": n.platform,
                     "status": ("away" if wid in self._away else
                                "draining" if wid in self._draining else
                                "online" if wid in self._alive else "connecting"),
                     **self._info.get(wid, {})} for wid, n in sorted(nodes.items())]

    # ------------------------------------------------------------------ orders

    def owns(self, node_id: str) -> bool:
        """Every node but the server's own pool is a remote worker's.

        Registered or not: an order to a worker that is gone is lost with it, and its attempts with
        it.
        """
        return node_id != LOCAL_NODE

    def prepare(self, cmd: PrepareAttempt, task: TaskSpec, *,
                max_output_bytes: int | None = None,
                resources: ResourceSpec | None = None) -> None:
        """Send a placement to its worker (engine thread).

        ``resources`` is not sent: the worker reads the request from the spec it holds.
        """
        try:
            order = self._order(cmd, task, max_output_bytes)
        except (OsmoError, OSError) as exc:
            self._emit(AttemptStartFailed(cmd.attempt_id, str(exc)))
            return
        digests = {e.digest for body in order.manifests.values()
                   for e in Manifest.from_json(body).entries}
        self._access.place(cmd.attempt_id, cmd.node_id, task, digests)
        self._send(cmd.node_id, order)

    def _order(self, cmd: PrepareAttempt, task: TaskSpec,
               max_output_bytes: int | None) -> Prepare:
        with self._lock:
            sent = self._sent_specs.setdefault(cmd.node_id, set())
            first = cmd.workflow_id not in sent
            sent.add(cmd.workflow_id)
        row = self._store.workflow(cmd.workflow_id, with_spec=first)
        if row is None:
            raise OsmoError(f"workflow {cmd.workflow_id} is not in the store")
        spec = row.spec if first else None
        return Prepare(cmd, {ref: self._manifest_of(ref) for ref in set(cmd.inputs.values())
                             if not _is_url(ref)},
                       # the values are asked for by the worker (``worker_secrets``)
                       secrets=has_secrets(task, self._store.credential, self._url_credential,
                                           containers=self._contained(cmd.node_id)),
                       max_output_bytes=max_output_bytes, spec=spec,
                       exec_timeout=self._exec_timeout(cmd.workflow_id, row.spec if first
                                                       else None),
                       priority=row.options.priority)

    def _exec_timeout(self, workflow_id: str, spec: StoredSpec | None) -> float | None:
        """The workflow's ``exec_timeout`` (its spec read once per workflow, then kept)."""
        with self._lock:
            if workflow_id in self._timeouts:
                return self._timeouts[workflow_id]
        if spec is None:
            row = self._store.workflow(workflow_id)
            if row is None:
                return None
            spec = row.spec
        try:
            found = spec.load().timeout.exec_timeout
        except OsmoError:
            found = None
        with self._lock:
            self._timeouts[workflow_id] = found
            while len(self._timeouts) > _KEPT_TIMEOUTS:
                del self._timeouts[next(iter(self._timeouts))]
        return found

    def _contained(self, wid: str) -> str | None:
        """How worker ``wid`` runs image tasks: ``container``, ``kubernetes``, or None.

        The first two pull images, so get registry credentials (its own engine also
        runs typed tasks in their images).
        """
        with self._lock:
            runtime = str(self._info.get(wid, {}).get("runtime") or "")
        return next((kind for kind in ("container", "kubernetes") if runtime.startswith(kind)),
                    None)

    def _manifest_of(self, ref: str) -> str:
        found = self._store.output_of(ref)
        body = self._store.manifest_body(found[0]) if found else None
        if body is None:  # server-side data with no recorded manifest (a dataset copy)
            body = self._artifacts.ingest(Path(ref)).to_json()
        return body

    def run(self, cmd: RunAttempt) -> None:
        """Start a prepared attempt (its group's barrier released)."""
        self._access.restored(cmd.node_id, [cmd.attempt_id])
        self._send(cmd.node_id, Run(cmd.attempt_id))

    def kill(self, cmd: KillAttempt) -> None:
        """Stop an attempt on its worker."""
        self._access.restored(cmd.node_id, [cmd.attempt_id])
        kill = Kill(cmd.attempt_id, cmd.reason)
        with self._lock:
            away = cmd.node_id in self._away
            if away:
                self._held_kills.setdefault(cmd.node_id, []).append(kill)
        if not away:
            self._send(cmd.node_id, kill)

    def tell(self, wid: str, order: Order) -> None:
        """Send worker ``wid`` an order (sealed on its channel)."""
        self._send(wid, order)

    def speaker(self, verb: str, request: dict[str, Any], who: Identity) -> str:
        """The worker id a request of ``who`` speaks for (``WorkerAccess.speaker``)."""
        return self._speaker(verb, request, who)

    def check_placed(self, verb: str, wid: str, aid: str, who: Identity) -> None:
        """Refuse (NotAllowed) unless attempt ``aid`` is placed on worker ``wid``."""
        self._access.placed_on(verb, wid, aid, who)

    def _same_host_of(self, wid: str) -> SameHost | None:
        with self._lock:
            return self._same_host.get(wid)

    def _send(self, wid: str, order: Order) -> None:
        with self._lock:
            heard = self._heard.get(wid)
        found = self._gate.channels.get(heard[0]) if heard is not None else None
        if found is None:  # it never spoke on a channel this server knows: it registers again
            log.warning("no channel to worker %s: order %s not sent", wid,
                        type(order).__name__)
            return
        rel = f"to-worker/{wid}"
        attachment, payload = seal_json(found[0], Purpose.PUSH, rel, order_to_dict(order))
        self._link.put(self._link.key(rel), payload, attachment)

    # ------------------------------------------------------------------ reports

    def _handle(self, wid: str, report: dict[str, Any]) -> None:
        try:
            event = event_from_dict(report)
        except (ValueError, KeyError, TypeError):
            log.warning("unknown report from worker %s: %r", wid, report)
            return
        if isinstance(event, AttemptExited):
            self._logs.end(event.attempt_id)
            self._outputs.exited(wid, event)
            return
        if isinstance(event, (AttemptStartFailed, AttemptLost)):
            self._logs.end(event.attempt_id)
        self._emit(event)

    def close(self) -> None:
        """Stop listening (workers keep running; they register again with the next server)."""
        self._closed.set()
        for sub in self._subs:
            sub.close()
        self._server_token.close()
        self._blobs.close()
        self._outputs.close()
        self._logs.close()


def _is_url(ref: str) -> bool:
    return "://" in ref
