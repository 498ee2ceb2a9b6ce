"""Composes the server: store, scheduler, engine and its executors, zenoh API; recovery.

The executors (``osmo.executor``) are the local pool (unless ``--no-local-pool``) and the
remote-worker hub; they report into the engine's inbox, which exists before both, and the
engine owns and closes them.
``serve()`` runs one server for one ``OSMO_HOME`` in the foreground until SIGTERM/SIGINT or
an API ``shutdown``. Only one server runs per home: it holds ``server.lock`` for its life.

Recovery after a crash (kill -9): workflows that were not terminal are restored into the
scheduler from the store; attempts that were placed or running on the local pool died with
the server (their leftover processes are killed by pid, after checking the pid still names
the same process), so each is reported lost and rescheduled as a new retry. Completed tasks
are never re-run; the lost attempt's id is fenced, so it can never be committed. An attempt
whose report the old server was applying when it died is recovered the same way the first
time; the second time a server dies applying a report of that task, it is quarantined
instead: failed with the reason, never run again on its own (see ``osmo.server.recovery``).

If the engine cannot go on (the state store is gone or unwritable), the server stops and
exits with code 3, so that a supervisor or health check sees it instead of a server that
answers but can no longer change anything.
"""

from __future__ import annotations

import fcntl
import gc
import logging
import os
import signal
import sys
import threading
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from osmo.artifacts import ArtifactStore
from osmo.config import open_home, write_json_atomic
from osmo.errors import InfrastructureError, OsmoError
from osmo.executor import Executor
from osmo.layout import Home
from osmo.options import ServerOptions
from osmo.runtime.choose import containers_for_node, image_ids
from osmo.runtime.container.runtime import ContainerRuntime
from osmo.scheduler import TaskState
from osmo.scheduler.types import AttemptLost, Event, NodeUp
from osmo.server.auth import Authenticator, TokenHandlers, accept_tokens, owner_token
from osmo.server.credentials import url_credential
from osmo.server.datasets import Datasets
from osmo.server.engine import Engine
from osmo.server.handlers import Handlers
from osmo.server.inbox import Inbox
from osmo.server.isolation import reason
from osmo.server.notices import Notifier
from osmo.server.placing import output_manifests
from osmo.server.records import RunRecords
from osmo.server.recovery import (
    InFlight,
    Restored,
    kill_leftovers,
    quarantine,
    restore,
    split_lost,
)
from osmo.server.requests import AttemptsOn
from osmo.server.sessions import Sessions
from osmo.server.workers import WorkerHub
from osmo.store.sqlite import Store
from osmo.transport.blobs import host_id
from osmo.transport.listeners import check_listeners
from osmo.transport.rpc import ApiServer
from osmo.transport.seal import Signer
from osmo.transport.wire import PEER_ALLOW, PEER_DENY
from osmo.transport.zenoh_link import Link
from osmo.worker.pool import LocalPool
from osmo.worker.procs import kill_recorded
from osmo.worker.sessions import NodeSessions

__all__ = ["serve"]

log = logging.getLogger("osmo.server")


def serve(home: Home, options: ServerOptions | None = None, *,
          ready: threading.Event | None = None) -> None:
    """Run the server of ``home`` in the foreground until stopped.

    Args:
        home: the osmo home (``osmo.config.open_home``).
        options: how it listens and runs (default: ``ServerOptions()``).
        ready: set once the server answers requests.

    Raises:
        InfrastructureError: another server runs for ``home``, or the engine could not go on.
    """
    _tune_interpreter()
    lock_fd = _take_lock(home)
    home.server_info.unlink(missing_ok=True)  # a crashed server's stale address
    server = _Server(home, options or ServerOptions())
    for sig in (signal.SIGTERM, signal.SIGINT):
        signal.signal(sig, lambda *_: server.stopping.set())
    if ready is not None:
        ready.set()
    try:
        while not server.stopping.wait(timeout=3600):
            pass
    finally:
        server.close()
        os.close(lock_fd)
    if server.fatal:
        raise InfrastructureError(f"the server stopped because its engine cannot go on "
                                  f"({reason(server.fatal[0])}); see the log above")


def _take_lock(home: Home) -> int:
    fd = os.open(home.server_lock, os.O_RDWR | os.O_CREAT, 0o600)
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError:
        os.close(fd)
        raise InfrastructureError(
            f"another osmo server is already running for {home.root}") from None
    return fd


