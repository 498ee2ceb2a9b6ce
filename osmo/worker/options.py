"""A remote worker's options, defined once.

``osmo worker``'s flags and ``osmo.worker.remote.RemoteWorker`` both use :class:`WorkerOptions`.
The flags a worker shares with the server (runtime, sandbox, log limit) are ``osmo.options``'.

Light on purpose: the CLI imports it to build its parser.
"""

from __future__ import annotations

import argparse
import os
from dataclasses import dataclass, field
from pathlib import Path

from osmo.config import DEFAULT_CLUSTER
from osmo.errors import UsageError
from osmo.options import (
    DEFAULT_LOG_LIMIT,
    SandboxMode,
    SlurmOptions,
    WarmOptions,
    add_log_limit_argument,
    add_runtime_arguments,
    shares,
)
from osmo.status import PRIORITIES

__all__ = ["DEFAULT_KILL_GRACE", "DEFAULT_POOL", "WorkerOptions"]

DEFAULT_POOL = "default"
"""The pool a worker serves unless told another."""

DEFAULT_KILL_GRACE = 3.0
"""Seconds between SIGTERM and SIGKILL when an attempt is killed."""


@dataclass(frozen=True)
class WorkerOptions:
    """How a worker presents itself (see ``osmo worker --help``; every default is here).

    Attributes:
        connect: the server's zenoh endpoints.
        pool: the pool it serves.
        name: its unique name (default: ``HOSTNAME-PID``; ``osmo.names.check_worker_name``).
        platform: matched against resource specs' ``platform``.
        cpus, gpus, memory: capacity to offer (default: what the machine has).
        labels: free ``key: value`` labels, shown with the worker.
        cluster: the server's cluster name.
        zenoh_config: a zenoh JSON5 file (TLS, user/password).
        drain_timeout: on SIGTERM, how long running attempts may finish before they are
            handed back.
        capacity_every: a cluster node (Kubernetes, Slurm) reads its cluster's capacity and
            platforms again this often (seconds; 0: only at registration) and offers what
            changed with its next beat.
        kill_grace: seconds between SIGTERM and SIGKILL when an attempt is killed.
        address: how peers reach its tasks (default: the outbound interface's address).
        token: its API token, role worker (``osmo token create NAME --role worker``).
        token_file: the file it was read from (``--token-file``).
        sandbox: run commands in bubblewrap: ``auto`` (when it works here), ``on``, ``off``.
        sandbox_share: host folders every sandboxed task sees (``--sandbox-share DIR``:
            writable, ``DIR:ro``: read-only).
        runtime: how it runs image tasks: ``auto``, ``container`` or ``process``; ``slurm``:
            every task as a Slurm batch job (a worker on a login host).
        slurm: what every Slurm job of its pool gets (partitions, account, QOS, constraint).
        slurm_python: the Python its Slurm jobs run their agent with on the compute nodes
            (default: the worker's own, on a filesystem they share).
        container_engine: ``podman`` or ``docker`` (default: the first that answers).
        kubernetes_config: the Kubernetes pool's JSON configuration, with ``runtime``
            ``kubernetes`` (``osmo.runtime.kubernetes.config``; None: every default).
        store_limit: bytes its artifact store may hold before cached blobs are removed
            (``osmo.worker.store_keeper``; None: a quarter of its filesystem; 0: no limit).
        log_limit: bytes each attempt's log keeps at most (``osmo.worker.logs``).
        warm: its warm runners (``--warm``; ``osmo.options.WarmOptions``).
    """

    connect: tuple[str, ...]
    pool: str = DEFAULT_POOL
    name: str | None = None
    platform: str | None = None
    cpus: float | None = None
    gpus: int | None = None
    memory: int | None = None
    labels: dict[str, str] = field(default_factory=dict)
    cluster: str = DEFAULT_CLUSTER
    zenoh_config: str | None = None
    drain_timeout: float = 600.0
    capacity_every: float = 30.0
    kill_grace: float = DEFAULT_KILL_GRACE
    address: str | None = None
    token: str | None = None
    token_file: str | None = None
    sandbox: SandboxMode = "auto"
    sandbox_share: tuple[str, ...] = ()
    runtime: str = "auto"
    slurm: SlurmOptions = field(default_factory=SlurmOptions)
    slurm_python: str | None = None
    container_engine: str | None = None
    kubernetes_config: str | None = None
    store_limit: int | None = None
    log_limit: int = DEFAULT_LOG_LIMIT
    warm: WarmOptions = field(default_factory=WarmOptions)

    @property
    def secret_files(self) -> tuple[str, ...]:
        """Files with this worker's secrets: no sandboxed task sees them, wherever they are.

        Its token file and its zenoh config.
        """
        return tuple(f for f in (self.token_file, self.zenoh_config) if f)

    @staticmethod
    def add_arguments(w: argparse.ArgumentParser) -> None:
        """Add ``osmo worker``'s flags (``--home`` is the caller's)."""
        d = WorkerOptions(connect=())
        w.add_argument("--connect", action="append", required=True, metavar="ENDPOINT",
                       help="the server's zenoh endpoint, e.g. tcp/10.0.0.5:7447 (repeatable)")
        w.add_argument("--pool", default=d.pool, help=f"pool this worker serves ({d.pool})")
        w.add_argument("--name", help="unique worker name (default: HOSTNAME-PID)")
        w.add_argument("--platform", help="platform name matched against resource specs")
        w.add_argument("--cpus", type=float, help="CPU slots to offer (default: cores)")
        w.add_argument("--gpus", type=int, help="GPUs to offer (default: detected)")
        w.add_argument("--memory", help="memory to offer, e.g. 8Gi (default: detected)")
        w.add_argument("--label", action="append", default=[], metavar="KEY=VALUE")
        w.add_argument("--zenoh-config", metavar="FILE",
                       default=os.environ.get("OSMO_ZENOH_CONFIG"),
                       help="zenoh JSON5 config for TLS / user-password (OSMO_ZENOH_CONFIG)")
        w.add_argument("--cluster", default=d.cluster, help="the server's cluster name")
        w.add_argument("--token", help="API token with role worker (default: OSMO_TOKEN); "
                                       "an admin makes one: osmo token create NAME --role worker")
        w.add_argument("--token-file", metavar="FILE",
                       help="read the token from FILE (e.g. a mounted Kubernetes Secret)")
        w.add_argument("--drain-timeout", type=float, default=d.drain_timeout,
                       metavar="SECONDS", help="on SIGTERM, how long running tasks may finish "
                                               f"before being handed back ({d.drain_timeout:g})")
        w.add_argument("--capacity-every", type=float, default=d.capacity_every,
                       metavar="SECONDS",
                       help="with --runtime kubernetes or slurm: how often the cluster's "
                            "capacity and platforms are read again, so nodes added or gone "
                            f"count ({d.capacity_every:g}; 0: only at registration)")
        w.add_argument("--store-limit", metavar="SIZE",
                       help="how much its artifact store may hold before cached outputs and "
                            "inputs are removed, oldest first, e.g. 50Gi; 0: no limit "
                            "(default: a quarter of its disk). Outputs the server has not "
                            "taken yet are never removed")
        add_log_limit_argument(w)
        WarmOptions.add_arguments(w)
        add_runtime_arguments(w)
        w.add_argument("--kubernetes-config", metavar="FILE",
                       default=os.environ.get("OSMO_KUBERNETES_CONFIG"),
                       help="with --runtime kubernetes: the pool's JSON configuration "
                            "(namespace, node selectors, gang scheduler, ...; "
                            "OSMO_KUBERNETES_CONFIG)")
        s = w.add_argument_group("Slurm (--runtime slurm)")
        s.add_argument("--slurm-partition", action="append", default=[], metavar="NAME",
                       help="a partition its jobs may use (repeatable; default: Slurm's "
                            "default partition); its capacity is theirs. A task whose "
                            "platform names one of them goes there")
        s.add_argument("--slurm-account", metavar="NAME", help="the account its jobs charge")
        s.add_argument("--slurm-qos", metavar="NAME", help="the QOS of its jobs")
        s.add_argument("--slurm-nice", type=int, default=100, metavar="N",
                       help="a workflow's priority as --nice: HIGH none, NORMAL N, LOW 2N "
                            "(default 100; 0: no --nice)")
        s.add_argument("--slurm-priority-qos", action="append", default=[],
                       metavar="PRIORITY=QOS",
                       help="the QOS of the jobs of workflows of that priority (HIGH, NORMAL "
                            "or LOW; repeatable), instead of --slurm-qos")
        s.add_argument("--slurm-constraint", metavar="FEATURES",
                       help="node features its jobs require (--constraint)")
        s.add_argument("--slurm-python", metavar="PATH",
                       help="the Python 3 the jobs run osmo's agent with on the compute "
                            "nodes (default: this worker's, on a shared filesystem)")

    @classmethod
    def from_args(cls, args: argparse.Namespace) -> WorkerOptions:
        """The options parsed by a parser that :meth:`add_arguments` set up.

        Raises:
            UsageError: a ``--memory``, ``--label`` or ``--capacity-every`` that cannot be
                read.
        """
        from osmo.spec.units import parse_size

        try:
            memory = (int(args.memory) if args.memory and args.memory.isdigit() else
                      parse_size(args.memory) if args.memory else None)
        except ValueError as exc:
            raise UsageError(f"--memory {args.memory!r}: {exc} (e.g. 8Gi, 512Mi)") from None
        if not 0 <= args.capacity_every < float("inf"):
            raise UsageError(f"--capacity-every {args.capacity_every:g}: seconds from 0 "
                             "(0: only at registration)")
        try:
            store_limit = None if args.store_limit is None else parse_size(args.store_limit)
        except ValueError as exc:
            raise UsageError(f"--store-limit {args.store_limit!r}: {exc} (e.g. 50Gi, 0 for "
                             "no limit)") from None
        return cls(connect=tuple(args.connect), pool=args.pool, name=args.name,
                   platform=args.platform, cpus=args.cpus, gpus=args.gpus, memory=memory,
                   labels=_labels(args.label), cluster=args.cluster,
                   zenoh_config=args.zenoh_config, drain_timeout=args.drain_timeout,
                   capacity_every=args.capacity_every,
                   token=_token(args.token, args.token_file), token_file=args.token_file,
                   sandbox=args.sandbox,
                   sandbox_share=shares(args.sandbox_share), runtime=args.runtime,
                   slurm=_slurm(args), slurm_python=args.slurm_python,
                   container_engine=args.container_engine,
                   kubernetes_config=args.kubernetes_config, store_limit=store_limit,
                   log_limit=args.log_limit, warm=WarmOptions.from_args(args))


