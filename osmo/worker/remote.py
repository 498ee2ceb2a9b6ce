"""A remote worker: ``osmo worker --connect ENDPOINT --pool NAME``.

It dials out to the server (so it may sit behind a firewall), registers its capacity, keeps
a liveliness token alive, and runs the server's orders with the same :class:`LocalPool` the
server uses on its own host — one runtime implementation. The wire protocol is described in
``osmo.transport.wire``.

Data: an attempt's inputs are fetched by digest from the server's artifact store (only the
blobs this worker lacks; hard links when both share a host and filesystem;
``osmo.worker.held_inputs``), and the pool
hands the attempt its own checked copy of them, as on the server (``transfer.copy_inputs``);
its outputs are ingested into this worker's own store and
pulled by the server, which acknowledges each exit report once every byte is safe with it.
Unacknowledged reports are kept and sent again whenever the worker registers again (after a
server restart), so a result that finished while the server was away is not lost.

Trust: every request is sealed on a channel of the worker's token (role worker,
``osmo.transport.seal``); its reports and log batches are requests the server checks against
the attempts placed on this worker. It obeys only orders the server sealed on one of its
channels (a put on its key by any other peer is dropped), and its blob server answers only
the server's requests sealed on them. It beats every ``wire.BEAT_EVERY`` seconds; a beat the
server refuses (it restarted, or counted the worker gone) makes it register again. An
attempt's secrets and data-URL credentials are asked for (``worker_secrets``) rather than
carried by the ``prepare`` order.

Adoption: on a node whose attempts outlive it (``--runtime slurm``: batch jobs;
``--runtime kubernetes``: pods), each attempt is journaled in its home
(``osmo.worker.journal``). A node started again on that home reads the journal before
anything else, keeps those attempts' folders, re-attaches to their jobs or pods
(``LocalPool.adopt``: their logs resume where they were shipped, their outputs are
collected as usual; log lines wait until it registered), cancels every other job or pod its
previous life left, and registers with the adopted attempts as ``active`` and ``outlives``
set (the server held them while it was away: ``osmo.server.workers``). An adopted attempt
the server no longer places on it (the registration's ``placed``: it stayed away past the
grace) is killed and reports nothing. Stopped (not killed), it cancels its attempts and
hands them back at once.

Leftovers: the pool records each running command's pid and start time under ``<home>/procs``;
a worker started on a home kills whatever a previous life left there before it announces
itself (``osmo.worker.procs``), so a SIGKILLed worker's task never runs beside its
rescheduled copy (tasks also die with their worker: ``osmo.runtime.process.groups``).

Drain (SIGTERM): the worker stops taking work (it re-registers with no capacity), lets
running attempts finish for up to ``drain_timeout`` seconds and waits until their outputs
were taken; attempts still running then are killed and handed back (reported lost, so they
are rescheduled without using a retry). Then it exits.
"""

from __future__ import annotations

import json
import logging
import os
import socket
import threading
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

from osmo.artifacts import ArtifactStore, Manifest
from osmo.config import write_json_atomic
from osmo.errors import NotAllowed, OsmoError, UsageError
from osmo.layout import Home
from osmo.names import check_worker_name
from osmo.runtime.api import Adopting, Terms
from osmo.runtime.choose import image_runtime_for_node, slurm_for_node
from osmo.runtime.kubernetes.capacity import cluster_capacity
from osmo.runtime.kubernetes.runtime import KubernetesRuntime
from osmo.runtime.slurm import SlurmRuntime
from osmo.scheduler.types import (
    LOCAL_NODE,
    AttemptExited,
    AttemptLost,
    AttemptStartFailed,
    Capacity,
    Event,
    KillAttempt,
    PrepareAttempt,
    RunAttempt,
)
from osmo.spec.model import ResourceSpec, TaskSpec, WorkflowSpec
from osmo.spec.stored import StoredSpec
from osmo.transport.blobs import SERVER, BlobServer, SameHost, host_id
from osmo.transport.rpc import ApiClient
from osmo.transport.seal import Purpose
from osmo.transport.wire import (
    BEAT_EVERY,
    Ack,
    Hello,
    Kill,
    OpenSession,
    Order,
    Prepare,
    Run,
    Sweep,
    event_to_dict,
    offer_to_dict,
    order_from_dict,
)
from osmo.transport.zenoh_link import Link, Subscription
from osmo.worker.held_inputs import HeldInputs
from osmo.worker.journal import Journal
from osmo.worker.options import WorkerOptions
from osmo.worker.pool import LocalPool
from osmo.worker.procs import kill_recorded
from osmo.worker.sessions import NodeSessions
from osmo.worker.store_keeper import StoreKeeper, clear_runs, default_limit

