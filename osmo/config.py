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
import stat
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from osmo.errors import NotAuthenticated
from osmo.layout import Home

__all__ = [
    "DEFAULT_CLUSTER",
    "DEFAULT_PORT",
    "ServerInfo",
    "free_port",
    "home_path",
    "lock_is_held",
    "open_home",
    "private_file",
    "read_json_private",
    "read_profile",
    "read_server_info",
    "write_json_atomic",
    "write_profile",
]

DEFAULT_PORT = 7447
"""The server's zenoh port when nothing else listens on it."""

DEFAULT_CLUSTER = "local"
"""The key prefix (``osmo/<cluster>/...``) a server, its workers and clients share unless
told another."""


def home_path(home: str | os.PathLike[str] | None = None) -> Path:
    """The osmo home folder's absolute path, symlinks resolved; nothing is created or checked.

    ``home`` if given, else ``OSMO_HOME``, else ``osmo`` in the XDG data folder.
    """
    if home is None:
        home = os.environ.get("OSMO_HOME")
    if home is None:
        xdg = os.environ.get("XDG_DATA_HOME") or str(Path.home() / ".local" / "share")
        home = Path(xdg) / "osmo"
    return Path(home).expanduser().resolve()


def open_home(home: str | os.PathLike[str] | None = None, *, worker: bool = False) -> Home:
    """Where a home path becomes a :class:`~osmo.layout.Home` (the one place).

    The server, the SDK and the CLI open the osmo home (:func:`home_path`): made 0700 if
    missing, and checked to be yours. A home that other users may read or enter (wider than
    0700) is made 0700, with a one-line notice on stderr: it holds the state store,
    credentials and the admin token. Everything below them is handed this object.

    With ``worker``, a remote worker's home: ``home`` as given (absolute), else ``worker`` in
    the osmo home (the worker makes it when it starts).

    Raises:
        NotAuthenticated: the osmo home belongs to another OS user (exit 3).
    """
    if worker:
        path = Path(home).absolute() if home is not None else open_home().root / "worker"
    else:
        path = home_path(home)
        path.mkdir(mode=0o700, parents=True, exist_ok=True)
        _check_owner(path)
    return Home(path)


def _check_owner(path: Path) -> None:
    """Refuse another user's home; make ours 0700 if it is wider."""
    try:
        st = path.stat()
    except PermissionError:
        st = None
    if st is None or st.st_uid != os.geteuid():
        owner = f"uid {st.st_uid}" if st is not None else "another user"
        raise NotAuthenticated(
            f"OSMO_HOME {path} belongs to {owner}, not to you (uid {os.geteuid()}): its server "
            "answers only its owner; use your own OSMO_HOME, or a token the owner created for "
            "you (`osmo token create NAME --role user`) with --server and --token")
    if stat.S_IMODE(st.st_mode) & 0o077:
        os.chmod(path, 0o700)
        print(f"osmo: {path} was open to other users (mode {stat.S_IMODE(st.st_mode):o}); "
              "made it 0700", file=sys.stderr)


def private_file(path: Path) -> None:
    """Make ``path`` readable and writable by its owner only (if it exists)."""
    try:
        if stat.S_IMODE(path.stat().st_mode) & 0o077:
            os.chmod(path, 0o600)
    except FileNotFoundError:
        pass


@dataclass(frozen=True)
class ServerInfo:
    """What a running local server wrote about itself in ``server.json``.

    ``warnings``: what it warned about at start (``osmo server start`` repeats them).
    """

    endpoint: str
    pid: int
    cluster: str
    started_at: float
    warnings: tuple[str, ...] = ()


def write_json_atomic(path: Path, data: dict[str, Any]) -> None:
    """Write JSON to a temp file and rename it over ``path`` (never a partial file).

    The file is its owner's only (0600): some of these hold a token.
    """
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_TRUNC | os.O_CLOEXEC, 0o600)
    with os.fdopen(fd, "w") as f:
        f.write(json.dumps(data, indent=2))
    os.replace(tmp, path)


def read_json_private(path: Path, max_bytes: int = 4 << 20) -> dict[str, Any]:
    """The JSON object in ``path``, never read through a symlink nor past ``max_bytes``.

    Raises:
        OSError: it cannot be opened (missing, a symlink).
        ValueError: it is not JSON, not an object, or too large.
    """
    fd = os.open(path, os.O_RDONLY | os.O_NOFOLLOW | os.O_CLOEXEC)
    with os.fdopen(fd, "rb") as f:
        raw = f.read(max_bytes + 1)
    if len(raw) > max_bytes:
        raise ValueError(f"{path.name} is too large")
    data = json.loads(raw)
    if not isinstance(data, dict):
        raise ValueError(f"{path.name} is not an object")
    return data


def read_server_info(home: Home) -> ServerInfo | None:
    """The server.json of ``home``, or None if absent or unreadable."""
    try:
        data = json.loads(home.server_info.read_text())
        return ServerInfo(data["endpoint"], int(data["pid"]), data["cluster"],
                          float(data["started_at"]),
                          tuple(str(w) for w in data.get("warnings") or ()))
    except (OSError, ValueError, KeyError):
        return None


def lock_is_held(home: Home) -> bool:
    """True if a server process holds ``server.lock`` of ``home`` (it is alive)."""
    try:
        fd = os.open(home.server_lock, os.O_RDWR | os.O_CREAT, 0o600)
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


PROFILE_KEYS = ("server", "cluster", "zenoh-config", "token")
"""What ``osmo profile set`` accepts."""


def read_profile(home: Home) -> dict[str, str]:
    """The saved client profile (``OSMO_HOME/profile.json``); empty when none."""
    try:
        data = json.loads(home.profile.read_text())
    except (OSError, ValueError):
        return {}
    return {str(k): str(v) for k, v in data.items() if k in PROFILE_KEYS} if isinstance(
        data, dict) else {}


def write_profile(home: Home, profile: dict[str, str]) -> None:
    """Save the client profile atomically."""
    home.root.mkdir(parents=True, exist_ok=True)
    write_json_atomic(home.profile, profile)


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
