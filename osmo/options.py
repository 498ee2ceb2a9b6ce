"""How a server and a worker run: the flags both take, and the server's options, as frozen data.

``osmo server``'s flags, the background server process's command line (``python -m
osmo.server.app``) and ``serve()`` all use :class:`ServerOptions`; ``osmo worker``'s
(``osmo.worker.options.WorkerOptions``) share the runtime and log flags defined here
(:func:`add_runtime_arguments`, :func:`add_log_limit_argument`).

Light on purpose, and below the server, the workers and the runtimes: the CLI imports it to
build its parsers, and the SDK, which starts a local server with these options, imports
nothing of ``osmo.server``, ``osmo.worker`` or ``osmo.runtime`` (``tests/test_layers.py``).

Persisted options: an explicit ``osmo server start`` (or ``osmo server``) saves its options in
``OSMO_HOME/server-options.json`` (:func:`remember`, mode 0600), and the automatic start of a
later CLI call reuses them (:func:`saved_options`), so a server brought back after a crash
listens where its workers look for it. The file holds the options as flags (``to_argv``),
read back through the same parser, so a field added to :class:`ServerOptions` is saved with
no change here. A start with other options replaces the saved ones: the new ones win.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import re
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal, NoReturn

from osmo.config import DEFAULT_CLUSTER
from osmo.errors import UsageError
from osmo.layout import Home

__all__ = ["DEFAULT_ADOPT_GRACE", "DEFAULT_LOG_LIMIT", "MIN_LOG_LIMIT", "SANDBOX_MODES",
           "SandboxMode", "ServerOptions", "SlurmOptions", "WarmOptions", "absolute",
           "add_log_limit_argument",
           "add_runtime_arguments",
           "option_changes", "options_from_argv", "parse_log_limit", "remember",
           "parse_share", "saved_options", "shares"]

SandboxMode = Literal["auto", "on", "off"]
"""Whether process tasks run in bubblewrap: when it works here, always, never
(``osmo.runtime.process.sandbox.choose``)."""
SANDBOX_MODES: tuple[SandboxMode, ...] = ("auto", "on", "off")

DEFAULT_LOG_LIMIT = 64 << 20
"""Bytes one attempt's log may hold before its oldest records are dropped (``osmo.worker.logs``)."""
MIN_LOG_LIMIT = 1 << 20
DEFAULT_ADOPT_GRACE = 120.0
"""Seconds a node whose attempts outlive it (a cluster's jobs or pods) may be away before its
attempts are lost (``osmo server start --adopt-grace``; ``osmo.server.workers``)."""
"""The smallest ``--log-limit``: room for several of the longest records."""


_SLURM_WORD = re.compile(r"^[A-Za-z0-9_.+-]+$")  # a partition, account, QOS, feature


@dataclass(frozen=True)
class SlurmOptions:
    """What a Slurm worker's configuration adds to every job of its pool (``--slurm-*``).

    Attributes:
        partitions: the partitions it may use (``--partition``, comma-separated; none:
            Slurm's default).
        account: ``--account``.
        qos: ``--qos``.
        constraint: ``--constraint`` (node features).
        extra: more sbatch options, each one ``--opt=value`` word, as the operator wrote them.
        nice: a workflow's priority as ``--nice``: HIGH none, NORMAL this, LOW twice this
            (0: no ``--nice``; a user may only lower a job's priority).
        priority_qos: priority (``HIGH``...) → the QOS its jobs use instead of ``qos``.
    """

    partitions: tuple[str, ...] = ()
    account: str | None = None
    qos: str | None = None
    constraint: str | None = None
    extra: tuple[str, ...] = ()
    nice: int = 100
    priority_qos: tuple[tuple[str, str], ...] = ()

    def check(self) -> None:
        """Raise UsageError for a value that is not a plain Slurm word."""
        for flag, value in (*(("--slurm-partition", p) for p in self.partitions),
                            ("--slurm-account", self.account), ("--slurm-qos", self.qos),
                            ("--slurm-constraint", self.constraint),
                            *(("--slurm-priority-qos", q) for _, q in self.priority_qos)):
            if value is not None and not _SLURM_WORD.match(value):
                raise UsageError(f"{flag} {value!r}: only letters, digits and _ . + - are "
                                 "allowed")
        if not 0 <= self.nice <= 100_000:
            raise UsageError(f"--slurm-nice {self.nice}: a number from 0 to 100000")
        for word in self.extra:
            if not word.startswith("--") or "\n" in word:
                raise UsageError(f"--slurm-option {word!r}: write one --option=value word")


