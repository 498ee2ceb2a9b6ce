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
from pathlib import Path

from osmo.artifacts import ArtifactStore
from osmo.config import home_dir, write_json_atomic
from osmo.errors import InfrastructureError, OsmoError
from osmo.executor import Executor
from osmo.layout import Home
from osmo.options import ServerOptions
from osmo.scheduler.types import AttemptLost, NodeUp
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
from osmo.server.recovery import InFlight, kill_leftovers, quarantine, restore, split_lost
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
from osmo.worker import containers
from osmo.worker.pool import LocalPool
from osmo.worker.procs import kill_recorded
from osmo.worker.sessions import NodeSessions

__all__ = ["serve"]

log = logging.getLogger("osmo.server")


def _take_lock(home: Home) -> int:
    fd = os.open(home.server_lock, os.O_RDWR | os.O_CREAT, 0o600)
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError:
        os.close(fd)
        raise InfrastructureError(
            f"another osmo server is already running for {home.root}") from None
    return fd


def serve(home: str | os.PathLike[str] | None = None, options: ServerOptions | None = None,
          *, ready: threading.Event | None = None) -> None:
    """Run the server in the foreground until stopped.

    Args:
        home: the osmo home (default: ``OSMO_HOME`` / XDG data folder).
        options: how it listens and runs (default: ``ServerOptions()``).
        ready: set once the server answers requests.
    """
    _tune_interpreter()
    home_path = home_dir(home)
    layout = Home(home_path)
    lock_fd = _take_lock(layout)
    layout.server_info.unlink(missing_ok=True)  # a crashed server's stale address
    options = options or ServerOptions()
    boxes = containers.for_node(options.runtime, options.container_engine,
                                home_path) if options.local_pool else None
    listen, connect = list(options.listen), list(options.connect)
    check_listeners(listen, options.zenoh_config, insecure=options.insecure)
    local = f"unixsock-stream/{_socket(layout)}"
    endpoints = [local, *listen]
    store = Store(layout.state_db)
    owner_token(home_path, store)
    accept_tokens(store, options.accept_tokens)
    authenticate = Authenticator(store, Signer(layout.notice_key))
    inflight = InFlight(layout.applying, layout.crashes)
    restored = restore(store)
    active, failed = quarantine(restored.active, inflight.strike(inflight.left))
    lost, remote_nodes = split_lost(active)
    kill_leftovers(store, lost)
    kill_recorded(layout.procs)  # what the old server spawned but had not committed a pid of

    link = Link.router(endpoints, options.cluster, connect=connect,
                       config_file=options.zenoh_config, peer=bool(connect) and not listen,
                       allow=PEER_ALLOW, deny=PEER_DENY)
    stopping = threading.Event()

    notifier = Notifier(link, authenticate.channels.signer)
    on_changed = notifier.changed

    inbox = Inbox()
    artifacts = ArtifactStore(layout.artifacts)
    pool = LocalPool(home=home_path, emit=inbox.post,
                     cpus=options.cpus, gpus=options.gpus, artifacts=artifacts,
                     credential_for=url_credential(store),
                     input_manifests=output_manifests(store),
                     task_secrets=store.credential,
                     sandbox=options.sandbox, sandbox_share=options.sandbox_share,
                     procs_dir=layout.procs, containers=boxes,
                     log_limit=options.log_limit) if options.local_pool else None
    hub = WorkerHub(link=link, emit=inbox.post, store=store,
                    artifacts=artifacts, home=home_path, url_credential=url_credential(store),
                    attempts_on=lambda node: list(inbox.ask(AttemptsOn(node))),
                    gate=authenticate, log_limit=options.log_limit)
    records = RunRecords(store, home_path)
    fatal: list[BaseException] = []

    def on_fatal(exc: BaseException) -> None:
        fatal.append(exc)
        stopping.set()

    executors: list[Executor] = [hub] if pool is None else [pool, hub]
    engine = Engine(store=store, scheduler=restored.scheduler, executors=executors, inbox=inbox,
                    specs=restored.specs, on_changed=on_changed, home=home_path,
                    on_finished=records.finished, datasets=Datasets(store, artifacts, home_path),
                    reuse=restored.reuse, restore=lambda: restore(store),
                    inflight=inflight, on_fatal=on_fatal,
                    image_ids=containers.image_ids(options.runtime, options.container_engine,
                                                   boxes))
    lost_ids = {t.attempt_id for t in lost}
    for task in active:  # still running on remote workers: placed by the old server
        cmd = restored.scheduler.placement(str(task.attempt_id))
        if task.attempt_id not in lost_ids and cmd is not None:
            engine.placements.recall(cmd)  # so that their outputs get lineage here too
    if pool is not None:
        engine.post(NodeUp(pool.node()))
    for event in failed:
        engine.post(event)
    for task in lost:
        engine.post(AttemptLost(str(task.attempt_id), "server restarted; attempt lost",
                                server_restart=True))
    engine.start()
    hub.expect(remote_nodes, options.reconnect_grace)

    info = {"endpoint": local,
            "endpoints": endpoints, "pid": os.getpid(), "cluster": options.cluster,
            "zenoh_config": (str(Path(options.zenoh_config).absolute())
                             if options.zenoh_config else None),
            "host_id": host_id(), "artifacts": str(artifacts.root),
            "started_at": time.time(), "home": str(home_path), "options": options.to_argv(),
            "runtime": pool.runtime_name() if pool is not None else None,
            "sandbox_why": pool.no_sandbox_why if pool is not None else None,
            "warnings": [pool.sandbox_warning] if pool is not None and pool.sandbox_warning else []}
    local_sessions = NodeSessions(link, pool) if pool is not None else None
    handlers = Handlers(engine, home_path, info, on_shutdown=stopping.set, workers=hub,
                        link=link, gate=authenticate, tokens=TokenHandlers(store, authenticate),
                        sessions=Sessions(store, hub, local_sessions))
    api_server = ApiServer(link, handlers.handle, authenticate, inline=WorkerHub.INLINE,
                           on_crash=lambda exc: log.error("API handler crashed", exc_info=exc))
    write_json_atomic(layout.server_info, info)
    log.info("osmo server %s listening on %s (home %s)", os.getpid(),
             ", ".join(endpoints or connect or []), home_path)

    for sig in (signal.SIGTERM, signal.SIGINT):
        signal.signal(sig, lambda *_: stopping.set())
    if ready is not None:
        ready.set()
    try:
        while not stopping.wait(timeout=3600):
            pass
    finally:
        time.sleep(0.05)  # let the reply to a `shutdown` request leave
        layout.server_info.unlink(missing_ok=True)
        api_server.close()
        if local_sessions is not None:
            local_sessions.close("the server is stopping")
        engine.stop()  # and its executors: the local pool's processes die with the server
        notifier.close()
        records.close()
        link.close()
        store.close()
        inflight.close()
        os.close(lock_fd)
    if fatal:
        raise InfrastructureError(f"the server stopped because its engine cannot go on "
                                  f"({reason(fatal[0])}); see the log above")


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
        serve(args.home, ServerOptions.from_args(args))
    except OsmoError as exc:
        print(f"osmo server: {exc}", file=sys.stderr)
        sys.exit(exc.exit_code)


if __name__ == "__main__":
    main()