def _slurm(args: argparse.Namespace) -> SlurmOptions:
    """The ``--slurm-*`` flags (UsageError: one is not a plain Slurm word)."""
    by_priority = []
    for item in args.slurm_priority_qos:
        priority, _, qos = item.partition("=")
        if priority.upper() not in PRIORITIES or not qos:
            raise UsageError(f"--slurm-priority-qos {item!r}: write PRIORITY=QOS, PRIORITY "
                             f"one of {', '.join(PRIORITIES)}")
        by_priority.append((priority.upper(), qos))
    made = SlurmOptions(partitions=tuple(args.slurm_partition), account=args.slurm_account,
                        qos=args.slurm_qos, constraint=args.slurm_constraint,
                        nice=args.slurm_nice, priority_qos=tuple(by_priority))
    made.check()
    return made


def _token(token: str | None, token_file: str | None) -> str | None:
    """The worker's token: ``--token`` > ``--token-file`` > ``OSMO_TOKEN`` (None: none given).

    Raises:
        UsageError: the file cannot be read.
    """
    if token_file and not token:
        try:
            token = Path(token_file).read_text().strip()
        except OSError as exc:
            raise UsageError(f"--token-file {token_file}: {exc.strerror}") from None
    return token or os.environ.get("OSMO_TOKEN") or None


def _labels(items: list[str]) -> dict[str, str]:
    out = {}
    for item in items:
        key, sep, value = item.partition("=")
        if not sep or not key:
            raise UsageError(f"--label {item!r}: write KEY=VALUE")
        out[key] = value
    return out