def add_runtime_arguments(p: argparse.ArgumentParser) -> None:
    """How tasks run: ``--sandbox``, ``--runtime``, ``--container-engine`` (server and worker)."""
    p.add_argument("--sandbox", choices=SANDBOX_MODES, default="auto",
                   help="run process tasks in a bubblewrap sandbox: auto (when bwrap works "
                        "here; the default), on (required), off")
    shared = os.environ.get("OSMO_SANDBOX_SHARE") or ""
    p.add_argument("--sandbox-share", action="append", metavar="DIR[:ro]",
                   default=_env_shares(shared),
                   help="a host folder every sandboxed task may read and write, at the same "
                        "path; DIR:ro for read only (repeatable; OSMO_SANDBOX_SHARE, "
                        "':'-separated, e.g. /scratch:/data:ro). Tasks get their own empty "
                        "/tmp otherwise. As root, tasks run as nobody: a writable share must "
                        "be writable by nobody")
    p.add_argument("--runtime", choices=("auto", "container", "process", "kubernetes", "slurm"),
                   default=os.environ.get("OSMO_RUNTIME") or "auto",
                   help="run tasks that name an image in containers (container), as host "
                        "processes (process), or in containers when an engine is installed "
                        "(auto, the default; OSMO_RUNTIME); osmo worker only: kubernetes, "
                        "as pods of a cluster (see --kubernetes-config); slurm (a worker on "
                        "a Slurm login host), every task as a Slurm batch job")
    p.add_argument("--container-engine", choices=("podman", "docker"),
                   default=os.environ.get("OSMO_CONTAINER_ENGINE") or None,
                   help="the container engine (default: podman, else docker; "
                        "OSMO_CONTAINER_ENGINE)")


@dataclass(frozen=True)
class WarmOptions:
    """A pool's warm runners for typed tasks (``osmo.runtime.process.warm``).

    Attributes:
        on: typed tasks start as forks of a runner that imported their type (``--warm on``,
            the default) or as fresh interpreters (``--warm off``).
        idle: seconds a runner waits for its next attempt before it exits (``--warm-idle``).
        max_memory: bytes of resident memory over which a runner is replaced
            (``--warm-max-memory``; None: no limit).
    """

    on: bool = True
    idle: float = 60.0
    max_memory: int | None = 2 << 30

    @staticmethod
    def add_arguments(p: argparse.ArgumentParser) -> None:
        """``--warm``, ``--warm-idle``, ``--warm-max-memory`` (server and worker)."""
        d = WarmOptions()
        p.add_argument("--warm", choices=("on", "off"),
                       default=os.environ.get("OSMO_WARM") or "on",
                       help="start typed tasks (type:) as forks of a runner that imported "
                            "their type once: on (the default; OSMO_WARM) or off (a fresh "
                            "interpreter per attempt). Process tasks without a sandbox only")
        p.add_argument("--warm-idle", type=float, default=d.idle, metavar="SECONDS",
                       help=f"a warm runner exits after this long without tasks ({d.idle:g})")
        p.add_argument("--warm-max-memory", default="2Gi", metavar="SIZE",
                       help="a warm runner whose resident memory is above this is replaced "
                            "(default 2Gi; 0: no limit)")

    @classmethod
    def from_args(cls, args: argparse.Namespace) -> WarmOptions:
        """The options :meth:`add_arguments` parsed. Raises UsageError: a bad size or time."""
        from osmo.spec.units import parse_size

        if not args.warm_idle > 0:
            raise UsageError(f"--warm-idle {args.warm_idle:g}: a number of seconds above 0")
        try:
            limit = parse_size(str(args.warm_max_memory))
        except ValueError as exc:
            raise UsageError(f"--warm-max-memory {args.warm_max_memory!r}: {exc} "
                             "(e.g. 2Gi, 0 for no limit)") from None
        return cls(on=args.warm == "on", idle=args.warm_idle, max_memory=limit or None)

    def __str__(self) -> str:
        """``on``, ``off``, or its flags that differ from the defaults."""
        return " ".join(self.to_argv()) or "on"

    def to_argv(self) -> list[str]:
        """The same options as flags (those that differ from the defaults)."""
        d = WarmOptions()
        out = [] if self.on else ["--warm", "off"]
        out += [] if self.idle == d.idle else ["--warm-idle", f"{self.idle:g}"]
        if self.max_memory != d.max_memory:
            out += ["--warm-max-memory", str(self.max_memory or 0)]
        return out


