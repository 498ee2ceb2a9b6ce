"""A node's network namespace for its sandboxed tasks: the one module that knows slirp4netns.

Why: on the host's network a task reaches every listener on the host's loopback (the
server's API, the zenoh router, a user's database) and the host's abstract Unix sockets.
So every sandboxed task of a node (a server's local pool, or a worker) runs in one network
namespace of the node's own, made once when the pool starts:

- **its own loopback**: the host's ``127.0.0.1``/``::1`` listeners and abstract Unix
  sockets (which belong to a network namespace) are not there. Tasks of the node share this
  loopback, so the tasks of a group reach each other through ``{{host:NAME}}`` as before
  (the local pool's address is ``127.0.0.1``), and ``osmo workflow port-forward`` connects
  to a task's port inside it (:meth:`NodeNetwork.socket`).
- **outbound connectivity** through ``slirp4netns`` (Debian package ``slirp4netns``; what
  rootless podman uses): a user-mode TCP/IP stack that opens the task's connections as
  ordinary sockets of the host, with ``--disable-host-loopback``, so its gateway
  (``10.0.2.2``) does not lead to the host's loopback. The namespace's address is
  ``10.0.2.100``; DNS goes to ``10.0.2.3``, which slirp4netns forwards to the host's
  resolvers (port 53 only). No port of the namespace is published on the host.
  ``--enable-sandbox`` and ``--enable-seccomp`` confine slirp4netns itself.
  Without slirp4netns (or where it cannot run: it needs ``/dev/net/tun``), the namespace has
  its loopback only, and :attr:`NodeNetwork.caveat` says so (each attempt's log shows it).

Why one namespace per node and not one per task: making one and connecting it takes tens
of milliseconds (``bench/bench_sandbox.py``: the keeper and slirp4netns ready), against a
whole sandboxed start of 2–4 ms; joining the node's costs a start about 0.1 ms as root (the
spawning thread's ``setns``) and one ``nsenter`` exec otherwise. Tasks of a group on one
node keep reaching each other on their shared loopback, as ``{{host:NAME}}`` says. The
price: tasks of one node see each other's listeners, as they did on the host's network.

How: a small keeper process (``osmo.runtime.process.netns_keeper``, run as a script) makes the
namespaces and lives in them: the network namespace, and a user namespace for the tasks
(``osmo.runtime.process.sandbox`` says who they are in it). An :class:`Entry` says how a start
joins them: as root, the spawning thread itself enters the network namespace for the
spawn (:func:`entered`: two ``setns`` calls, nothing to exec) and bwrap gets the user
namespace as a descriptor; otherwise ``nsenter`` enters both (``/proc/<keeper>/ns/*``;
the keeper is never reaped while the pool runs, so its pid cannot name another process).
The keeper answers requests for sockets made inside the namespace. It exits when the
pool's end of its socket pair closes, and slirp4netns when its exit pipe does: both end
with the pool's process, however it ends.
"""

from __future__ import annotations

import array
import contextlib
import ctypes
import ipaddress
import os
import select
import shutil
import socket
import subprocess
import sys
import tempfile
import threading
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import IO

from osmo.errors import InfrastructureError

__all__ = ["DNS", "GATEWAY", "SLIRP_PACKAGE", "Entry", "NodeNetwork", "entered"]

SLIRP_PACKAGE = "slirp4netns"
GATEWAY = "10.0.2.2"
"""The namespace's gateway (slirp4netns); it does not lead to the host's loopback."""
DNS = "10.0.2.3"
"""The namespace's name server (slirp4netns forwards it to the host's resolvers)."""

_KEEPER = Path(__file__).with_name("netns_keeper.py")
_READY_TIMEOUT = 15.0
_MTU = 65520  # slirp4netns' largest: fewer, larger packets through the user-mode stack
_CLONE_NEWNET = 0x40000000  # os.setns is Python 3.12+
_libc = ctypes.CDLL(None, use_errno=True)