class _Server:
    """One running server: its parts, composed and started in order (see the module docstring).

    ``stopping`` is set to stop it (a signal, a ``shutdown`` request, or the engine that
    cannot go on: then ``fatal`` holds why); :meth:`close` stops the parts.
    """

    def __init__(self, home: Home, options: ServerOptions) -> None:
        self.stopping = threading.Event()
        self.fatal: list[BaseException] = []
        self.home = home
        boxes = containers_for_node(options.runtime, options.container_engine,
                                    home) if options.local_pool else None
        check_listeners(options.listen, options.zenoh_config, insecure=options.insecure)
        self.endpoints = [f"unixsock-stream/{_socket(home)}", *options.listen]
        self.store = Store(home.state_db)
        owner_token(home, self.store)
        accept_tokens(self.store, options.accept_tokens)
        self.gate = Authenticator(self.store, Signer(home.notice_key))
        self.inflight = InFlight(home.applying, home.crashes)
        recovered = _Recovered.from_store(self.store, self.inflight, home)
        self.link = Link.router(self.endpoints, options.cluster, connect=list(options.connect),
                                config_file=options.zenoh_config,
                                peer=bool(options.connect) and not options.listen,
                                allow=PEER_ALLOW, deny=PEER_DENY)
        self.notifier = Notifier(self.link, self.gate.channels.signer)
        self.records = RunRecords(self.store, home)
        self.artifacts = ArtifactStore(home.artifacts)
        self.pool, self.hub, self.engine = self._executors(options, boxes, recovered)
        recovered.replay(self.engine, self.pool)
        self.engine.start()
        self.hub.expect(recovered.remote_nodes, options.reconnect_grace)
        self.info = self._info(options)
        self.local_sessions = (NodeSessions(self.link, self.pool) if self.pool is not None
                               else None)
        self.api = self._api()
        write_json_atomic(home.server_info, self.info)
        log.info("osmo server %s listening on %s (home %s)", os.getpid(),
                 ", ".join(self.endpoints or options.connect or []), home.root)

    def _executors(self, options: ServerOptions, boxes: ContainerRuntime | None,
                   recovered: _Recovered) -> tuple[LocalPool | None, WorkerHub, Engine]:
        """The local pool (unless ``--no-local-pool``), the remote workers' hub, the engine.

        The executors report into the engine's inbox, which exists before them; the engine
        owns and closes them.
        """
        store, artifacts, inbox = self.store, self.artifacts, Inbox()
        pool = LocalPool(home=self.home, emit=inbox.post,
                         cpus=options.cpus, gpus=options.gpus, artifacts=artifacts,
                         credential_for=url_credential(store),
                         input_manifests=output_manifests(store),
                         task_secrets=store.credential,
                         sandbox=options.sandbox, sandbox_share=options.sandbox_share,
                         procs_dir=self.home.procs, containers=boxes,
                         log_limit=options.log_limit,
                         warm=options.warm) if options.local_pool else None
        for secret in options.secret_files:  # a token file a task must not read
            if pool is not None:
                pool.hide(Path(secret))
        hub = WorkerHub(link=self.link, emit=inbox.post, store=store, artifacts=artifacts,
                        home=self.home, url_credential=url_credential(store),
                        attempts_on=lambda node: list(inbox.ask(AttemptsOn(node))),
                        gate=self.gate, log_limit=options.log_limit,
                        adopt_grace=options.adopt_grace)
        executors: list[Executor] = [hub] if pool is None else [pool, hub]
        engine = Engine(store=store, scheduler=recovered.restored.scheduler,
                        executors=executors, inbox=inbox, specs=recovered.restored.specs,
                        on_changed=self.notifier.changed, home=self.home,
                        on_finished=self.records.finished,
                        datasets=Datasets(store, artifacts, self.home),
                        reuse=recovered.restored.reuse, restore=lambda: restore(store),
                        inflight=self.inflight, on_fatal=self._on_fatal,
                        image_ids=image_ids(options.runtime, options.container_engine, boxes))
        return pool, hub, engine

    def _info(self, options: ServerOptions) -> dict[str, Any]:
        """What the server writes to ``server.json`` and answers ``ping`` with."""
        pool = self.pool
        return {"endpoint": self.endpoints[0], "endpoints": self.endpoints, "pid": os.getpid(),
                "cluster": options.cluster,
                "zenoh_config": (str(Path(options.zenoh_config).absolute())
                                 if options.zenoh_config else None),
                "host_id": host_id(), "artifacts": str(self.artifacts.root),
                "started_at": time.time(), "home": str(self.home.root),
                "options": options.to_argv(),
                "runtime": pool.runtime_name() if pool is not None else None,
                "sandbox_why": pool.no_sandbox_why if pool is not None else None,
                "warnings": [pool.sandbox_warning] if pool is not None and pool.sandbox_warning
                else []}

    def _on_fatal(self, exc: BaseException) -> None:
        self.fatal.append(exc)
        self.stopping.set()

    def _api(self) -> ApiServer:
        """The API on the link: every verb through the handlers, as its caller's identity."""
        handlers = Handlers(self.engine, self.home, self.info, on_shutdown=self.stopping.set,
                            workers=self.hub, link=self.link, gate=self.gate,
                            tokens=TokenHandlers(self.store, self.gate),
                            sessions=Sessions(self.store, self.hub, self.local_sessions),
                            warm=self.pool.warm_runners if self.pool is not None else None)
        return ApiServer(self.link, handlers.handle, self.gate, inline=WorkerHub.INLINE,
                         on_crash=lambda exc: log.error("API handler crashed", exc_info=exc))

    def close(self) -> None:
        """Stop answering, then stop the engine (and its executors) and close what is open."""
        time.sleep(0.05)  # let the reply to a `shutdown` request leave
        self.home.server_info.unlink(missing_ok=True)
        self.api.close()
        if self.local_sessions is not None:
            self.local_sessions.close("the server is stopping")
        self.engine.stop()  # and its executors: the local pool's processes die with the server
        self.notifier.close()
        self.records.close()
        self.link.close()
        self.store.close()
        self.inflight.close()