def add_log_limit_argument(p: argparse.ArgumentParser) -> None:
    """``--log-limit SIZE``: the cap on each attempt's log (server and worker)."""
    p.add_argument("--log-limit", type=_log_limit, default=DEFAULT_LOG_LIMIT, metavar="SIZE",
                   help="the most each task attempt's log keeps, e.g. 256Mi (default 64Mi, "
                        "least 1Mi): past it the oldest lines are dropped behind one line "
                        "saying how many bytes were")


def _log_limit(text: str) -> int:
    try:
        return parse_log_limit(text)
    except ValueError as exc:
        raise argparse.ArgumentTypeError(f"{exc} (e.g. 64Mi, 1Gi)") from None


def parse_share(spec: str) -> tuple[str, bool]:
    """``DIR`` → (DIR, writable); ``DIR:ro`` → read-only; ``DIR:rw`` → writable."""
    folder, sep, mode = spec.rpartition(":")
    if sep and mode in ("ro", "rw") and folder:
        return folder, mode == "rw"
    return spec, True


def shares(folders: list[str] | None) -> tuple[str, ...]:
    """``--sandbox-share`` folders, absolute (relative to the working folder); ``:ro`` kept."""
    out = []
    for spec in folders or ():
        folder, writable = parse_share(spec)
        out.append(os.path.abspath(folder) + ("" if writable else ":ro"))
    return tuple(dict.fromkeys(out))


def _env_shares(value: str) -> list[str]:
    """OSMO_SANDBOX_SHARE's folders (``/scratch:/data:ro``).

    ``:``-separated; a ``ro`` or ``rw`` after a folder says how it is shared.
    """
    out: list[str] = []
    for part in value.split(os.pathsep):
        if part in ("ro", "rw") and out:
            out[-1] = f"{parse_share(out[-1])[0]}:{part}"
        elif part:
            out.append(part)
    return out


def parse_log_limit(text: str) -> int:
    """A ``--log-limit`` (``64Mi``, ``1Gi``, a number of bytes) in bytes.

    Raises:
        ValueError: not a size, or smaller than :data:`MIN_LOG_LIMIT`.
    """
    from osmo.spec.units import parse_size

    limit = parse_size(text)
    if limit < MIN_LOG_LIMIT:
        raise ValueError(f"{text!r} is too small; the least is 1Mi")
    return limit