@dataclass(frozen=True)
class Entry:
    """How a start joins a node's namespaces (:meth:`NodeNetwork.entry`).

    Attributes:
        prefix: argv to run before the sandbox (``nsenter``, when osmo is not root).
        netns_fd: osmo as root: the network namespace the spawning thread enters...
        host_netns_fd: ...and the one it returns to (:func:`entered`).
        userns_fd: osmo as root: the tasks' user namespace, for bwrap (-1: none).
        resolv_conf: a file to show as ``/etc/resolv.conf`` (the host's names a name server
            on its loopback, which the namespace cannot reach), or None.
    """

    prefix: tuple[str, ...] = ()
    netns_fd: int = -1
    host_netns_fd: int = -1
    userns_fd: int = -1
    resolv_conf: str | None = None


@contextlib.contextmanager
def entered(entry: Entry) -> Iterator[None]:
    """While inside, the calling thread (only it) is in ``entry``'s network namespace.

    Processes it starts meanwhile begin there; sockets it makes meanwhile belong there.

    Raises:
        OSError: the namespace cannot be entered.
    """
    if entry.netns_fd < 0:
        yield
        return
    _setns(entry.netns_fd)
    try:
        yield
    finally:
        _setns(entry.host_netns_fd)  # cannot fail for root; if it did, the thread is unusable


def _setns(fd: int) -> None:
    if _libc.setns(fd, _CLONE_NEWNET) != 0:
        errno = ctypes.get_errno()
        raise OSError(errno, f"cannot enter a network namespace: {os.strerror(errno)}")


