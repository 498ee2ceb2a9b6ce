r"""The pod's side of its data: the init container's fetch and the collector's send-back.

Run in osmo's own image, beside a task's container, never in it::

    python3 -m osmo.runtime.kubernetes.podside fetch   --connect EP --cluster C --node N \
        --attempt ID --ticket /var/run/osmo/fetch --root /osmo-pod
    python3 -m osmo.runtime.kubernetes.podside collect --connect EP --cluster C --node N \
        --attempt ID --ticket /var/run/osmo/collect --root /osmo-pod \
        [--zenoh-config /var/run/osmo/zenoh.json5]

``--root`` is where the pod's data volume (an ``emptyDir``) is mounted in this container; the
task's container mounts parts of it at OSMO's layout. ``--zenoh-config`` is what the side
shows a router that authenticates (its own user, TLS certificates), from the same Secret.
Each side trades its one-time ticket
(a file of the attempt's Secret) for a sealed channel to the node
(``osmo.runtime.kubernetes.podio`` is the node's side):

- ``fetch`` writes the attempt's folders and files under the root (never through a symlink,
  never outside it), each file hashed as it arrives; a file that does not match its sha256
  fails the pod before the task starts, with a message naming it (on stderr, in
  ``/dev/termination-log``, and sent to the node).
- ``collect`` waits until the node saw the task's container end, then lists
  ``<root>/osmo/data/output`` with ingest's symlink policy (``osmo.artifacts.scan``: a
  symlink leaving the folder rejects the output) and sends it, file by file, with each
  file's sha256. The node writes it; a task ended in a way that hands nothing on is not
  collected.

Exit codes: 0 done, 1 the data was refused or did not match, 3 the node cannot be reached.
Imports only osmo's core (zenoh, cryptography): the image needs nothing else.
"""

from __future__ import annotations

import argparse
import base64
import hashlib
import os
import sys
import time
from collections.abc import Sequence
from pathlib import Path

from osmo.artifacts.errors import OutputRejected
from osmo.artifacts.scan import scan
from osmo.errors import NotAuthenticated, OsmoError, ServerUnreachable, UsageError
from osmo.runtime.kubernetes.podio import CHUNK, check_relative, root_of
from osmo.transport.rpc import ApiClient
from osmo.transport.zenoh_link import Link

__all__ = ["OUTPUT", "PATIENCE", "collect", "fetch", "main"]

OUTPUT = "osmo/data/output"
"""The output folder in the pod's data volume (``/osmo/data/output`` in the task's view)."""
_TERMINATION_LOG = Path("/dev/termination-log")
PATIENCE = 900.0
"""Seconds a collector waits for a node that cannot be reached (killed, restarting)."""


class DataError(OsmoError):
    """What the pod received or must send is not what it should be (exit 1)."""


def fetch(api: ApiClient, attempt: str, root: Path) -> int:
    """Fetch the attempt's files under ``root``; the bytes received.

    Raises:
        DataError: a file did not match its digest or size, or a path leaves ``root``.
    """
    listing = api.call("manifest", {"attempt": attempt})
    for folder in listing["dirs"]:
        _make_dirs(root, folder)
    total = 0
    for index, entry in enumerate(listing["files"]):
        name, size, digest = entry["path"], int(entry["size"]), str(entry["digest"])
        _make_dirs(root, name, parents_only=True)
        h = hashlib.sha256()
        fd = os.open(root / name, os.O_WRONLY | os.O_CREAT | os.O_EXCL | os.O_NOFOLLOW
                     | os.O_CLOEXEC, 0o600)
        try:
            offset = 0
            while offset < size:
                data = base64.b64decode(api.call("read", {"attempt": attempt, "index": index,
                                                          "offset": offset})["data"])
                if not data:
                    break
                h.update(data)
                os.write(fd, data)
                offset += len(data)
            os.fchmod(fd, int(entry["mode"]) & 0o755)
        finally:
            os.close(fd)
        if offset != size or "sha256:" + h.hexdigest() != digest:
            raise DataError(f"{name} does not match its digest {digest} (got "
                            f"sha256:{h.hexdigest()}, {offset} of {size} bytes): the input "
                            "was changed on its way to the pod")
        total += size
    api.call("fetched", {"attempt": attempt})
    return total


def collect(api: ApiClient, attempt: str, root: Path, *, max_files: int | None = None,
            patience: float = PATIENCE, pause: float = 1.0) -> int:
    """Send ``root``'s output folder to the node once the task ended; the bytes sent.

    A node that cannot be reached (killed, restarting) is waited for up to ``patience``
    seconds, asked again every ``pause``; a node that came back in a new life (it opened a
    new channel for the ticket: it adopted the pod) gets the whole output again, from the
    start: what it received before died with its previous life.

    Raises:
        DataError: the output holds what cannot be sent (a symlink out of it, a FIFO).
        RemoteError, UsageError, NotAllowed: the node refused it (the message says why).
        ServerUnreachable, NotAuthenticated: the node did not come back in time.
    """
    deadline = time.monotonic() + patience
    said = ""  # the last reason told: once per reason, not once per second of waiting
    while True:
        try:
            return _collect_once(api, attempt, root, max_files)
        except (ServerUnreachable, NotAuthenticated, _Restarted) as exc:
            if time.monotonic() >= deadline:
                raise (exc.cause if isinstance(exc, _Restarted) else exc) from None
            if str(exc) != said:
                said = str(exc)
                print(f"osmo: collect: the node is away ({exc}); asking again until it is "
                      "back", file=sys.stderr)
            time.sleep(pause)