@dataclass(frozen=True)
class ServerOptions:
    """How one server runs (every default is here).

    Attributes:
        listen: zenoh endpoints to listen on besides the home's Unix socket (none: that
            socket only, ``OSMO_HOME/server.sock``; nothing on TCP).
        connect: join an existing zenoh router instead of hosting one.
        zenoh_config: a zenoh JSON5 file (TLS, mutual TLS, user/password).
        cluster: the key prefix shared with workers and clients.
        cpus, gpus: override the local pool's detected capacity.
        local_pool: run tasks on the server's host too (off: remote workers only).
        reconnect_grace: seconds remote workers get to come back after a restart.
        adopt_grace: seconds a node whose attempts outlive it (a cluster's jobs or pods)
            may be away before its attempts are lost and rescheduled.
        insecure: allow a network listener without zenoh authentication (warned at every
            start; see ``osmo.transport.listeners.check_listeners``).
        accept_tokens: ``NAME:ROLE:FILE`` tokens to accept (Kubernetes Secrets).
        sandbox: run the local pool's tasks in bubblewrap: ``auto``, ``on``, ``off``.
        sandbox_share: host folders every sandboxed task sees (``--sandbox-share DIR``:
            writable, ``DIR:ro``: read-only).
        runtime: how the local pool runs image tasks: ``auto``, ``container`` or ``process``
            (``osmo.runtime.choose.container_engine``).
        container_engine: ``podman`` or ``docker`` (default: the first that answers).
        log_limit: bytes each attempt's log keeps at most, on the local pool and as stored
            from remote workers' batches (``osmo.worker.logs``).
        warm: the local pool's warm runners (``--warm``; :class:`WarmOptions`).
    """

    listen: tuple[str, ...] = ()
    connect: tuple[str, ...] = ()
    zenoh_config: str | None = None
    cluster: str = DEFAULT_CLUSTER
    cpus: float | None = None
    gpus: int | None = None
    local_pool: bool = True
    reconnect_grace: float = 30.0
    adopt_grace: float = DEFAULT_ADOPT_GRACE
    insecure: bool = False
    accept_tokens: tuple[str, ...] = ()
    sandbox: SandboxMode = "auto"
    sandbox_share: tuple[str, ...] = ()
    runtime: str = "auto"
    container_engine: str | None = None
    log_limit: int = DEFAULT_LOG_LIMIT
    warm: WarmOptions = field(default_factory=WarmOptions)

    @property
    def secret_files(self) -> tuple[str, ...]:
        """Files with this server's secrets: no sandboxed task sees them, wherever they are.

        Its ``--accept-token`` files and its zenoh config.
        """
        tokens = [spec.split(":", 2)[2] for spec in self.accept_tokens if spec.count(":") >= 2]
        return (*tokens, *([self.zenoh_config] if self.zenoh_config else []))

    @staticmethod
    def add_arguments(p: argparse.ArgumentParser) -> None:
        """Add the server's flags to ``p``.

        ``--listen``, ``--connect``, ``--zenoh-config``, ``--cluster``, ``--cpus``, ``--gpus``,
        ``--no-local-pool``, ``--reconnect-grace``, ``--sandbox``, ``--log-limit``.
        """
        d = ServerOptions()
        p.add_argument("--listen", action="append", metavar="ENDPOINT",
                       help="zenoh endpoint to listen on, repeatable (default: none, only the "
                            "home's Unix socket (OSMO_HOME/server.sock)); e.g. "
                            "tcp/0.0.0.0:7447 to accept remote workers (with authentication)")
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
        p.add_argument("--adopt-grace", type=float, default=d.adopt_grace, metavar="SECONDS",
                       help="how long a node whose attempts outlive it (Slurm jobs, pods) may "
                            "be away before they are rescheduled; back in time, it adopts "
                            f"them ({d.adopt_grace:g})")
        p.add_argument("--accept-token", action="append", metavar="NAME:ROLE:FILE",
                       help="accept the API token in FILE as token NAME with ROLE "
                            "(repeatable; e.g. a mounted Kubernetes Secret)")
        p.add_argument("--insecure", action="store_true",
                       help="allow --listen on a network address without zenoh "
                            "authentication (usrpwd or mTLS in --zenoh-config); tokens then "
                            "travel in clear")
        add_log_limit_argument(p)
        add_runtime_arguments(p)
        WarmOptions.add_arguments(p)

    @classmethod
    def from_args(cls, args: argparse.Namespace) -> ServerOptions:
        """The options parsed by a parser that :meth:`add_arguments` set up.

        Raises:
            UsageError: ``--runtime slurm`` (a worker's, on a login host).
        """
        if args.runtime == "slurm" and args.local_pool:
            raise UsageError("--runtime slurm is for a worker on a Slurm login host (osmo "
                             "worker --runtime slurm); a server's own pool runs tasks here")
        return cls(listen=tuple(args.listen or ()), connect=tuple(args.connect or ()),
                   zenoh_config=args.zenoh_config, cluster=args.cluster, cpus=args.cpus,
                   gpus=args.gpus, local_pool=args.local_pool,
                   reconnect_grace=args.reconnect_grace, adopt_grace=args.adopt_grace,
                   insecure=getattr(args, "insecure", False),
                   accept_tokens=tuple(getattr(args, "accept_token", None) or ()),
                   sandbox=args.sandbox, sandbox_share=shares(args.sandbox_share),
                   runtime=args.runtime, container_engine=args.container_engine,
                   log_limit=args.log_limit, warm=WarmOptions.from_args(args))

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
                            ("--adopt-grace", self.adopt_grace),
                            ("--sandbox", self.sandbox),
                            ("--runtime", self.runtime),
                            ("--container-engine", self.container_engine),
                            ("--log-limit", self.log_limit)):
            if value != getattr(d, flag[2:].replace("-", "_")):
                out += [flag, str(value)]
        out += [arg for d in self.sandbox_share for arg in ("--sandbox-share", d)]
        out += self.warm.to_argv()
        out += [] if self.local_pool else ["--no-local-pool"]
        out += [arg for spec in self.accept_tokens for arg in ("--accept-token", spec)]
        return out + (["--insecure"] if self.insecure else [])


