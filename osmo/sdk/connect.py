"""Finding, starting and stopping the local server; opening an API connection to a server.

The endpoint used: an explicit ``server`` argument > ``OSMO_SERVER`` > the saved profile
(``osmo profile set server ENDPOINT``, kept in ``OSMO_HOME/profile.json``) > the home's
``server.json`` (the local server's Unix socket, ``OSMO_HOME/server.sock``). With none of
them and ``autostart`` on, a server is started in the background for the home (``python -m
osmo.server.app``, its own session, output in ``server.log``), with the options the last
explicit start saved in the home (``osmo.options.saved_options``), and the call waits
until it answers.

The token sent with every request: an explicit ``token`` > ``OSMO_TOKEN`` > the profile's
``token`` > the home owner's admin token (``OSMO_HOME/auth/admin.token``), this last one only
to the home's own server (its socket or an endpoint it listens on), never to another.
"""

from __future__ import annotations

import os
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

from osmo.config import (
    DEFAULT_CLUSTER,
    ServerInfo,
    lock_is_held,
    open_home,
    read_profile,
    read_server_info,
)
from osmo.errors import InfrastructureError, ServerUnreachable
from osmo.layout import Home
from osmo.options import ServerOptions, saved_options
from osmo.transport.listeners import check_listeners
from osmo.transport.rpc import ApiClient
from osmo.transport.zenoh_link import Link

__all__ = ["Connection", "running_options", "server_status", "start_server", "stop_server"]

START_TIMEOUT = 60.0  # a server's start takes 1-2 s; minutes of load can stretch it


class Connection:
    """An open API connection (a zenoh client session plus the request helper).

    ``home``: the osmo home it was opened from (the client's own artifact store lives there).
    """

    def __init__(self, endpoint: str, cluster: str = DEFAULT_CLUSTER,
                 zenoh_config: str | None = None, token: str | None = None, *,
                 home: Home) -> None:
        self.endpoint = endpoint
        self.home = home
        self.link = Link.client([endpoint], cluster, config_file=zenoh_config)
        self.api = ApiClient(self.link, token=token)

    def close(self) -> None:
        """Close the session."""
        self.link.close()


def _wait_ready(home: Home, proc: subprocess.Popen[bytes] | None, timeout: float) -> ServerInfo:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        info = read_server_info(home)
        if info is not None and (proc is None or info.pid == proc.pid) and lock_is_held(home):
            return info
        if proc is not None and proc.poll() is not None:
            log = home.server_log.read_text(errors="replace")[-2000:]
            raise InfrastructureError(f"the osmo server exited at start:\n{log}")
        time.sleep(0.02)  # start-up only: waiting for another process to write its file
    if proc is not None and proc.poll() is None:  # still starting: it serves once ready
        raise InfrastructureError(f"the osmo server (pid {proc.pid}) is still starting after "
                                  f"{timeout:.0f}s; run the command again, or see "
                                  f"{home.server_log}")
    raise InfrastructureError(f"the osmo server did not become ready within {timeout:.0f}s; "
                              f"see {home.server_log}")


def start_server(home: str | os.PathLike[str] | None = None,
                 options: ServerOptions | None = None) -> ServerInfo:
    """Start a background server for ``home`` with ``options`` unless one runs.

    Args:
        home: the osmo home (default: ``OSMO_HOME`` / XDG data folder).
        options: how it runs; None: the options saved by the last explicit start, else the
            defaults.

    Returns:
        the running server's info (``server.json``), once it answers.

    Raises:
        UsageError: ``options`` is None and the saved options are damaged.
    """
    return _start(open_home(home), options)


def _start(home: Home, options: ServerOptions | None) -> ServerInfo:
    if options is not None:
        check_listeners(options.listen, options.zenoh_config, insecure=options.insecure)
    if lock_is_held(home):
        return _wait_ready(home, None, START_TIMEOUT)
    if options is None:
        options = saved_options(home) or ServerOptions()
        check_listeners(options.listen, options.zenoh_config, insecure=options.insecure)
    args = [sys.executable, "-m", "osmo.server.app", "--home", str(home.root),
            *options.to_argv()]
    log_fd = os.open(home.server_log, os.O_WRONLY | os.O_CREAT | os.O_APPEND, 0o600)
    with open(log_fd, "ab") as out:
        proc = subprocess.Popen(args, stdin=subprocess.DEVNULL, stdout=out, stderr=out,
                                start_new_session=True, close_fds=True)
    return _wait_ready(home, proc, START_TIMEOUT)