@dataclass
class NodeNetwork:
    """A running node network namespace (see the module docstring); :meth:`start` makes one.

    Attributes:
        keeper: the keeper process (its pid names the namespaces).
        netns: the path of the network namespace (``/proc/<keeper>/ns/net``).
        userns: the path of the tasks' user namespace (``/proc/<keeper>/ns/user``); when
            osmo is not root it also owns the network namespace.
        caveat: what is missing (no outbound connectivity, and why); empty when nothing is.
    """

    keeper: _Helper
    netns: str
    userns: str
    caveat: str
    _peer: socket.socket
    _slirp: _Helper | None = None
    _exit_w: int = -1
    _fds: list[int] = field(default_factory=list)
    _resolv: str | None = None

    def __post_init__(self) -> None:
        self._lock = threading.Lock()

    @classmethod
    def start(cls, ids: tuple[int, int], *, outbound: bool = True,
              address: str | None = None) -> NodeNetwork:
        """Make the namespaces and connect them (blocks until they are ready).

        ``ids``: when osmo runs as root, the host ``(uid, gid)`` that root of the tasks'
        user namespace is (otherwise it is osmo's own). ``outbound``: connect it through
        slirp4netns (a probe needs only the namespaces). ``address``: the node's address
        as its peers know it (``{{host:NAME}}``), also given to the namespace's loopback
        so that tasks listen on it and reach each other there (an IPv4 address that is
        not a loopback one; anything else is left out).

        Raises:
            InfrastructureError: the namespace cannot be made here (the message says why).
        """
        root = os.geteuid() == 0
        mine, theirs = socket.socketpair(socket.AF_UNIX, socket.SOCK_SEQPACKET)
        try:
            keeper = _Helper.start([sys.executable, "-I", "-S", str(_KEEPER),
                                    str(theirs.fileno()), "root" if root else "user",
                                    *_own_address(address)], theirs.fileno())
        except OSError as exc:
            mine.close()
            raise InfrastructureError(f"cannot start the network namespace keeper: {exc}") from exc
        finally:
            theirs.close()
        answer = _answer(mine)
        if answer != b"ready":
            mine.close()
            err = keeper.stop().strip()
            why = answer.decode(errors="replace").removeprefix("error: ") or err or "no answer"
            raise InfrastructureError(f"cannot make the tasks' network namespace: {why}")
        path = f"/proc/{keeper.proc.pid}/ns"
        net = cls(keeper, f"{path}/net", f"{path}/user", "", mine)
        try:
            if root:
                net._map(ids)
        except OSError as exc:
            net.close()
            raise InfrastructureError(f"cannot map the tasks' user namespace: {exc}") from exc
        if outbound:
            net._connect()
        return net

    def _map(self, ids: tuple[int, int]) -> None:
        """Root of the keeper's user namespace is ``ids`` on the host; keep its descriptors."""
        for name, host_id in (("uid_map", ids[0]), ("gid_map", ids[1])):
            fd = os.open(f"/proc/{self.keeper.proc.pid}/{name}", os.O_WRONLY)
            try:
                os.write(fd, f"0 {host_id} 1\n".encode())
            finally:
                os.close(fd)
        for path in (self.netns, "/proc/thread-self/ns/net", self.userns):
            self._fds.append(os.open(path, os.O_RDONLY | os.O_CLOEXEC))

    def entry(self) -> Entry:
        """How a start joins these namespaces."""
        if self._fds:
            netns, host, userns = self._fds
            return Entry(netns_fd=netns, host_netns_fd=host, userns_fd=userns,
                         resolv_conf=self._resolv)
        nsenter = shutil.which("nsenter") or "nsenter"
        return Entry(prefix=(nsenter, f"--user={self.userns}", f"--net={self.netns}",
                             "--preserve-credentials", "--"), resolv_conf=self._resolv)

    def _connect(self) -> None:
        """Give the namespace outbound connectivity through slirp4netns (or say why not)."""
        slirp = shutil.which("slirp4netns")
        if slirp is None:
            self.caveat = (f"no outbound network for tasks: {SLIRP_PACKAGE} is not installed "
                           f"(apt-get install {SLIRP_PACKAGE})")
            return
        ready_r, ready_w = os.pipe()
        exit_r, self._exit_w = os.pipe()
        os.set_inheritable(self._exit_w, False)
        # Its --enable-sandbox makes only / private before it unmounts the old root: on a
        # host whose /run/netns is a shared mount (podman's), that unmount would reach the
        # host and take podman's container namespaces with it. As root it therefore starts
        # in a mount namespace of its own whose every mount is private; otherwise its
        # namespace is one of the keeper's user namespace, where shared mounts are slaves.
        private = [shutil.which("unshare") or "unshare", "--mount", "--propagation",
                   "private", "--"] if self._fds else []
        argv = [*private, slirp, "--configure", f"--mtu={_MTU}", "--disable-host-loopback",
                "--enable-sandbox", "--enable-seccomp", f"--ready-fd={ready_w}",
                f"--exit-fd={exit_r}"]
        argv += [] if self._fds else [f"--userns-path={self.userns}"]  # it owns the network
        argv += ["--netns-type=path", self.netns, "tap0"]
        try:
            self._slirp = _Helper.start(argv, ready_w, exit_r)
        except OSError as exc:
            self.caveat = f"no outbound network for tasks: cannot start {slirp}: {exc}"
            return
        finally:
            os.close(ready_w)
            os.close(exit_r)
        try:
            ready = select.select([ready_r], [], [], _READY_TIMEOUT)[0] and os.read(ready_r, 1)
        finally:
            os.close(ready_r)
        if not ready:
            lines = [line for line in self._slirp.stop().splitlines() if line.strip()]
            self._slirp = None
            self.caveat = ("no outbound network for tasks: slirp4netns failed"
                           + (f" ({lines[-1].strip()})" if lines else ""))
            return
        self._resolv = _resolv_conf()

    def socket(self, family: socket.AddressFamily, kind: socket.SocketKind) -> socket.socket:
        """A new socket inside the namespace (connect it to reach a task's port).

        Raises:
            OSError: the keeper is gone or cannot make it.
        """
        name = ("tcp" if kind == socket.SOCK_STREAM else "udp") + (
            "6" if family == socket.AF_INET6 else "4")
        with self._lock:  # one request and its answer at a time
            self._peer.send(name.encode())
            data, fds = _receive(self._peer)
        if data != b"ok" or not fds:
            raise OSError(f"the network namespace keeper: {data.decode(errors='replace')}")
        return socket.socket(fileno=fds[0])

    def close(self) -> None:
        """Stop slirp4netns and the keeper (the namespace goes with them); idempotent."""
        if self._exit_w >= 0:
            os.close(self._exit_w)
            self._exit_w = -1
        self._peer.close()
        for helper in (self._slirp, self.keeper):
            if helper is not None:
                helper.stop()
        self._slirp = None
        for fd in self._fds:
            os.close(fd)
        self._fds.clear()
        if self._resolv is not None:
            with contextlib.suppress(OSError):
                os.unlink(self._resolv)
                os.rmdir(os.path.dirname(self._resolv))
            self._resolv = None


