"""Command-line options of the server, shared by ``osmo server`` and the background process."""

from __future__ import annotations

import argparse
from typing import Any

__all__ = ["add_server_options", "server_args", "server_kwargs"]


def add_server_options(p: argparse.ArgumentParser) -> None:
    """Add ``--listen``, ``--connect``, ``--zenoh-config``, ``--cluster``, capacity flags."""
    p.add_argument("--listen", action="append", metavar="ENDPOINT",
                   help="zenoh endpoint to listen on, repeatable (default: tcp/127.0.0.1:7447, "
                        "or a free port); e.g. tcp/0.0.0.0:7447 to accept remote workers")
    p.add_argument("--connect", action="append", metavar="ENDPOINT",
                   help="join an existing zenoh router (zenohd) instead of hosting one")
    p.add_argument("--zenoh-config", metavar="FILE",
                   help="zenoh JSON5 config: TLS, mutual TLS, user/password (zenoh's own keys)")
    p.add_argument("--cluster", default="local", help="key prefix shared with workers/clients")
    p.add_argument("--cpus", type=float, help="CPU slots of the local pool (default: cores)")
    p.add_argument("--gpus", type=int, help="GPU slots of the local pool (default: detected)")
    p.add_argument("--no-local-pool", dest="local_pool", action="store_false",
                   help="run no tasks on the server's host (remote workers only)")
    p.add_argument("--reconnect-grace", type=float, default=30.0, metavar="SECONDS",
                   help="after a restart, how long remote workers get to come back (30)")


def server_kwargs(args: argparse.Namespace) -> dict[str, Any]:
    """``serve()`` keyword arguments from parsed options."""
    return {"listen": args.listen, "connect": args.connect, "zenoh_config": args.zenoh_config,
            "cluster": args.cluster, "cpus": args.cpus, "gpus": args.gpus,
            "local_pool": args.local_pool, "reconnect_grace": args.reconnect_grace}


def server_args(args: argparse.Namespace) -> list[str]:
    """The same options as a command line (to start the server in the background)."""
    out: list[str] = []
    for ep in args.listen or []:
        out += ["--listen", ep]
    for ep in args.connect or []:
        out += ["--connect", ep]
    if args.zenoh_config:
        out += ["--zenoh-config", args.zenoh_config]
    if args.cluster != "local":
        out += ["--cluster", args.cluster]
    if args.cpus is not None:
        out += ["--cpus", str(args.cpus)]
    if args.gpus is not None:
        out += ["--gpus", str(args.gpus)]
    if not args.local_pool:
        out.append("--no-local-pool")
    if args.reconnect_grace != 30.0:
        out += ["--reconnect-grace", str(args.reconnect_grace)]
    return out