__all__ = ["RemoteWorker"]

log = logging.getLogger("osmo.worker")


@dataclass
class _Pending:
    """An attempt whose inputs are being fetched (orders that came meanwhile)."""

    run: bool = False
    kill: str | None = None


class RemoteWorker:
    """One worker process (see the module docstring). ``run()`` blocks until stopped."""

    def __init__(self, home: Home, options: WorkerOptions) -> None:
        self.home = home  # absolute: osmo.config.open_home(worker=True)
        home.root.mkdir(parents=True, exist_ok=True)
        self.opts = options
        self._address = options.address or _address()  # how peers reach its tasks
        self.id = check_worker_name(options.name or f"{socket.gethostname()}-{os.getpid()}",
                                    reserved=(LOCAL_NODE, SERVER))
        if not options.token:
            raise UsageError("a worker needs a token with role worker: --token, --token-file "
                             "or OSMO_TOKEN (an admin makes one with `osmo token create NAME "
                             "--role worker --pool POOL`)")
        self.store = ArtifactStore(home.artifacts)
        self.link = Link.client(list(options.connect), options.cluster,
                                config_file=options.zenoh_config)
        self._api = ApiClient(self.link, timeout=10.0, token=options.token)
        self._lock = threading.Lock()
        self._changed = threading.Condition(self._lock)
        self._specs: dict[str, WorkflowSpec] = {}
        self._stored: dict[str, StoredSpec] = {}  # as sent (journaled with its attempts)
        self._adopted: set[str] = set()  # until the server says which it still places here
        self._early_logs: list[tuple[str, bytes]] | None = []  # sent once it registered
        self._url_creds: dict[str, dict[str, str]] = {}
        self._pending: dict[str, _Pending] = {}
        self._inputs = HeldInputs(self._api, self.store)
        self._active: set[str] = set()
        self._inputs_of: dict[str, list[Manifest]] = {}  # of attempts not ended yet
        self._unacked: dict[str, dict[str, Any]] = {}
        self._unacked_outputs: dict[str, Manifest] = {}  # only here until acknowledged
        self._handed_back: set[str] = set()
        self._server_host: SameHost | None = None
        self._draining = False
        self._connected = False
        self._server_lost = False
        self._register_now = threading.Event()
        self._offered: dict[str, Any] | None = None  # what the server last heard it offers
        self._offer_read = time.monotonic()  # when the cluster's capacity was last read
        self._offer_failing = False  # the last read failed (said once)
        self._stop = threading.Event()
        self._refused: NotAllowed | None = None  # the server refused to register it
        self._io = ThreadPoolExecutor(4, thread_name_prefix="osmo-inputs")
        self._token: Subscription | None = None
        # what a previous life left on a cluster is adopted or cancelled (below)
        cluster = slurm_for_node(options.runtime, home, options.slurm,
                                 python=options.slurm_python, engine=options.container_engine)
        images = image_runtime_for_node(options.runtime, options.container_engine, home,
                                        kubernetes_config=options.kubernetes_config)
        # the pool's rule (``Runtimes.adopting``), before the pool exists: the journal comes first
        outlives = any(isinstance(r, Adopting) for r in (images, *(cluster or ())))
        self._journal = journal = Journal(home.root / "journal", self._stored.get)
        entries = journal.read(home) if outlives else []
        if not outlives:
            journal.clear()
        kill_recorded(home.procs)  # before it announces itself
        # a previous life's attempts were all rescheduled, but those it adopts now
        clear_runs(home, self._io, keep={entry.dirs.root for entry in entries})
        limit = default_limit(home.root) if options.store_limit is None else options.store_limit
        self._keeper = StoreKeeper(home, self.store, self._inputs, limit,
                                   self._protected, self._io)
        cpus, gpus, memory = _capacity(options, images, cluster[0] if cluster else None)
        self._clusters = (images, cluster[0] if cluster else None)  # their platforms
        self.pool = LocalPool(
            home=home, emit=self._emit, node_id=self.id, pool=options.pool,
            cpus=cpus, gpus=gpus, memory=memory,
            kill_grace=options.kill_grace, artifacts=self.store,
            credential_for=self._url_creds.get, log_sink=self._send_log,
            log_limit=options.log_limit,
            input_manifests=self._inputs.manifest_of, sandbox=options.sandbox,
            sandbox_share=options.sandbox_share, address=self._address,
            procs_dir=home.procs, containers=images,
            cluster=cluster[0] if cluster else None, cluster_images=cluster[1] if cluster else None,
            warm=options.warm, journal=journal if outlives else None)
        if isinstance(images, KubernetesRuntime):  # its pods' own data, with the pool's `data`
            images.serve_pod_data(self.link, self.id, list(options.connect), options.cluster,
                                  config_file=options.zenoh_config)
        for entry in entries:
            log.info("adopting attempt %s from this node's previous life", entry.attempt_id)
            with self._lock:
                self._active.add(entry.attempt_id)
                self._adopted.add(entry.attempt_id)
            self.pool.adopt(entry)
        for left in self.pool.cancel_orphans():
            log.warning("cancelled %s that this node's previous life left", left)
        for secret in options.secret_files:
            self.pool.hide(Path(secret))
        self.sessions = NodeSessions(self.link, self.pool, lambda ticket: self._api.call(
            "worker_session", {"id": self.id, "ticket": ticket}))
        self._subs: list[Any] = []

    # ------------------------------------------------------------------ life cycle

    def run(self) -> None:
        """Register, serve orders, register again whenever the server comes back.

        Registering is retried until the server answers. Returns after :meth:`stop` or a finished
        :meth:`drain`.

        Raises:
            NotAllowed: the server refused to register it (its token may not serve its pool,
                or its id is another token's live worker).
        """
        orders = f"to-worker/{self.id}"
        self._subs = [
            self.link.subscribe_raw(self.link.key(orders), lambda _key, data, att: (
                self._on_sealed_order(orders, data, att))),
            BlobServer(self.link, self.id, self.store, self._api.open_asked),
            self.link.watch(self.link.key("alive", SERVER), self._on_server),
        ]
        delay = 0.2
        self._register_now.set()
        while not self._stop.is_set():
            if self._register_now.wait(timeout=BEAT_EVERY):
                self._register_now.clear()
                if not self._register():
                    self._stop.wait(delay)
                    delay = min(delay * 2, 5.0)
                    self._register_now.set()
                    continue
                delay = 0.2
            else:
                self._beat()
            self._write_health()
        self._close()
        if self._refused is not None:
            raise self._refused

    def _beat(self) -> None:
        """Tell the server this worker is alive; register again if it no longer counts it.

        A cluster node's beat carries what its cluster offers when that changed
        (:meth:`_new_offer`).
        """
        beat: dict[str, Any] = {"id": self.id, "warm": self.pool.warm_runners()}
        offer = self._new_offer()
        if offer is not None:
            beat["offer"] = offer
        try:
            self._api.call("worker_beat", beat, timeout=BEAT_EVERY * 2)
            if offer is not None:
                log.info("offered the server its cluster's capacity now: %s", offer)
                with self._lock:
                    self._offered = offer
        except NotAllowed:
            log.info("the server no longer counts worker %s: registering again", self.id)
            self._register_now.set()
        except OsmoError as exc:
            with self._lock:
                self._connected = False
            log.info("beat not answered (%s)", exc)

    def stop(self) -> None:
        """Leave now: running attempts are killed (the server reschedules them)."""
        self._stop.set()

    def drain(self) -> None:
        """Stop taking work, let running attempts finish, hand back the rest, then stop.

        Running attempts get up to ``drain_timeout``; it waits until their outputs were taken.
        """
        with self._lock:
            self._draining = True
        self._write_health()
        try:
            self._api.call("worker_drain", {"id": self.id})
        except OsmoError as exc:
            log.warning("could not tell the server about the drain: %s", exc)
        deadline = time.monotonic() + self.opts.drain_timeout
        with self._changed:
            self._changed.wait_for(lambda: not (self._pending or self._active),
                                   timeout=max(0.0, deadline - time.monotonic()))
            left = sorted(self._active | set(self._pending))
            self._handed_back.update(left)
        for aid in left:
            log.info("handing back %s (still running at the end of the drain)", aid)
            self._send(event_to_dict(AttemptLost(
                aid, f"worker {self.id} drained; attempt handed back")))
            self.pool.kill(KillAttempt(aid, self.id, "worker draining"))
        with self._changed:
            self._changed.wait_for(lambda: not self._unacked, timeout=30.0)
        self._stop.set()

    def _close(self) -> None:
        outlives = self.pool.outlives()
        if outlives:  # the server would hold them for the node's return: handed back now
            with self._lock:
                left = sorted(self._active - self._handed_back)
                self._handed_back.update(left)
            for aid in left:
                self._send(event_to_dict(AttemptLost(aid, f"worker {self.id} stopped")))
        for sub in self._subs:
            sub.close()
        if self._token is not None:
            self._token.close()
        self.sessions.close("the worker is stopping")
        self.pool.close()  # its jobs are cancelled: nothing is left to adopt
        if outlives:
            self._journal.clear()
        self._io.shutdown(wait=False, cancel_futures=True)
        self.link.close()
        self.home.worker_health.unlink(missing_ok=True)

    # ------------------------------------------------------------------ registration

    def _on_server(self, _key: str, alive: bool) -> None:
        """The server's token: gone means it stopped, back means register again.

        Gone: it stopped or is cut off. Back: a new server process knows nothing of this worker yet.
        """
        with self._lock:
            self._connected = self._connected and alive
            came_back = alive and self._server_lost
            self._server_lost = self._server_lost or not alive
            if came_back:
                self._server_lost = False
        if came_back:
            self._register_now.set()

    def _new_offer(self) -> dict[str, Any] | None:
        """What its cluster offers now (``wire.offer_to_dict``), if the server has not heard it.

        A cluster node only reads it, every ``capacity_every`` seconds.
        """
        images, cluster = self._clusters
        every = self.opts.capacity_every
        if every <= 0 or (cluster is None and not isinstance(images, KubernetesRuntime)):
            return None
        now = time.monotonic()
        if now - self._offer_read < every:
            return None
        self._offer_read = now
        try:
            self.pool.offer(*_capacity(self.opts, images, cluster))
        except OsmoError as exc:  # said once while it keeps failing
            (log.debug if self._offer_failing else log.warning)(
                "cannot read the cluster's capacity (offering what it did): %s", exc)
            self._offer_failing = True
            return None
        self._offer_failing = False
        own = self.pool.node()
        offer = offer_to_dict(own.capacity, _platforms(images, cluster, own.capacity.storage))
        with self._lock:
            return None if offer == self._offered else offer

    def _register(self) -> bool:
        own = self.pool.node()  # its labels (the sandbox) win over the user's
        node = replace(own, platform=self.opts.platform, address=self._address,
                       labels={**self.opts.labels, **own.labels},
                       platforms=_platforms(*self._clusters, own.capacity.storage))
        offered = offer_to_dict(node.capacity, node.platforms)
        with self._lock:
            hello = Hello(node, pid=os.getpid(), host_id=host_id(),
                          artifacts=str(self.store.root), draining=self._draining,
                          active=tuple(sorted(self._active | set(self._pending))),
                          finished=tuple(self._unacked.values()),
                          runtime=self.pool.runtime_name(),
                          sandbox_why=self.pool.no_sandbox_why,
                          outlives=self.pool.outlives(),
                          instance=self._instance()).to_dict()
        try:
            reply = self._api.call("worker_register", hello)
        except NotAllowed as exc:  # e.g. a pool its token may not serve: retrying cannot help
            self._refused = exc
            self._stop.set()
            return False
        except OsmoError as exc:
            log.info("server not reachable yet (%s); retrying", exc)
            return False
        self._settle_adopted(reply.get("placed"))
        with self._lock:
            early, self._early_logs = self._early_logs or [], None
        for attempt_id, records in early:
            self._send_log(attempt_id, records)
        same = reply.get("host_id") == hello["host_id"] and reply.get("artifacts")
        self._server_host = SameHost(Path(reply["artifacts"])) if same else None
        if same:  # its tasks must not see the server's home (its state store) either
            self.pool.hide(Path(reply["artifacts"]).parent)
        if self._token is None:
            self._token = self.link.token(self.link.key("alive", "worker", self.id))
        with self._lock:
            self._connected = True
            self._offered = offered
        log.info("worker %s registered with the server (pool %s)", self.id, self.opts.pool)
        return True

    def _settle_adopted(self, placed: object) -> None:
        """Kill the adopted attempts the server no longer places here (they report nothing)."""
        if not isinstance(placed, list):
            return
        with self._lock:
            stray = sorted(self._adopted - {str(aid) for aid in placed})
            self._adopted.clear()
            self._handed_back.update(stray)
        for aid in stray:
            log.warning("attempt %s is no longer placed on this node: its job is cancelled",
                        aid)
            self.pool.kill(KillAttempt(aid, self.id, "no longer placed on this node"))

    def _write_health(self) -> None:
        with self._lock:
            state = {"id": self.id, "pid": os.getpid(), "connected": self._connected,
                     "draining": self._draining, "running": len(self._active),
                     "updated_at": time.time()}
        write_json_atomic(self.home.worker_health, state)

    # ------------------------------------------------------------------ orders

    def _on_sealed_order(self, rel: str, data: bytes, attachment: bytes | None) -> None:
        """An order put on this worker's key: obeyed only if the server sealed it for us."""
        opened = self._api.opened(Purpose.PUSH, rel, attachment, data)
        if opened is None:
            log.warning("dropped a message on %s that the server did not seal", rel)
            return
        try:
            order = order_from_dict(json.loads(opened[2]))
        except ValueError as exc:  # a newer server's order, say: never a traceback here
            log.warning("dropped an order the server sealed: %s", exc)
            return
        self._on_order(order)

    def _on_order(self, order: Order) -> None:
        match order:
            case Prepare():
                self._prepare(order)
            case Run(attempt_id=aid) | Kill(attempt_id=aid):
                with self._lock:
                    pending = self._pending.get(aid)
                    if pending is not None:
                        if isinstance(order, Run):
                            pending.run = True
                        else:
                            pending.kill = pending.kill or order.reason
                        return
                if isinstance(order, Run):
                    self.pool.run(RunAttempt(aid, self.id))
                else:
                    self.pool.kill(KillAttempt(aid, self.id, order.reason))
            case OpenSession(ticket=ticket):  # exec / port-forward: a ticket for its grant
                self.sessions.order(ticket)
            case Sweep(instance=instance):  # a node of this pool is down for good
                self._io.submit(self._sweep, instance)
            case Ack(attempt_id=aid):
                with self._changed:
                    acked = self._unacked.pop(aid, None) is not None
                    self._unacked_outputs.pop(aid, None)
                    self._changed.notify_all()
                if acked:
                    self._keeper.acknowledged(aid)

    def _instance(self) -> str | None:
        """The label this node's cluster objects carry (None: it makes none)."""
        runtime = self._clusters[0]
        return runtime.instance if isinstance(runtime, KubernetesRuntime) else None

    def _sweep(self, instance: str) -> None:
        """Delete what node instance ``instance`` left (``wire.Sweep``); never raises.

        Once done, it says so (``worker_swept``): until then the server holds the order for
        it, and gives it to another node of the pool if this one leaves first.
        """
        runtime = self._clusters[0]
        if not isinstance(runtime, KubernetesRuntime):
            log.warning("ignored an order to sweep instance %r: this node makes no cluster "
                        "objects", instance[:80])
            return
        try:
            swept = runtime.sweep(instance)
        except OsmoError as exc:
            log.warning("could not sweep instance %r: %s", instance[:80], exc)
            return
        for name in swept:
            log.warning("deleted %s that node instance %s left (it is down for good)", name,
                        instance)
        try:
            self._api.call("worker_swept", {"id": self.id, "instance": instance})
        except OsmoError as exc:  # it is ordered again when this node registers again
            log.warning("could not tell the server instance %r is swept: %s", instance[:80],
                        exc)

    def _prepare(self, order: Prepare) -> None:
        cmd = order.cmd
        with self._lock:
            if order.spec is not None:
                self._specs[cmd.workflow_id] = order.spec.load()
                self._stored[cmd.workflow_id] = order.spec
            self._pending[cmd.attempt_id] = _Pending()
        manifests = {ref: Manifest.from_json(body) for ref, body in order.manifests.items()}
        with self._keeper.gate:  # protected before it is checked: no collection between
            with self._lock:
                self._inputs_of[cmd.attempt_id] = list(manifests.values())
            fetched = all(self._inputs.holds(m) for m in manifests.values())
        if fetched and not order.secrets:
            self._fetch_and_prepare(cmd, order, manifests)  # nothing to fetch: no thread hop
        else:
            self._io.submit(self._fetch_and_prepare, cmd, order, manifests)

    def _fetch_and_prepare(self, cmd: PrepareAttempt, order: Prepare,
                           manifests: dict[str, Manifest]) -> None:
        values: dict[str, Any] = {}
        try:
            task = self._task(cmd)
            if order.secrets:  # asked for: an order is no place for a secret
                got = self._api.call("worker_secrets", {"id": self.id,
                                                        "attempt_id": cmd.attempt_id})
                values = got.get("secrets") or {}
                with self._lock:
                    self._url_creds.update(got.get("url_credentials") or {})
            new = [m for m in manifests.values() if not self._inputs.holds(m)]
            local = {ref: self._inputs.fetch(m, self._server_host)
                     for ref, m in manifests.items()}
            for manifest in new:
                self._keeper.added(manifest)
            cmd = replace(cmd, inputs={k: local.get(v, v) for k, v in cmd.inputs.items()})
        except Exception as exc:  # noqa: BLE001 - every prepare gets one final report
            with self._changed:
                self._pending.pop(cmd.attempt_id, None)
                self._inputs_of.pop(cmd.attempt_id, None)
                self._changed.notify_all()
            self._send(event_to_dict(AttemptLost(  # rescheduled: maybe another worker can
                cmd.attempt_id, f"inputs could not be fetched to worker {self.id}: {exc}")))
            return
        with self._lock:
            pending = self._pending.pop(cmd.attempt_id, _Pending())
            self._active.add(cmd.attempt_id)
        self.pool.prepare(cmd, task, values, max_output_bytes=order.max_output_bytes,
                          resources=self._request(cmd, task),
                          terms=Terms(order.exec_timeout, order.priority))
        if pending.kill is not None:
            self.pool.kill(KillAttempt(cmd.attempt_id, self.id, pending.kill))
        elif pending.run:
            self.pool.run(RunAttempt(cmd.attempt_id, self.id))

    def _request(self, cmd: PrepareAttempt, task: TaskSpec) -> ResourceSpec | None:
        with self._lock:
            spec = self._specs.get(cmd.workflow_id)
        return spec.resource_for(task) if spec is not None else None

    def _task(self, cmd: PrepareAttempt) -> TaskSpec:
        with self._lock:
            spec = self._specs.get(cmd.workflow_id)
        if spec is None:
            raise OsmoError(f"no spec of workflow {cmd.workflow_id} was sent to this worker")
        return spec.task(cmd.task)

    # ------------------------------------------------------------------ reports

    def _emit(self, event: Event) -> None:
        """The pool's reports (its thread): forward them; keep exit reports until acked."""
        aid = getattr(event, "attempt_id", None)
        if aid is None:
            return
        with self._changed:
            final = isinstance(event, (AttemptExited, AttemptStartFailed, AttemptLost))
            if final:
                self._active.discard(aid)
                self._inputs_of.pop(aid, None)
                self._changed.notify_all()
            if aid in self._handed_back:
                if final:
                    self._handed_back.discard(aid)
                return
            data = event_to_dict(event)
            output = (Manifest.from_json(event.manifest)
                      if isinstance(event, AttemptExited) and event.manifest else None)
            if isinstance(event, AttemptExited):
                self._unacked[aid] = data
                if output is not None:
                    self._unacked_outputs[aid] = output
        self._send(data)
        if output is not None:
            # its output was ingested here: a next task of a chain placed on this worker
            # takes it as input with no fetch (and no thread hop to fetch nothing)
            self._inputs.hold(output)
            self._keeper.added(output)

    def _protected(self) -> list[Manifest]:
        """What the store must keep: outputs not acknowledged, inputs of live attempts."""
        with self._lock:
            return [*self._unacked_outputs.values(),
                    *(m for ms in self._inputs_of.values() for m in ms)]

    def _send(self, data: dict[str, Any]) -> None:
        self._api.send("worker_report", {"id": self.id, "report": data})

    def _send_log(self, attempt_id: str, records: bytes) -> None:
        with self._lock:  # adopted attempts log before the node registered: held till then
            if self._early_logs is not None:
                self._early_logs.append((attempt_id, records))
                return
        self._api.send("worker_log", {"id": self.id, "attempt_id": attempt_id,
                                      "records": records.decode(errors="replace")})