@dataclass
class _Recovered:
    """What a server starting on a home's store takes over (see the module docstring).

    Attributes:
        restored: the scheduler rebuilt from the store, with specs and cache choices.
        active: attempts placed or running that are not quarantined.
        failed: a failure for each quarantined attempt.
        lost: the active attempts of the local pool, which died with the old server.
        remote_nodes: remote workers whose attempts are expected back.
    """

    restored: Restored
    active: list[TaskState]
    failed: list[Event]
    lost: list[TaskState]
    remote_nodes: set[str]

    @classmethod
    def from_store(cls, store: Store, inflight: InFlight, home: Home) -> _Recovered:
        """Restore the store's state; kill what the old server's local attempts left running."""
        restored = restore(store)
        active, failed = quarantine(restored.active, inflight.strike(inflight.left))
        lost, remote_nodes = split_lost(active)
        kill_leftovers(store, lost)
        kill_recorded(home.procs)  # what the old server spawned but had not committed a pid of
        return cls(restored, active, failed, lost, remote_nodes)

    def replay(self, engine: Engine, pool: LocalPool | None) -> None:
        """Tell the engine what it takes over, before it starts."""
        lost_ids = {t.attempt_id for t in self.lost}
        for task in self.active:  # still running on remote workers: placed by the old server
            cmd = self.restored.scheduler.placement(str(task.attempt_id))
            if task.attempt_id not in lost_ids and cmd is not None:
                engine.placements.recall(cmd)  # so that their outputs get lineage here too
        if pool is not None:
            engine.post(NodeUp(pool.node()))
        for event in self.failed:
            engine.post(event)
        for task in self.lost:
            engine.post(AttemptLost(str(task.attempt_id), "server restarted; attempt lost",
                                    server_restart=True))


def _socket(layout: Home) -> Path:
    """The local Unix socket's path, ready to listen on.

    A stale socket of a dead server is removed (this server holds the home's lock); the short
    fallback folder under /tmp must be this user's only.
    """
    path = layout.server_socket
    if path.parent != layout.root.absolute():
        path.parent.mkdir(mode=0o700, exist_ok=True)
        st = path.parent.stat()
        if st.st_uid != os.geteuid() or st.st_mode & 0o077:
            raise InfrastructureError(f"{path.parent} must be a folder of yours with mode 0700 "
                                      "(it holds the local server's socket); remove it")
    path.unlink(missing_ok=True)
    return path


def _tune_interpreter() -> None:
    """This process serves: a shorter GIL switch interval and far fewer garbage collections.

    With CPython's default GC thresholds, a 100,000-task submit spends most of its time in
    collections scanning the objects it is building (measured: 27.7 s → 9.3 s for the spec
    check and the scheduler's records). The server's objects are long-lived records, not
    cyclic garbage, so collecting every 50,000 allocations instead of 700 costs no memory
    that matters.
    """
    sys.setswitchinterval(float(os.environ.get("OSMO_SWITCH_INTERVAL", "0.005")))
    gc.set_threshold(50_000, 20, 50)


def main() -> None:
    """Entry point of the background server process (``python -m osmo.server.app``)."""
    logging.basicConfig(level=logging.INFO, stream=sys.stderr,
                        format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    import argparse

    parser = argparse.ArgumentParser(prog="osmo-server")
    parser.add_argument("--home")
    ServerOptions.add_arguments(parser)
    args = parser.parse_args()
    try:
        serve(open_home(args.home), ServerOptions.from_args(args))
    except OsmoError as exc:
        print(f"osmo server: {exc}", file=sys.stderr)
        sys.exit(exc.exit_code)


if __name__ == "__main__":
    main()
