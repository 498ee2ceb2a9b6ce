"""The server's options, defined once.

``osmo server``'s flags, the background server process's command line (``python -m
osmo.server.app``) and ``serve()`` all use :class:`ServerOptions`.

Light on purpose: the CLI imports it to build its parser.
"""

from __future__ import annotations

import argparse
from dataclasses import dataclass

from osmo.config import DEFAULT_CLUSTER
from osmo.worker.options import add_runtime_arguments

__all__ = ["ServerOptions"]


@dataclass(frozen=True)
class ServerOptions:
    """How one server runs (every default is here).

    Attributes:
        listen: zenoh endpoints to listen on (none: ``tcp/127.0.0.1:7447``, or another free
            port if that one is taken, unless ``connect`` is given).
        connect: join an existing zenoh router instead of hosting one.
        zenoh_config: a zenoh JSON5 file (TLS, mutual TLS, user/password).
        cluster: the key prefix shared with workers and clients.
        cpus, gpus: override the local pool's detected capacity.
        local_pool: run tasks on the server's host too (off: remote workers only).
        reconnect_grace: seconds remote workers get to come back after a restart.
        runtime: how the local pool runs image tasks: ``auto``, ``container`` or ``process``
            (``osmo.worker.containers.choose``).
        container_engine: ``podman`` or ``docker`` (default: the first that answers).
    """

    listen: tuple[str, ...] = ()
    connect: tuple[str, ...] = ()
    zenoh_config: str | None = None
    cluster: str = DEFAULT_CLUSTER
    cpus: float | None = None
    gpus: int | None = None
    local_pool: bool = True
    reconnect_grace: float = 30.0
    runtime: str = "auto"
    container_engine: str | None = None

    @staticmethod
    def add_arguments(p: argparse.ArgumentParser) -> None:
        """Add the server's flags to ``p``.

        ``--listen``, ``--connect``, ``--zenoh-config``, ``--cluster``, ``--cpus``, ``--gpus``,
        ``--no-local-pool``, ``--reconnect-grace``.
        """
        d = ServerOptions()
        p.add_argument("--listen", action="append", metavar="ENDPOINT",
                       help="zenoh endpoint to listen on, repeatable (default: "
                            "tcp/127.0.0.1:7447, or a free port); e.g. tcp/0.0.0.0:7447 to "
                            "accept remote workers")
        p.add_argument("--connect", action="append", metavar="ENDPOINT",
                       help="join an existing zenoh router (zenohd) instead of hosting one")
        p.add_argument("--zenoh-config", metavar="FILE",
                       help="zenoh JSON5 config: TLS, mutual TLS, user/password (zenoh's own "
                            "keys)")
        p.add_argument("--cluster", default=d.cluster,
                       help="key prefix shared with workers/clients")
        p.add_argument("--cpus", type=float, help="CPU slots of the local pool (default: cores)")
        p.add_argument("--gpus", type=int, help="GPU slots of the local pool (default: detected)")
        p.add_argument("--no-local-pool", dest="local_pool", action="store_false",
                       help="run no tasks on the server's host (remote workers only)")
        p.add_argument("--reconnect-grace", type=float, default=d.reconnect_grace,
                       metavar="SECONDS", help="after a restart, how long remote workers get "
                                               f"to come back ({d.reconnect_grace:g})")
        add_runtime_arguments(p)

    @classmethod
    def from_args(cls, args: argparse.Namespace) -> ServerOptions:
        """The options parsed by a parser that :meth:`add_arguments` set up."""
        return cls(listen=tuple(args.listen or ()), connect=tuple(args.connect or ()),
                   zenoh_config=args.zenoh_config, cluster=args.cluster, cpus=args.cpus,
                   gpus=args.gpus, local_pool=args.local_pool,
                   reconnect_grace=args.reconnect_grace, runtime=args.runtime,
                   container_engine=args.container_engine)

    def to_argv(self) -> list[str]:
        """The same options as flags, to start the server in another process.

        Only those that differ from the defaults.
        """
        d = ServerOptions()
        out = [arg for ep in self.listen for arg in ("--listen", ep)]
        out += [arg for ep in self.connect for arg in ("--connect", ep)]
        for flag, value in (("--zenoh-config", self.zenoh_config), ("--cluster", self.cluster),
                            ("--cpus", self.cpus), ("--gpus", self.gpus),
                            ("--reconnect-grace", self.reconnect_grace),
                            ("--runtime", self.runtime),
                            ("--container-engine", self.container_engine)):
            if value != getattr(d, flag[2:].replace("-", "_")):
                out += [flag, str(value)]
        return out + ([] if self.local_pool else ["--no-local-pool"])
