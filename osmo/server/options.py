"""The server's options, defined once.

``osmo server``'s flags, the background server process's command line (``python -m
osmo.server.app``) and ``serve()`` all use :class:`ServerOptions`.

Light on purpose: the CLI imports it to build its parser.

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
import ipaddress
import json
import os
import time
from dataclasses import dataclass
from pathlib import Path
from typing import NoReturn

from osmo.config import DEFAULT_CLUSTER
from osmo.errors import UsageError
from osmo.layout import Home
from osmo.runtime.sandbox import SandboxMode
from osmo.worker.logs import DEFAULT_LOG_LIMIT
from osmo.worker.options import add_log_limit_argument, add_runtime_arguments, shares

__all__ = ["ServerOptions", "absolute", "check_listeners", "network_listeners",
           "option_changes", "options_from_argv", "remember", "saved_options"]


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
        insecure: allow a network listener without zenoh authentication (warned at every
            start; see :func:`check_listeners`).
        accept_tokens: ``NAME:ROLE:FILE`` tokens to accept (Kubernetes Secrets).
        sandbox: run the local pool's tasks in bubblewrap: ``auto``, ``on``, ``off``.
        sandbox_share: host folders every sandboxed task sees (``--sandbox-share DIR``:
            writable, ``DIR:ro``: read-only).
        runtime: how the local pool runs image tasks: ``auto``, ``container`` or ``process``
            (``osmo.worker.containers.choose``).
        container_engine: ``podman`` or ``docker`` (default: the first that answers).
        log_limit: bytes each attempt's log keeps at most, on the local pool and as stored
            from remote workers' batches (``osmo.worker.logs``).
    """

    listen: tuple[str, ...] = ()
    connect: tuple[str, ...] = ()
    zenoh_config: str | None = None
    cluster: str = DEFAULT_CLUSTER
    cpus: float | None = None
    gpus: int | None = None
    local_pool: bool = True
    reconnect_grace: float = 30.0
    insecure: bool = False
    accept_tokens: tuple[str, ...] = ()
    sandbox: SandboxMode = "auto"
    sandbox_share: tuple[str, ...] = ()
    runtime: str = "auto"
    container_engine: str | None = None
    log_limit: int = DEFAULT_LOG_LIMIT

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
        p.add_argument("--accept-token", action="append", metavar="NAME:ROLE:FILE",
                       help="accept the API token in FILE as token NAME with ROLE "
                            "(repeatable; e.g. a mounted Kubernetes Secret)")
        p.add_argument("--insecure", action="store_true",
                       help="allow --listen on a network address without zenoh "
                            "authentication (usrpwd or mTLS in --zenoh-config); tokens then "
                            "travel in clear")
        add_log_limit_argument(p)
        add_runtime_arguments(p)

    @classmethod
    def from_args(cls, args: argparse.Namespace) -> ServerOptions:
        """The options parsed by a parser that :meth:`add_arguments` set up."""
        return cls(listen=tuple(args.listen or ()), connect=tuple(args.connect or ()),
                   zenoh_config=args.zenoh_config, cluster=args.cluster, cpus=args.cpus,
                   gpus=args.gpus, local_pool=args.local_pool,
                   reconnect_grace=args.reconnect_grace,
                   insecure=getattr(args, "insecure", False),
                   accept_tokens=tuple(getattr(args, "accept_token", None) or ()),
                   sandbox=args.sandbox, sandbox_share=shares(args.sandbox_share),
                   runtime=args.runtime, container_engine=args.container_engine,
                   log_limit=args.log_limit)

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
                            ("--sandbox", self.sandbox),
                            ("--runtime", self.runtime),
                            ("--container-engine", self.container_engine),
                            ("--log-limit", self.log_limit)):
            if value != getattr(d, flag[2:].replace("-", "_")):
                out += [flag, str(value)]
        out += [arg for d in self.sandbox_share for arg in ("--sandbox-share", d)]
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


def saved_options(home: Path) -> ServerOptions | None:
    """The options the last explicit start saved in ``home``; None when none were saved.

    Raises:
        UsageError: the file is unreadable or holds options the server does not take.
    """
    path = Home(home).server_options
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


def remember(home: Path, options: ServerOptions) -> list[str]:
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
    path = Home(home).server_options
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


_LOCAL_PROTOCOLS = ("unixsock-stream", "unixpipe")


def network_listeners(listen: tuple[str, ...] | list[str]) -> list[str]:
    """The endpoints of ``listen`` that other machines could reach (not loopback or a socket).

    Loopback is a loopback IP address (``127.0.0.0/8``, ``::1``) or the exact name
    ``localhost``; any other name (``127.example.com`` too) may resolve anywhere.
    """
    return [endpoint for endpoint in listen if not _is_local(endpoint)]


def _is_local(endpoint: str) -> bool:
    proto, _, rest = endpoint.partition("/")
    if proto in _LOCAL_PROTOCOLS:
        return True
    address = rest.split("?", 1)[0].split("#", 1)[0]  # zenoh's endpoint config and metadata
    host = address.rpartition(":")[0]
    if host.startswith("[") and host.endswith("]"):
        host = host[1:-1]
    if host.lower() == "localhost":
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False


def check_listeners(listen: tuple[str, ...] | list[str], zenoh_config: str | None, *,
                    insecure: bool) -> None:
    """Refuse a network listener without zenoh authentication, unless ``insecure``.

    Authentication means user/password (``transport.auth.usrpwd``) or mutual TLS
    (``transport.link.tls.enable_mtls``) in the zenoh config. With ``insecure``, a warning is
    logged at every start (stderr and ``server.log``).

    Raises:
        UsageError: a network listener, no authentication, no ``--insecure``.
    """
    import logging

    from osmo.transport.zenoh_link import authenticates

    exposed = network_listeners(listen)
    if not exposed or authenticates(zenoh_config):
        return
    what = ", ".join(exposed)
    if insecure:
        logging.getLogger("osmo.server").warning(
            "INSECURE: listening on %s without zenoh authentication (--insecure): anyone who "
            "can reach it can connect, and API tokens travel in clear over plain TCP", what)
        return
    raise UsageError(
        f"refusing to listen on {what} without authentication: anyone who can reach it "
        "could connect, and API tokens would travel in clear over plain TCP. Give a "
        "--zenoh-config with TLS and mutual TLS (enable_mtls) or user/password (usrpwd); "
        "see README 'Run across machines'. To accept the risk (a trusted network only), add "
        "--insecure")