def _capacity(options: WorkerOptions, images: object, cluster: SlurmRuntime | None
              ) -> tuple[float | None, int | None, int | None]:
    """What the worker offers: its options', else its cluster's, else its machine's.

    Kubernetes is not asked when the options say all three (a pool that may not read nodes,
    ``readNodes: false`` in the chart, must). Slurm always is: ``sinfo`` also checks that
    the pool's partitions exist.
    """
    cpus: float | None
    gpus: int | None
    memory: int | None
    told = None not in (options.cpus, options.gpus, options.memory)
    if cluster is not None:
        offered = cluster.capacity()
        cpus, gpus, memory = offered.cpus, offered.gpus, offered.memory
    elif isinstance(images, KubernetesRuntime) and not told:
        cpus, gpus, memory = cluster_capacity(images.kube, images.pool)
    else:
        return options.cpus, options.gpus, options.memory
    return (options.cpus if options.cpus is not None else cpus,
            options.gpus if options.gpus is not None else gpus,
            options.memory if options.memory is not None else memory)


def _platforms(images: object, cluster: SlurmRuntime | None,
               storage: int) -> dict[str, Capacity]:
    """Every platform a cluster node serves, with its capacity.

    A Kubernetes pool's come from its nodes' labels, a Slurm pool's from its partitions;
    any other worker has none (its one ``--platform`` has its whole capacity). A cluster
    that cannot say now offers none.
    """
    try:
        if cluster is not None:
            found = {name: (float(p.cpus), p.gpus, p.memory)
                     for name, p in cluster.platforms().items()}
        elif isinstance(images, KubernetesRuntime):
            found = images.platforms()
        else:
            return {}
    except OsmoError as exc:
        log.warning("cannot read the cluster's platforms (registering none): %s", exc)
        return {}
    return {name: Capacity(cpus, gpus, memory, storage)
            for name, (cpus, gpus, memory) in found.items()}


def _address() -> str:
    """This host's address as peers should reach it (``{{host:task}}``)."""
    try:
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
            s.connect(("10.255.255.255", 1))  # no packet is sent; picks the outbound interface
            return str(s.getsockname()[0])
    except OSError:
        return "127.0.0.1"

