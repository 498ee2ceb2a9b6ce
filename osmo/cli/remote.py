"""CLI verbs for running across machines: ``osmo worker``, ``osmo health``, ``osmo profile``."""

from __future__ import annotations

import argparse
import json
import os
import signal
import sys
import threading
import time
from typing import Any

from osmo.config import PROFILE_KEYS, open_home, read_profile, write_profile
from osmo.errors import NotAuthenticated, OsmoError, ServerUnreachable
from osmo.layout import Home
from osmo.worker.options import WorkerOptions

__all__ = ["add_parsers", "run_health", "run_profile", "run_worker"]

_HEALTH_STALE = 30.0


def add_parsers(sub: argparse._SubParsersAction) -> None:  # type: ignore[type-arg]
    """Register ``worker``, ``health`` and ``profile``."""
    w = sub.add_parser("worker", help="run a worker that dials out to a server and runs tasks")
    WorkerOptions.add_arguments(w)
    w.add_argument("--home", help="the worker's folder (default: OSMO_HOME/worker)")
    h = sub.add_parser("health", help="exit 0 when the server (or --worker) is healthy, else 3")
    h.add_argument("--worker", action="store_true",
                   help="check the worker process of this host's worker folder instead")
    h.add_argument("--home", help="the worker's folder (with --worker)")
    h.add_argument("--server", default=argparse.SUPPRESS,
                   help="server endpoint to check (same as the global --server)")
    p = sub.add_parser("profile", help="saved client settings: server, cluster, zenoh-config, "
                                       "token (kept 0600)")
    verbs = p.add_subparsers(dest="profile_verb", metavar="VERB", required=True)
    s = verbs.add_parser("set", help="osmo profile set server tcp/HOST:7447")
    s.add_argument("key", choices=PROFILE_KEYS)
    s.add_argument("value")
    u = verbs.add_parser("unset", help="forget a setting")
    u.add_argument("key", choices=PROFILE_KEYS)
    verbs.add_parser("show", help="print the profile")


def _worker_home(args: argparse.Namespace) -> Home:
    return open_home(args.home, worker=True)


def run_worker(args: argparse.Namespace) -> int:
    """``osmo worker``: run until SIGINT (leave now) or SIGTERM (drain, then leave)."""
    from osmo.worker.remote import RemoteWorker

    worker = RemoteWorker(_worker_home(args), WorkerOptions.from_args(args))
    signal.signal(signal.SIGINT, lambda *_: worker.stop())
    signal.signal(signal.SIGTERM, lambda *_: threading.Thread(
        target=worker.drain, name="osmo-drain", daemon=True).start())
    print(f"osmo worker {worker.id}: pool {args.pool}, connecting to "
          f"{', '.join(args.connect)}", file=sys.stderr, flush=True)
    worker.run()
    return 0


def run_health(args: argparse.Namespace) -> int:
    """``osmo health [--worker]``."""
    if args.worker:
        return _worker_health(_worker_home(args))
    from osmo.sdk.client import Client

    try:
        with Client(args.server, autostart=False) as client:
            client.ping()
    except NotAuthenticated as exc:  # the server answered: it is up, this caller has no token
        print(f"ok (answering; {exc})")
        return 0
    except (ServerUnreachable, OsmoError) as exc:
        print(f"unhealthy: {exc}", file=sys.stderr)
        return 3
    print("ok")
    return 0


def _worker_health(home: Home) -> int:
    try:
        state: dict[str, Any] = json.loads(home.worker_health.read_text())
        os.kill(int(state["pid"]), 0)
    except (OSError, ValueError, KeyError):
        print(f"unhealthy: no worker running for {home.root}", file=sys.stderr)
        return 3
    age = time.time() - float(state.get("updated_at", 0))
    if age > _HEALTH_STALE:
        print(f"unhealthy: worker {state.get('id')} has not reported for {age:.0f}s",
              file=sys.stderr)
        return 3
    status = ("draining" if state.get("draining") else
              "connected" if state.get("connected") else "connecting")
    print(f"ok: worker {state.get('id')} {status}, {state.get('running', 0)} running")
    return 0


def run_profile(args: argparse.Namespace) -> int:
    """``osmo profile set|unset|show``."""
    home = open_home()
    profile = read_profile(home)
    if args.profile_verb == "set":
        profile[args.key] = args.value
        write_profile(home, profile)
    elif args.profile_verb == "unset":
        profile.pop(args.key, None)
        write_profile(home, profile)
    else:
        for key in PROFILE_KEYS:
            print(f"{key}: {profile.get(key, '-')}")
    return 0
