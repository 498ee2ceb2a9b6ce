"""Warm runners inside containers: attempts forked from a runner in a container of their image.

The pool's side of ``osmo.runtime.process.warm_runner``'s container mode. Per
:class:`ContainerWarmKey` (the image id, the task type and its version, the type's folders,
the network) :class:`ContainerWarmRunners` keeps one runner container:
``ENGINE run --rm --preserve-fds=1 ...`` in the foreground (stdin and stdout from and to
``/dev/null``), whose pid 1 is ``python3 -m osmo.runtime.process.warm_runner 3 TYPE VERSION
PATHS...`` on the image's own interpreter, fd 3 its end of a ``SOCK_SEQPACKET`` pair with
the pool. What it owns:

- **the runner container**: osmo's code bound read-only at ``/osmo/lib/osmo`` (and the
  ``osmo_plugins`` package, if installed, at ``/osmo/lib/osmo_plugins``), custom type
  folders at ``/osmo/types/N``, ``PYTHONPATH`` those then ``/osmo/lib``; labels
  ``osmo.owner=OWNER`` and ``osmo.warm=1`` (a restarted node's ``clean_orphans`` by owner
  removes it); the name ``osmo-warm-<hash of owner and key>-<random>`` (a runner killed a
  moment ago may still hold its name). It runs as root in the
  container with no capability and ``no-new-privileges``: the user namespace it makes
  for its attempts (every uid mapped to itself) is mapped by the pool (``map``), which
  has the ``CAP_SYS_ADMIN`` that needs; it holds no credential and no attempt's data.
- **its death**: the engine's client gets ``PR_SET_PDEATHSIG``; the runner exits when its
  socket's peer is gone without a ``retire`` (the pool was killed), and its exit ends the
  container (it is pid 1) and every attempt (their pid namespaces are below its own);
  ``--rm`` is done by the engine's own exit command even when the client is gone. Idle
  (``OSMO_WARM_IDLE``), it exits by itself, and the container with it.
- **each attempt** (:meth:`ContainerWarmRunners.start`, from a ``ContainerRun``): detached
  clones (``osmo.runtime.process.mounts.detached``) of its mounts' host folders, read-only
  per ``Mount.read_only``, moved by the attempt's pid 1 to ``Mount.target``; its ``/proc``
  mounted here from the context its pid 1 sends on a relay socket; its argv and its whole
  environment (``run.env`` and ``run.secret_env``) only on its own request pipe, written
  after the fork. ``workdir`` (or ``/``) and ``user`` (``UID:GID``, default root) too.
- **per-attempt limits**: a cgroup of its own below the runner container's (cgroup v1:
  ``memory`` and ``cpu`` hierarchies; the container's path from ``/proc/RUNNER/cgroup``)
  with ``memory.limit_in_bytes`` = ``run.memory`` and a CFS quota of ``run.cpus``; the
  attempt's host pid (from its pidfd) is moved in *before* its request is written (its
  process forks only after), and the cgroup is removed at ``release``. A cgroup that cannot
  be made fails the start (``StartError``): never an attempt without its limits. cgroup v2
  would need a leaf for the runner itself (no process may sit in an inner cgroup that has
  controllers enabled for children): the runner would move itself to ``RUNNER/runner``
  and each attempt get ``RUNNER/attempt-PID`` with ``memory.max`` and ``cpu.max``; not
  done here (this machine has v1): on v2 :meth:`ContainerWarmRunners.can_limit` says no,
  and the runtime starts an attempt with limits cold.

Kill, reap and release keep ``osmo.runtime.api.ProcessHandle``'s contract as
``osmo.runtime.process.warm`` does (SIGTERM/SIGKILL through the pidfd, then the group;
``128+N``; ``lost`` when the runner died under the attempt).
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import logging
import os
import signal
import socket
import subprocess
import tempfile
import threading
import time
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path

from osmo.runtime.api import StartError
from osmo.runtime.container.engine import ContainerEngine
from osmo.runtime.container.layout import RUNNER_PATHS, CoverError, code_mounts
from osmo.runtime.container.run import ContainerRun, mount_option
from osmo.runtime.process import mounts
from osmo.runtime.process.groups import die_with_parent
from osmo.runtime.process.proctable import process_start_time, start_clock
from osmo.runtime.process.warm import (
    DEFAULT_IDLE,
    ForkedProcess,
    RunnerInfo,
    WarmHandle,
    changed,
    close_attempt,
    mount_proc,
    pidfd_pid,
    private_pipe,
    reap_attempt,
    receive,
    resident,
    signal_attempt,
)
from osmo.runtime.process.warm_runner import (
    CONTAINER_VARIABLE,
    IDLE_VARIABLE,
    MAP,
    MAPPED,
    READY,
    RETIRE,
)
from osmo.tasktypes.registry import shipped_packages

__all__ = ["ContainerWarmHandle", "ContainerWarmKey", "ContainerWarmRunners", "WARM_LABEL",
           "WarmRun"]

_log = logging.getLogger("osmo.worker.pool")

WARM_LABEL = "osmo.warm"
"""The label every runner container carries (``1``)."""
_READY_TIMEOUT = 300.0
_REPLY_TIMEOUT = 30.0
_CGROUP_ROOT = Path("/sys/fs/cgroup")
_CFS_PERIOD = 100_000
_ID_MAP = "0 0 4294967295"  # every uid and gid to itself


@dataclass(frozen=True)
class ContainerWarmKey:
    """What one runner container serves.

    Attributes:
        image: the image (its id: a tag moved meanwhile changes nothing).
        type: the task type as the spec writes it (empty: a runner of commands).
        version: the version it was submitted against (None: any).
        paths: the host folders a custom type is imported from.
        network: the runner container's ``--network`` (None: the engine's default).
        entry: an installed type's ``module:attr`` (its entry point's), which the runner
            imports: the image has osmo's code, not the node's package metadata.
    """

    image: str
    type: str
    version: str | None = None
    paths: tuple[str, ...] = ()
    network: str | None = None
    entry: str | None = None


@dataclass(frozen=True)
class WarmRun:
    """A launch's ``run`` when its attempt starts in a runner container (the runtime's).

    Attributes:
        key: its runner's.
        run: the container it would be cold: its mounts, environment, user and limits are
            the attempt's.
    """

    key: ContainerWarmKey
    run: ContainerRun


@dataclass(eq=False)
class ContainerWarmHandle(WarmHandle):
    """An attempt forked in a runner container.

    Attributes:
        cgroups: the folders of its own cgroups (removed at release).
        container: its runner container's name.
    """

    cgroups: tuple[str, ...] = ()
    container: str = ""


@dataclass(eq=False)
class _Runner:
    key: ContainerWarmKey
    name: str
    popen: subprocess.Popen[bytes]
    sock: socket.socket
    main: int  # the runner's host pid (below the container's pid 1 and its waiter)
    cgroups: dict[str, Path]  # controller -> the container's cgroup folder
    sources: dict[str, int] = field(default_factory=dict)  # a custom type's files: mtimes
    lock: threading.Lock = field(default_factory=threading.Lock)
    started: int = 0
    running: set[int] = field(default_factory=set)  # its attempts' pids, until reaped
    broken: bool = False

    def alive(self) -> bool:
        return not self.broken and self.popen.poll() is None

    def stale(self) -> bool:
        """Whether a source file of its custom type changed since it imported it."""
        return changed(self.sources)

    def retire(self) -> None:
        """No more attempts: it exits once those running ended."""
        self.broken = True
        with self.lock:
            with contextlib.suppress(OSError):
                self.sock.send(RETIRE)
            with contextlib.suppress(OSError):
                self.sock.shutdown(socket.SHUT_RDWR)
            self.sock.close()


class ContainerWarmRunners:
    """The runner containers of one node (see the module docstring).

    Args:
        engine: the engine (podman: ``--preserve-fds``).
        owner: the node's ``osmo.owner`` label value.
        idle: seconds a runner waits for its next attempt before it (and its container) ends.
        max_rss: bytes of resident memory over which a runner is retired (None: no limit).
        labels: more labels for the runner containers.
        hidden: what no task may see (osmo's homes, token files): covered where a custom
            type's folder holds it (``osmo.runtime.container.layout.code_mounts``); read at
            each runner's start.
        cover: an empty folder, bound over a hidden folder (None: a type folder holding one
            starts cold).
    """

    def __init__(self, engine: ContainerEngine, owner: str, *, idle: float = DEFAULT_IDLE,
                 max_rss: int | None = None, labels: Mapping[str, str] | None = None,
                 hidden: Sequence[Path] = (), cover: Path | None = None) -> None:
        self.engine, self.owner, self.idle, self.max_rss = engine, owner, idle, max_rss
        self.labels = {**(labels or {}), "osmo.owner": owner, WARM_LABEL: "1"}
        self.hidden, self._cover = hidden, cover
        self._runners: dict[ContainerWarmKey, _Runner] = {}
        self._refused: dict[ContainerWarmKey, str] = {}
        self._starting: dict[ContainerWarmKey, threading.Lock] = {}
        self._lock = threading.Lock()
        self._closed = False

    # ------------------------------------------------------------ runners

    def ready(self, key: ContainerWarmKey) -> bool:
        """Whether attempts of ``key`` can start warm now; starts its container (blocks)."""
        return self._runner(key) is not None

    def refused(self, key: ContainerWarmKey) -> str | None:
        """Why ``key`` cannot run warm (None: it can, or was not tried)."""
        return self._refused.get(key)

    def runner(self, key: ContainerWarmKey) -> tuple[str, int] | None:
        """The live runner of ``key``: its container's name and the runner's host pid."""
        with self._lock:
            found = self._runners.get(key)
        return (found.name, found.main) if found is not None and found.alive() else None

    def _runner(self, key: ContainerWarmKey) -> _Runner | None:
        with self._lock:
            if self._closed or key in self._refused:
                return None
            starting = self._starting.setdefault(key, threading.Lock())
        with starting:  # one start per key; other keys, reaps and listings go on meanwhile
            with self._lock:
                found = self._runners.get(key)
            if found is not None and found.alive() and not self._worn(found):
                return found
            if found is not None:
                with self._lock:
                    if self._runners.get(key) is found:
                        del self._runners[key]
                found.retire()
            made = self._spawn(key)  # blocks while the runner imports its type
            with self._lock:
                if made is not None and not self._closed:
                    self._runners[key] = made
                    return made
            if made is not None:  # the node closed meanwhile
                made.retire()
            return None

    def _worn(self, runner: _Runner) -> bool:
        """Whether ``runner`` must be retired: over its memory, or its sources changed."""
        return (self.max_rss is not None and resident(runner.main) > self.max_rss) or runner.stale()

    def has(self, key: ContainerWarmKey, path: str) -> bool:
        """Whether ``key``'s live runner container has ``path`` (not a symbolic link)."""
        found = self.runner(key)
        if found is None or not path.startswith("/"):
            return False
        shown = f"/proc/{found[1]}/root{path}"  # the runner's root, seen from here
        return os.path.lexists(shown) and not os.path.islink(shown)

    def can_limit(self, key: ContainerWarmKey) -> bool:
        """Whether ``key``'s live runner can give its attempts cpu and memory limits."""
        with self._lock:
            found = self._runners.get(key)
        return found is not None and {"memory", "cpu"} <= set(found.cgroups)

    def runners(self) -> list[RunnerInfo]:
        """The live runner containers, as ``osmo resource list`` shows them."""
        self.sweep()
        with self._lock:
            found = [runner for runner in self._runners.values() if runner.alive()]
        return [RunnerInfo(f"{runner.key.type}@{runner.key.version}" if runner.key.version
                           else runner.key.type, runner.main, resident(runner.main),
                           runner.started, len(runner.running)) for runner in found]

    def name(self, key: ContainerWarmKey) -> str:
        """The stem of ``key``'s runner containers' names.

        Each adds a suffix of its own: a runner killed a moment ago may still hold its name.
        """
        digest = hashlib.sha256(json.dumps([self.owner, key.image, key.type, key.version,
                                            key.paths, key.network, key.entry]).encode())
        return f"osmo-warm-{digest.hexdigest()[:12]}"

    def argv(self, key: ContainerWarmKey, name: str) -> list[str]:
        """The engine's ``run`` argv of ``key``'s runner container ``name`` (its socket at fd 3).

        Raises:
            CoverError: a type folder lies in what no task may see.
        """
        engine = self.engine.engine
        binds = code_mounts(shipped_packages(), key.paths, self.hidden, self._cover)
        types = [RUNNER_PATHS.types.format(i) for i in range(len(key.paths))]
        entry = json.dumps(["python3"]) if engine.name == "podman" else "python3"
        return [engine.path, "run", "--rm", "--preserve-fds=1", f"--name={name}",
                "--pull=never", "--user=0:0", "--cap-drop=all",
                "--security-opt=no-new-privileges",
                *(f"--label={k}={v}" for k, v in sorted(self.labels.items())),
                *([f"--network={key.network}"] if key.network else []),
                *(f"--mount={mount_option(m)}" for m in binds),
                f"--env=PYTHONPATH={':'.join([*types, RUNNER_PATHS.code])}",
                "--env=PYTHONDONTWRITEBYTECODE=1", f"--env={IDLE_VARIABLE}={self.idle:g}",
                f"--env={CONTAINER_VARIABLE}=1", f"--entrypoint={entry}", key.image,
                "-m", "osmo.runtime.process.warm_runner", "3", key.entry or key.type,
                key.version or "-", *types]

    def _spawn(self, key: ContainerWarmKey) -> _Runner | None:
        ours, theirs = socket.socketpair(socket.AF_UNIX, socket.SOCK_SEQPACKET)
        fd = theirs.fileno()
        deathsig = die_with_parent()

        def child() -> None:  # the runner's end at fd 3, as --preserve-fds=1 passes it
            deathsig()
            os.dup2(fd, 3)

        name = f"{self.name(key)}-{os.urandom(4).hex()}"
        try:
            argv = self.argv(key, name)
        except CoverError as exc:
            ours.close()
            theirs.close()
            self._refuse(key, str(exc))
            return None
        # the client's stderr: a file, never a pipe (a client that writes to a closed or full
        # pipe, a syslog warning say, would end or stall while its container runs on)
        err = tempfile.TemporaryFile()
        try:
            popen = subprocess.Popen(argv, env=self.engine.env, cwd="/",
                                     stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL,
                                     stderr=err, start_new_session=True,
                                     preexec_fn=child, pass_fds=(3,))
        except (OSError, subprocess.SubprocessError) as exc:
            ours.close()
            err.close()
            self._refuse(key, f"cannot start a warm runner container: {exc}")
            return None
        finally:
            theirs.close()
        try:
            reply, fds = receive(ours, _READY_TIMEOUT)
            if reply == MAP and fds:
                _map_users(fds[0])
                ours.send(MAPPED)
                reply = receive(ours, _READY_TIMEOUT)[0]
            else:
                for fd in fds:
                    os.close(fd)
        except OSError as exc:
            reply = f"error: {exc}".encode()
        if not reply.startswith(READY):
            ours.close()
            why = reply.decode("utf-8", "replace").removeprefix("error: ")
            with contextlib.suppress(ProcessLookupError):
                popen.kill()
            popen.wait()
            err.seek(0)
            said = err.read()[-2000:].decode("utf-8", "replace").strip()
            err.close()
            self._refuse(key, why or said or "the warm runner container exited while importing")
            return None
        err.close()  # (the client keeps its own descriptor of the unlinked file)
        main = self._runner_pid(name)
        return _Runner(key, name, popen, ours, main, _cgroups(main),
                       _host_sources(reply[len(READY):], key.paths))

    def _runner_pid(self, name: str) -> int:
        """The runner's host pid: the child of the container's pid 1 (which waits for it)."""
        top = int(self.engine.call("inspect", "--format={{.State.Pid}}", name).strip() or 0)
        pid = top
        for _ in range(1):
            deadline = time.monotonic() + 5
            while True:
                try:
                    children = Path(f"/proc/{pid}/task/{pid}/children").read_text().split()
                except OSError:
                    children = []
                if children or time.monotonic() > deadline:
                    break
                time.sleep(0.01)
            pid = int(children[0]) if children else pid
        return pid

    def _refuse(self, key: ContainerWarmKey, why: str) -> None:
        _log.info("image %s, type %s runs cold: %s", key.image, key.type, why)
        self._refused[key] = why

    def sweep(self) -> None:
        """Forget (and reap) runners whose container ended."""
        with self._lock:
            for key, runner in list(self._runners.items()):
                if runner.popen.poll() is not None:
                    del self._runners[key]
                    runner.retire()

    def close(self) -> None:
        """The node stops: every runner container is ended, with what still runs in it."""
        with self._lock:
            self._closed = True
            found = list(self._runners.values())
            self._runners.clear()
        for runner in found:
            runner.broken = True
            with runner.lock:  # a closed socket without ``retire``: it exits at once
                with contextlib.suppress(OSError):
                    runner.sock.shutdown(socket.SHUT_RDWR)
                runner.sock.close()
            try:
                runner.popen.wait(timeout=30)
            except subprocess.TimeoutExpired:
                runner.popen.kill()
                runner.popen.wait()

    # ------------------------------------------------------------ attempts

    def start(self, key: ContainerWarmKey, run: ContainerRun) -> ContainerWarmHandle:
        """Fork ``run``'s attempt in ``key``'s runner container (started if need be).

        Only ``run``'s argv, env, secret_env, mounts, workdir, user, cpus and memory are
        used: the image, network and names are the runner container's.

        Raises:
            StartError: no runner, a mount or its limits cannot be set up, or the runner
                failed to fork it.
        """
        if not run.argv:
            raise StartError("a warm container attempt needs a command")
        why = "no warm runner"
        for _ in range(2):  # a runner that died since: once more, on a new one
            runner = self._runner(key)
            if runner is None:
                why = self.refused(key) or why
                break
            try:
                return self._fork(runner, run)
            except OSError as exc:
                why = str(exc)
                if runner.alive():  # the attempt's own set-up failed, not its runner
                    raise StartError(f"cannot start '{run.argv[0]}' warm: {exc}") from exc
                with self._lock:
                    if self._runners.get(key) is runner:
                        del self._runners[key]
                runner.retire()
        raise StartError(f"cannot start '{run.argv[0]}' warm: {why}")

    def _fork(self, runner: _Runner, run: ContainerRun) -> ContainerWarmHandle:
        made: list[int] = []
        groups: list[str] = []
        relay: socket.socket | None = None
        pidfd = -1
        try:
            out_r, out_w = private_pipe(made)
            err_r, err_w = private_pipe(made)
            req_r, req_w = private_pipe(made)
            status_r, status_w = private_pipe(made)
            binds: list[list[object]] = []
            clones: list[int] = []
            for mount in run.mounts:
                fd = mounts.detached(str(mount.source), readonly=mount.read_only)
                made.append(fd)
                clones.append(fd)
                binds.append([mount.target, not mount.read_only, mount.source.is_dir()])
            ours, theirs = socket.socketpair(socket.AF_UNIX, socket.SOCK_SEQPACKET)
            relay = ours
            made.append(theirs.detach())
            request = b"fork " + json.dumps({"binds": binds, "cwd": run.workdir or "/",
                                             "user": _user(run.user)}).encode()
            started_at = start_clock()
            passed = [out_w, err_w, req_r, status_w, made[-1], *clones]
            with runner.lock:
                if runner.broken:
                    raise OSError("the runner retired")
                try:
                    socket.send_fds(runner.sock, [request], passed)
                    reply, fds = receive(runner.sock, _REPLY_TIMEOUT)
                except OSError:
                    runner.broken = True  # its socket failed: it is gone, or going
                    raise
            for fd in passed:
                os.close(fd)
                made.remove(fd)
            if not reply or not fds or not reply.isdigit():
                for fd in fds:
                    os.close(fd)
                runner.broken = runner.broken or not reply
                raise OSError(f"the runner answered {reply[:200]!r}")
            pidfd = fds[0]
            pid = pidfd_pid(pidfd)
            if not pid:
                raise OSError("the attempt ended before it started")
            if run.memory or run.cpus:  # before its process is forked (after its /proc)
                groups = _limit(runner.cgroups, pid, run.memory, run.cpus)
            mount_proc(relay)
            relay.close()
            relay = None
            _write_request(req_w, run)
            made.remove(req_w)
        except BaseException:
            if pidfd >= 0:
                with contextlib.suppress(OSError):
                    signal.pidfd_send_signal(pidfd, signal.SIGKILL)
                os.close(pidfd)
            if relay is not None:
                relay.close()
            for fd in made:
                os.close(fd)
            _remove_groups(groups)
            raise
        for fd in (out_r, err_r, status_r):
            os.set_blocking(fd, False)
        runner.started += 1
        runner.running.add(pid)
        handle = ContainerWarmHandle(pid, status_r, out_r, err_r, ForkedProcess(pid), pidfd=pidfd,
                                     runner=runner.main, cgroups=tuple(groups),
                                     container=runner.name)
        handle.started_at = process_start_time(pid) or started_at
        return handle

    def kill(self, handle: ContainerWarmHandle, *, force: bool = False) -> None:
        """SIGTERM (SIGKILL when ``force``) to the attempt, through its pidfd and its group.

        Its pid 1 takes no SIGTERM from outside (a namespace's init without a handler):
        the group, which its process shares, brings it there. Never raises.
        """
        signal_attempt(handle, force=force)

    def reap(self, handle: ContainerWarmHandle) -> int:
        """The exit code the runner reported (``lost`` when it died first: 137)."""
        with self._lock:
            running = [runner.running for runner in self._runners.values()]
        return reap_attempt(handle, running, "its warm runner container ended while it ran")

    def release(self, handle: ContainerWarmHandle) -> None:
        """Close its descriptors and remove its cgroups (idempotent)."""
        close_attempt(handle)
        _remove_groups(handle.cgroups)
        handle.cgroups = ()


def _map_users(pidfd: int) -> None:
    """Map every uid and gid to itself in the user namespace of the runner ``pidfd`` names.

    Only a process with ``CAP_SYS_ADMIN`` and ``CAP_SETUID`` in the container's user
    namespace (the host's, for a rootful engine) may write such maps: this one. Closes
    ``pidfd``.
    """
    try:
        pid = pidfd_pid(pidfd)
        if not pid:
            raise OSError("the runner ended before its user namespace was mapped")
        for name in ("uid_map", "gid_map"):
            Path(f"/proc/{pid}/{name}").write_text(_ID_MAP)
    finally:
        os.close(pidfd)


def _host_sources(data: bytes, paths: Sequence[str]) -> dict[str, int]:
    """The runner's sources (container paths under ``/osmo/types/N``: mtimes) on the host."""
    try:
        sources = json.loads(data or b"{}")
    except ValueError:
        return {}
    out: dict[str, int] = {}
    for index, folder in enumerate(paths):
        shown = RUNNER_PATHS.types.format(index) + "/"
        for path, mtime in sources.items() if isinstance(sources, dict) else ():
            if isinstance(path, str) and path.startswith(shown) and isinstance(mtime, int):
                out[os.path.join(os.path.realpath(folder), path[len(shown):])] = mtime
    return out


def _user(user: str | None) -> list[int]:
    """``UID:GID`` (numbers only: the image's names are not looked up) as [uid, gid]."""
    if not user:
        return [0, 0]
    uid, _, gid = user.partition(":")
    if not uid.isdigit() or (gid and not gid.isdigit()):
        raise OSError(f"a warm container attempt's user must be UID:GID, not {user!r}")
    return [int(uid), int(gid or uid)]


def _write_request(fd: int, run: ContainerRun) -> None:
    """The attempt's argv, folder and environment, for its process only; closes ``fd``."""
    data = json.dumps({"argv": list(run.argv), "cwd": run.workdir or "/",
                       "env": {**run.env, **run.secret_env}}).encode()
    try:
        with os.fdopen(fd, "wb") as pipe:
            pipe.write(data)
    except BrokenPipeError:
        pass


def _cgroups(pid: int) -> dict[str, Path]:
    """The cgroup v1 folders (``memory``, ``cpu``) of ``pid`` (empty: none found, or v2)."""
    found: dict[str, Path] = {}
    try:
        lines = Path(f"/proc/{pid}/cgroup").read_text().splitlines()
    except OSError:
        return found
    for line in lines:
        _, controllers, path = line.split(":", 2)
        for controller in controllers.split(","):
            folder = _CGROUP_ROOT / controller / path.lstrip("/")
            if controller in ("memory", "cpu") and folder.is_dir():
                found[controller] = folder
    return found


def _limit(cgroups: Mapping[str, Path], pid: int, memory: int | None,
           cpus: float | None) -> list[str]:
    """Make ``pid``'s own cgroups below the runner's with these limits, move it in.

    Raises:
        OSError: a cgroup cannot be made, limited or entered (what is made is removed).
    """
    wanted = {"memory": memory, "cpu": cpus}
    made: list[str] = []
    try:
        for controller, value in wanted.items():
            if not value:
                continue
            parent = cgroups.get(controller)
            if parent is None:
                raise OSError(f"no cgroup v1 '{controller}' hierarchy for the runner container "
                              "(cgroup v2 is not supported for warm container limits)")
            folder = parent / f"osmo-attempt-{pid}"
            folder.mkdir()
            made.append(str(folder))
            if controller == "memory":
                (folder / "memory.limit_in_bytes").write_text(str(int(value)))
            else:
                (folder / "cpu.cfs_period_us").write_text(str(_CFS_PERIOD))
                (folder / "cpu.cfs_quota_us").write_text(str(max(int(value * _CFS_PERIOD),
                                                                 1000)))
            (folder / "cgroup.procs").write_text(str(pid))
    except OSError as exc:
        _remove_groups(made)
        raise OSError(f"cannot limit the attempt in its own cgroup: {exc}") from exc
    return made


def _remove_groups(folders: Sequence[str]) -> None:
    """Remove attempts' cgroups once their processes are gone (a few tries: exits settle)."""
    for folder in folders:
        for _ in range(50):
            try:
                os.rmdir(folder)
                break
            except FileNotFoundError:
                break
            except OSError:
                time.sleep(0.02)
        else:
            _log.warning("cannot remove the cgroup %s", folder)
