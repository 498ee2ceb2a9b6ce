"""Where osmo keeps its state, and how a client finds its server.

``OSMO_HOME`` (default: ``$XDG_DATA_HOME/osmo``, else ``~/.local/share/osmo``) holds the
state store, the attempts' folders, the running server's address and lock, and more: its
layout is :mod:`osmo.layout`. A free ``server.lock`` means no server runs.

The server endpoint a client uses: ``--server`` > ``OSMO_SERVER`` > ``server.json``.
"""

from __future__ import annotations

import fcntl
import json
import os
import socket
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from osmo.layout import Home

__all__ = [
    "DEFAULT_CLUSTER",
    "DEFAULT_PORT",
    "ServerInfo",
    "free_port",
    "home_dir",
    "lock_is_held",
    "read_server_info",
    "write_json_atomic",
]

DEFAULT_PORT = 7447
"""The server's zenoh port when nothing else listens on it."""

DEFAULT_CLUSTER = "local"
"""The key prefix (``osmo/<cluster>/...``) a server, its workers and clients share unless
told another."""


def home_dir(home: str | os.PathLike[str] | None = None) -> Path:
    """The osmo home folder (created if missing)."""
    if home is None:
        home = os.environ.get("OSMO_HOME")
    if home is None:
        xdg = os.environ.get("XDG_DATA_HOME") or str(Path.home() / ".local" / "share")
        home = Path(xdg) / "osmo"
    path = Path(home).expanduser().resolve()
    path.mkdir(parents=True, exist_ok=True)
    return path


@dataclass(frozen=True)
class ServerInfo:
    """What a running local server wrote about itself in ``server.json``."""

    endpoint: str
    pid: int
    cluster: str
    started_at: float


def write_json_atomic(path: Path, data: dict[str, Any]) -> None:
    """Write JSON to a temp file and rename it over ``path`` (never a partial file)."""
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    tmp.write_text(json.dumps(data, indent=2))
    os.replace(tmp, path)


def read_server_info(home: Path) -> ServerInfo | None:
    """The server.json of ``home``, or None if absent or unreadable."""
    try:
        data = json.loads(Home(home).server_info.read_text())
        return ServerInfo(data["endpoint"], int(data["pid"]), data["cluster"],
                          float(data["started_at"]))
    except (OSError, ValueError, KeyError):
        return None


def lock_is_held(home: Path) -> bool:
    """True if a server process holds ``server.lock`` of ``home`` (it is alive)."""
    try:
        fd = os.open(Home(home).server_lock, os.O_RDWR | os.O_CREAT, 0o644)
    except OSError:
        return False
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError:
        return True
    else:
        fcntl.flock(fd, fcntl.LOCK_UN)
        return False
    finally:
        os.close(fd)


def free_port(preferred: int = DEFAULT_PORT, host: str = "127.0.0.1") -> int:
    """``preferred`` if nothing listens on it, else a free port chosen by the OS."""
    for port in (preferred, 0):
        with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as sock:
            try:
                sock.bind((host, port))
            except OSError:
                continue
            return int(sock.getsockname()[1])
    raise OSError("no free TCP port on loopback")


PROFILE_KEYS = ("server", "cluster", "zenoh-config")
"""What ``osmo profile set`` accepts."""


def read_profile(home: Path) -> dict[str, str]:
    """The saved client profile (``OSMO_HOME/profile.json``); empty when none."""
    try:
        data = json.loads(Home(home).profile.read_text())
    except (OSError, ValueError):
        return {}
    return {str(k): str(v) for k, v in data.items() if k in PROFILE_KEYS} if isinstance(
        data, dict) else {}


def write_profile(home: Path, profile: dict[str, str]) -> None:
    """Save the client profile atomically."""
    home.mkdir(parents=True, exist_ok=True)
    write_json_atomic(Home(home).profile, profile)


def host_id() -> str:
    """This machine's identity for this boot (machine id + boot id), to spot a same-host peer.

    ``OSMO_HOST_ID`` overrides it: processes on one machine that should behave as separate
    machines (tests, benchmarks of the network path) set different values.
    """
    if os.environ.get("OSMO_HOST_ID"):
        return os.environ["OSMO_HOST_ID"]
    parts = []
    for path in ("/etc/machine-id", "/proc/sys/kernel/random/boot_id"):
        try:
            parts.append(Path(path).read_text().strip())
        except OSError:
            parts.append("?")
    return ":".join(parts)