def _resolv_conf(host: str = "/etc/resolv.conf") -> str | None:
    """A resolv.conf naming :data:`DNS`, if the host's names a loopback name server.

    (systemd-resolved's 127.0.0.53, a local dnsmasq: unreachable from the namespace.) Its
    search and options lines are kept. None: the host's file serves as it is.
    """
    try:
        lines = Path(host).read_text().splitlines()
    except OSError:
        return None
    servers = [line.split()[1] for line in lines
               if line.startswith("nameserver") and len(line.split()) > 1]
    if not any(_loopback(server) for server in servers):
        return None
    kept = [line for line in lines if line.startswith(("search", "domain", "options"))]
    folder = tempfile.mkdtemp(prefix="osmo-netns-")
    os.chmod(folder, 0o755)
    path = os.path.join(folder, "resolv.conf")
    Path(path).write_text("\n".join([f"nameserver {DNS}", *kept]) + "\n")
    os.chmod(path, 0o644)
    return path


def _own_address(address: str | None) -> list[str]:
    """``[address]`` if it is an IPv4 address the loopback does not have already."""
    try:
        ip = ipaddress.ip_address(address or "")
    except ValueError:
        return []
    return [str(ip)] if ip.version == 4 and not ip.is_loopback and not ip.is_unspecified else []


def _loopback(address: str) -> bool:
    try:
        return ipaddress.ip_address(address.split("%")[0]).is_loopback
    except ValueError:
        return False


def _answer(peer: socket.socket) -> bytes:
    ready = select.select([peer], [], [], _READY_TIMEOUT)[0]
    try:
        return peer.recv(4096) if ready else b""
    except OSError:
        return b""


def _receive(peer: socket.socket) -> tuple[bytes, list[int]]:
    fds = array.array("i")
    data, ancillary, _, _ = peer.recvmsg(4096, socket.CMSG_SPACE(fds.itemsize))
    for level, kind, payload in ancillary:
        if level == socket.SOL_SOCKET and kind == socket.SCM_RIGHTS:
            fds.frombytes(payload[:len(payload) - len(payload) % fds.itemsize])
    return data, list(fds)


@dataclass
class _Helper:
    """A helper process (the keeper, slirp4netns) and the file its messages go to.

    (A pipe nobody reads while it runs could fill up and block it.)
    """

    proc: subprocess.Popen[bytes]
    messages: IO[bytes]

    @classmethod
    def start(cls, argv: list[str], *fds: int) -> _Helper:
        """Start ``argv`` in its own session with ``fds`` (raises OSError)."""
        messages = tempfile.TemporaryFile()
        try:
            proc = subprocess.Popen(argv, stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL,
                                    stderr=messages, pass_fds=fds, start_new_session=True)
        except BaseException:
            messages.close()
            raise
        return cls(proc, messages)

    def stop(self) -> str:
        """Stop it (SIGTERM, then SIGKILL after a second), collect it; its messages."""
        proc = self.proc
        if proc.poll() is None:
            proc.terminate()
            try:
                proc.wait(timeout=1.0)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait()
        if self.messages.closed:
            return ""
        with self.messages:
            self.messages.seek(0)
            return self.messages.read().decode(errors="replace")