class _Refusing(argparse.ArgumentParser):
    """A parser that raises instead of printing usage and exiting."""

    def error(self, message: str) -> NoReturn:
        raise ValueError(message)


def options_from_argv(argv: list[str]) -> ServerOptions:
    """The options that flags ``argv`` (as :meth:`ServerOptions.to_argv` writes them) give.

    Raises:
        ValueError: a flag the server does not take, or a bad value.
    """
    parser = _Refusing(prog="osmo server", add_help=False, exit_on_error=False)
    ServerOptions.add_arguments(parser)
    try:
        return ServerOptions.from_args(parser.parse_args(argv))
    except (argparse.ArgumentError, UsageError) as exc:
        raise ValueError(str(exc)) from None


def saved_options(home: Home) -> ServerOptions | None:
    """The options the last explicit start saved in ``home``; None when none were saved.

    Raises:
        UsageError: the file is unreadable or holds options the server does not take.
    """
    path = home.server_options
    try:
        data = json.loads(path.read_bytes())
    except FileNotFoundError:
        return None
    except (OSError, ValueError) as exc:
        raise _damaged(path, str(exc)) from None
    argv = data.get("argv") if isinstance(data, dict) else None
    if not isinstance(argv, list) or not all(isinstance(a, str) for a in argv):
        raise _damaged(path, "no list of flags under 'argv'")
    try:
        return options_from_argv(argv)
    except ValueError as exc:
        raise _damaged(path, str(exc)) from None


def _damaged(path: Path, why: str) -> UsageError:
    return UsageError(f"{path}: unusable saved server options ({why}); fix or delete the "
                      f"file, or start the server with the options you want (`osmo server "
                      f"start ...` saves them)")


def remember(home: Home, options: ServerOptions) -> list[str]:
    """Save ``options`` as ``home``'s server options; return what changed (see below).

    A relative ``zenoh_config`` is saved as an absolute path, so an automatic start from
    another folder finds it. The file is written atomically with mode 0600.

    Returns:
        :func:`option_changes` from the saved options (the defaults when none were saved or
        the file was damaged) to ``options``.
    """
    try:
        before = saved_options(home) or ServerOptions()
    except UsageError:
        before = ServerOptions()
    options = absolute(options)
    path = home.server_options
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    tmp.unlink(missing_ok=True)  # a crashed start's; O_EXCL then never follows a planted link
    fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
    with os.fdopen(fd, "w") as out:
        json.dump({"argv": options.to_argv(), "saved_at": time.time()}, out)
    os.replace(tmp, path)
    return option_changes(before, options)


def absolute(options: ServerOptions) -> ServerOptions:
    """``options`` with a relative ``zenoh_config`` made absolute (from the current folder)."""
    if options.zenoh_config is None:
        return options
    return dataclasses.replace(options, zenoh_config=str(Path(options.zenoh_config).absolute()))


def option_changes(before: ServerOptions, after: ServerOptions) -> list[str]:
    """One ``name: old → new`` line per option that differs (empty: the same options)."""
    out = []
    for f in dataclasses.fields(ServerOptions):
        old, new = getattr(before, f.name), getattr(after, f.name)
        if old != new:
            out.append(f"{f.name}: {_shown(old)} → {_shown(new)}")
    return out


def _shown(value: object) -> str:
    if value is None or value == ():
        return "(default)"
    if isinstance(value, tuple):
        return " ".join(str(v) for v in value)
    if isinstance(value, float) and value.is_integer():
        return str(int(value))
    return str(value)