class _Restarted(OsmoError):
    """The node answered on a new channel mid-collection: it restarted (send it all again)."""

    def __init__(self, cause: OsmoError) -> None:
        super().__init__(str(cause))
        self.cause = cause


def _collect_once(api: ApiClient, attempt: str, root: Path, max_files: int | None) -> int:
    """One collection from its ``wait`` to its ``done`` (:func:`collect`)."""
    while True:
        state = api.call("wait", {"attempt": attempt})
        if state["ended"]:
            break
    if not state["collect"]:
        return 0
    folder = root / OUTPUT
    try:
        listed = sorted(scan(str(folder), max_files=max_files)) if folder.is_dir() else []
    except OutputRejected as exc:
        raise DataError(str(exc)) from None
    life = api.channel()  # the node's life that takes the output
    try:
        return _send(api, attempt, listed)
    except OsmoError as exc:
        if not isinstance(exc, ServerUnreachable) and api.channel() is not life:
            raise _Restarted(exc) from None
        raise


def _send(api: ApiClient, attempt: str, listed: list[tuple[str, str, int]]) -> int:
    """Offer ``listed`` (name, real path, size), send each file, then every digest."""
    api.call("offer", {"attempt": attempt,
                       "files": [{"path": name, "size": size} for name, _, size in listed]})
    digests, total = [], 0
    for index, (_name, real, size) in enumerate(listed):
        h = hashlib.sha256()
        with open(real, "rb") as f:
            offset = 0
            while offset < size and (data := f.read(min(CHUNK, size - offset))):
                api.call("put", {"attempt": attempt, "index": index, "offset": offset,
                                 "data": base64.b64encode(data).decode()})
                h.update(data)
                offset += len(data)
        digests.append("sha256:" + h.hexdigest())
        total += offset
    api.call("done", {"attempt": attempt, "digests": digests})
    return total


def _make_dirs(root: Path, name: str, *, parents_only: bool = False) -> None:
    """Make ``root/name`` (or only its parents) folder by folder, never through a symlink."""
    try:
        check_relative(name)
    except UsageError as exc:
        raise DataError(str(exc)) from None
    parts = name.split("/")
    folder = root
    for part in parts[:-1] if parents_only else parts:
        folder = folder / part
        try:
            os.mkdir(folder, 0o755)
        except FileExistsError:
            if folder.is_symlink() or not folder.is_dir():
                raise DataError(f"{name}: {part} is not a folder") from None


def _args(argv: Sequence[str] | None) -> argparse.Namespace:
    p = argparse.ArgumentParser(prog="python -m osmo.runtime.kubernetes.podside")
    p.add_argument("side", choices=("fetch", "collect"))
    p.add_argument("--connect", action="append", required=True, help="the zenoh router")
    p.add_argument("--cluster", default="local")
    p.add_argument("--node", required=True)
    p.add_argument("--attempt", required=True)
    p.add_argument("--ticket", required=True, help="the file holding this side's ticket")
    p.add_argument("--root", required=True, help="where the pod's data volume is mounted")
    p.add_argument("--zenoh-config", help="a zenoh client config (the router's user, TLS)")
    p.add_argument("--timeout", type=float, default=30.0)
    return p.parse_args(argv)


def main(argv: Sequence[str] | None = None) -> int:
    """Run one side; its exit code (see the module docstring)."""
    args = _args(argv)
    link: Link | None = None
    api: ApiClient | None = None
    try:
        ticket = Path(args.ticket).read_text().strip()
        link = Link.client(args.connect, args.cluster, config_file=args.zenoh_config)
        api = ApiClient(link, timeout=args.timeout, token=ticket, root=root_of(args.node))
        root = Path(args.root)
        done = (fetch if args.side == "fetch" else collect)(api, args.attempt, root)
        print(f"osmo: {args.side}: {done} bytes", file=sys.stderr)
        return 0
    except OSError as exc:
        return _fail(api, args, f"{args.side}: {exc.strerror or exc}: {exc.filename or ''}", 1)
    except OsmoError as exc:
        code = exc.exit_code if exc.exit_code in (1, 3) else 1
        return _fail(api, args, f"{args.side}: {exc}", code)
    finally:
        if link is not None:
            link.close()


def _fail(api: ApiClient | None, args: argparse.Namespace, message: str, code: int) -> int:
    """Say why on stderr, in the termination log and to the node (when it can be reached)."""
    print(f"osmo: {message}", file=sys.stderr)
    try:
        _TERMINATION_LOG.write_text(message[:4000])
    except OSError:
        pass
    if api is not None:
        try:
            api.call("failed", {"attempt": args.attempt, "message": message[:2000]},
                     timeout=5.0)
        except OsmoError:
            pass
    return code


def _entry() -> None:
    sys.exit(main())


if __name__ == "__main__":
    _entry()