def server_status(home: str | os.PathLike[str] | None = None) -> ServerInfo | None:
    """The running local server's info, or None if none runs for ``home``."""
    return _status(open_home(home))


def _status(home: Home) -> ServerInfo | None:
    return read_server_info(home) if lock_is_held(home) else None


def stop_server(home: str | os.PathLike[str] | None = None, timeout: float = 30.0) -> int | None:
    """Stop the local server of ``home``; return its pid, or None when none was running.

    SIGTERM first; a server still running ``timeout`` seconds later (a shutdown stuck behind
    a huge workflow) gets SIGKILL, which loses nothing: the next start recovers from the
    store as after any crash.
    """
    import signal

    layout = open_home(home)
    info = _status(layout)
    if info is None:
        return None
    os.kill(info.pid, signal.SIGTERM)
    deadline = time.monotonic() + timeout
    while lock_is_held(layout) and time.monotonic() < deadline:
        time.sleep(0.05)
    while _running(info.pid) and time.monotonic() < deadline:  # the lock goes just before exit
        time.sleep(0.01)
    if _running(info.pid):
        try:
            os.kill(info.pid, signal.SIGKILL)
        except ProcessLookupError:
            return info.pid
        deadline = time.monotonic() + 10
        while _running(info.pid) and time.monotonic() < deadline:
            time.sleep(0.01)
    return info.pid


def _running(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    try:  # a zombie (exited, not yet reaped by its parent) counts as stopped
        return Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0] != "Z"
    except (OSError, IndexError):
        return False


def connect(server: str | None = None, home: str | os.PathLike[str] | None = None,
            *, autostart: bool = True, token: str | None = None) -> Connection:
    """Open a connection to the server chosen as described in the module docstring."""
    layout = open_home(home)
    profile = read_profile(layout)
    token = token or os.environ.get("OSMO_TOKEN") or profile.get("token")
    endpoint = server or os.environ.get("OSMO_SERVER") or profile.get("server")
    if endpoint:
        if token is None and endpoint in _local_endpoints(layout):
            token = _owner_token(layout)
        return Connection(endpoint, os.environ.get("OSMO_CLUSTER") or
                          profile.get("cluster") or DEFAULT_CLUSTER, profile.get("zenoh-config"),
                          token, home=layout)
    info = _status(layout)
    if info is None:
        if not autostart:
            raise ServerUnreachable(f"no osmo server running for {layout.root} "
                                    "(start one with `osmo server start`)")
        info = _start(layout, None)
    return Connection(info.endpoint, info.cluster, _local_config(layout),
                      token or _owner_token(layout), home=layout)


def _owner_token(home: Home) -> str | None:
    """The home owner's admin token, if the home's server made one."""
    try:
        return home.admin_token.read_text().strip() or None
    except OSError:
        return None


def _local_endpoints(home: Home) -> list[str]:
    """Every endpoint the home's running server listens on (its socket first)."""
    data = _server_json(home)
    out = [str(e) for e in [data.get("endpoint"), *data.get("endpoints", [])] if e]
    wildcard = {"tcp/0.0.0.0:": "tcp/127.0.0.1:", "tcp/[::]:": "tcp/[::1]:"}
    return out + [e.replace(w, local, 1) for e in out for w, local in wildcard.items()
                  if e.startswith(w)]


def _local_config(home: Home) -> str | None:
    """The zenoh config the home's server was started with.

    The same credentials serve the local CLI, unless ``OSMO_ZENOH_CONFIG`` says otherwise.
    """
    if os.environ.get("OSMO_ZENOH_CONFIG"):
        return None  # Link.client takes it from the environment
    value = _server_json(home).get("zenoh_config")
    return str(value) if value else None


def running_options(home: str | os.PathLike[str] | None = None) -> list[str] | None:
    """The options (as flags) the home's running server was started with; None: not known."""
    layout = open_home(home)
    if not lock_is_held(layout):
        return None
    value = _server_json(layout).get("options")
    return [str(v) for v in value] if isinstance(value, list) else None


def _server_json(home: Home) -> dict[str, Any]:
    import json

    try:
        data = json.loads(home.server_info.read_text())
    except (OSError, ValueError):
        return {}
    return data if isinstance(data, dict) else {}
