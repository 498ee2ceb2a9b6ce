"""Warm runners, the pool's side: typed tasks forked from a process that imported their type.

A typed task (``type:``) runs ``python -m osmo.tasktypes.runner CONTEXT``, which imports its
type's module and what that imports (gymnasium and MuJoCo: about a second; torch: four) at
every attempt. :class:`WarmRunners` keeps, per :class:`WarmKey` (the type and its version, the
interpreter, the type's folders and ``PYTHONPATH``; a node has its own), a runner
(``osmo.runtime.process.warm_runner``) that imported it once, and starts each attempt as a
fork of it. What it owns:

- **a runner's life**: started by :meth:`WarmRunners.ready` when the first attempt of its
  kind is prepared (the I/O thread waits for its import: that attempt costs what a cold one
  does, the next ones a fork); kept while attempts of its kind come; retired when idle
  (``idle`` seconds with no attempt: the runner exits by itself), when its resident memory
  is over ``max_rss`` bytes, when a source file of a custom type changed, and replaced when it
  died. A runner is spawned in its own session with ``PR_SET_PDEATHSIG``: it dies with the
  pool's process (a kill -9 of the server or worker), and its attempts die with it.
- **what a runner holds**: the pool's base environment (``env``) and the type's
  ``PYTHONPATH``, nothing of any attempt. An attempt's argv, folder and complete
  environment (its credentials' variables included) go through a pipe of its own whose read
  end is passed with the fork request: only the forked child reads it.
- **an attempt's start, kill and exit** (:class:`WarmHandle`): its stdout and stderr are
  pipes made here, their write ends passed to the runner (``SCM_RIGHTS``) and on to the
  child; the child leads its own session and process group (before the runner answers);
  the runner answers with a pidfd of it. ``kill`` signals the child through its pidfd and
  then its group (never a reused pid); ``exit_fd`` is a status pipe on which the runner writes the
  exit code (``128+N``: killed by signal N) once it reaped the child. A runner that died
  before it did so leaves the attempt ``lost`` (its child died with it).
- **its exit reaped**: a runner that exited (idle, or retired while attempts of it still
  ran) is reaped by :meth:`WarmRunners.sweep`, which the pool calls every few seconds, and
  by each look at the runners; none is left a zombie of a long-lived server or worker.
- **what ``osmo resource list`` shows**: :meth:`WarmRunners.runners`.

Which tasks run warm is the process runtime's choice (``osmo.runtime.process.runtime``):
typed tasks, unless the pool's ``--warm off`` or the task's ``warm: false``. A type whose
import fails, or starts threads, runs cold (its attempts then report the failure as a cold
runner does).

**Sandboxed runners** (``WarmKey.sandboxed``; the sandboxed runtime's choice,
``osmo.runtime.process.sandboxed``: only types osmo ships, only a root osmo): the runner
is started in a bubblewrap sandbox of its own (:meth:`WarmRunners.enclose`,
``Sandbox.runner_argv``: osmo's homes hidden, ``CAP_SYS_ADMIN`` kept in the node's user
namespace; ``SANDBOXED_VARIABLE`` set: each of its children is a new pid namespace's pid 1).
For each attempt the pool sends, with the fork request, its view's layout
(``Sandbox.layout``: exactly what bubblewrap would mount for it cold), a detached clone of
each of its folders (``osmo.runtime.process.mounts``; the runner cannot reach them) and a
relay socket, on which the attempt's pid 1 sends a proc context that the pool mounts for
it. The child's pid is the runner's namespace's: the pool takes its own from the pidfd.

What a warm start does not change: the user (the pool's), the environment (the attempt's
own, replacing the runner's), the log, the kill and timeout rules, the exit codes. What it
does change: variables the type's module reads *at import* come from the pool's
environment, not the task's (a task that needs its own opts out with ``warm: false``); and
every attempt of a runner starts from the same memory image (shared copy-on-write with
the runner and its other attempts until written; read-only to each of them).
"""

from __future__ import annotations

import contextlib
import json
import logging
import os
import select
import signal
import socket
import subprocess
import sys
import threading
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path

from osmo.runtime.api import Launch, ProcessHandle, StartError
from osmo.runtime.process import mounts
from osmo.runtime.process.groups import check_runnable, die_with_parent
from osmo.runtime.process.proctable import process_start_time, start_clock
from osmo.runtime.process.sandbox import Sandbox, View
from osmo.runtime.process.warm_runner import (
    IDLE_VARIABLE,
    READY,
    RUNNER_MODULE,
    SANDBOXED_VARIABLE,
)

__all__ = ["DEFAULT_IDLE", "ForkedProcess", "RunnerInfo", "WarmHandle", "WarmKey",
           "WarmRunners", "WarmStart", "changed", "close_attempt", "commands_key", "mount_proc",
           "pidfd_pid", "private_pipe", "reap_attempt", "receive", "resident", "signal_attempt",
           "warm_key"]

_log = logging.getLogger("osmo.worker.pool")

DEFAULT_IDLE = 60.0
"""Seconds a runner waits for its next attempt before it exits."""
_READY_TIMEOUT = 300.0  # an import of torch and its friends on a loaded machine
_REPLY_TIMEOUT = 30.0
_REPLY_MAX = 65536
BINDS_MAX = 200
"""The most folders a sandboxed warm attempt's view binds (more: it starts cold)."""


@dataclass(frozen=True)
class WarmKey:
    """What one runner serves: attempts of one type, in one environment.

    Attributes:
        type: the type as the spec writes it (``sim.rollout``, ``tasks:count``).
        version: the version it was submitted against (None: unknown).
        paths: the folders a custom type is imported from.
        python: the interpreter.
        pythonpath: the attempt's ``PYTHONPATH`` (``osmo.worker.launch.runner_env``).
        sandboxed: the runner is a sandbox of its own, each attempt a fork of it in its own
            view (:meth:`WarmRunners.enclose`; only for a type osmo ships).
    """

    type: str
    version: str | None
    paths: tuple[str, ...]
    python: str
    pythonpath: str
    sandboxed: bool = False


@dataclass(frozen=True)
class WarmStart:
    """A launch's ``run`` when it starts from a warm runner (the runtime sets it).

    Attributes:
        key: its runner's.
        view: a sandboxed attempt's view (what bubblewrap would show it cold).
    """

    key: WarmKey
    view: View | None = None


@dataclass(frozen=True)
class RunnerInfo:
    """One live runner, as ``osmo resource list`` shows it.

    Attributes:
        type: its task type (``ref@version`` when known).
        pid: its process id.
        rss: its resident memory in bytes (what its attempts share copy-on-write).
        started: attempts it started.
        running: attempts of it still running.
    """

    type: str
    pid: int
    rss: int
    started: int
    running: int

    def to_dict(self) -> dict[str, object]:
        """As JSON."""
        return {"type": self.type, "pid": self.pid, "rss": self.rss, "started": self.started,
                "running": self.running}


class ForkedProcess(subprocess.Popen[bytes]):
    """Stands for a runner's child where a ``Popen`` is expected: it spawns nothing.

    The child is the runner's, not ours: its exit code comes from the runner's status pipe
    (:meth:`WarmRunners.reap` sets ``returncode``); ``wait`` and ``poll`` only report it.
    """

    def __init__(self, pid: int) -> None:  # noqa: D107 - no Popen.__init__: nothing to spawn
        self.pid, self.returncode, self.args = pid, None, ()
        self.stdin = self.stdout = self.stderr = None
        self._child_created = False

    def poll(self) -> int | None:
        """The exit code once reaped (never waits)."""
        return self.returncode

    def wait(self, timeout: float | None = None) -> int:
        """The exit code once reaped (never waits)."""
        return -1 if self.returncode is None else self.returncode


@dataclass(eq=False)
class WarmHandle(ProcessHandle):
    """A started attempt forked from a runner (``exit_fd``: the runner's status pipe).

    Attributes:
        pidfd: a pidfd of the child (from the runner), for signals that never reach a reused
            pid.
        runner: the pid of the runner it was forked from.
    """

    pidfd: int = -1
    runner: int = 0


@dataclass(eq=False)
class _Runner:
    key: WarmKey
    popen: subprocess.Popen[bytes]
    sock: socket.socket
    sources: dict[str, int]
    lock: threading.Lock = field(default_factory=threading.Lock)
    started: int = 0
    running: set[int] = field(default_factory=set)
    broken: bool = False
    main: int = 0  # the runner's own pid (a sandboxed one's is below bubblewrap's)

    def alive(self) -> bool:
        return not self.broken and self.popen.poll() is None

    def rss(self) -> int:
        return resident(self.main or self.popen.pid)

    def stale(self) -> bool:
        return changed(self.sources)

    def retire(self) -> None:
        """No more attempts: it exits once those running ended.

        Under its lock: a fork request being sent on its socket (any thread) is never cut by
        the close, nor sent to a descriptor that took the closed one's number.
        """
        self.broken = True
        with self.lock:
            with contextlib.suppress(OSError):
                self.sock.shutdown(socket.SHUT_RDWR)
            self.sock.close()


class WarmRunners:
    """The warm runners of one node (see the module docstring).

    Args:
        env: the pool's base environment (``osmo.worker.taskenv.base_env``), a runner's own.
        idle: seconds a runner waits for its next attempt before it exits.
        max_rss: bytes of resident memory over which a runner is retired (None: no limit).
    """

    def __init__(self, env: Mapping[str, str], *, idle: float = DEFAULT_IDLE,
                 max_rss: int | None = None) -> None:
        self._env, self.idle, self.max_rss = dict(env), idle, max_rss
        self._runners: dict[WarmKey, _Runner] = {}
        self._refused: dict[WarmKey, str] = {}
        self._lock = threading.Lock()
        self._starting: dict[WarmKey, threading.Lock] = {}
        self._retired: list[_Runner] = []  # dropped while still running: reaped by sweep()
        self._closed = False
        self._sandbox: Sandbox | None = None
        self._hidden: Sequence[Path] = ()

    def enclose(self, sandbox: Sandbox, hidden: Sequence[Path]) -> None:
        """Make sandboxed runners (keys with ``sandboxed``) in ``sandbox``, hiding ``hidden``.

        ``sandbox`` must be a root osmo's that joined the node's namespaces; ``hidden`` is
        read at each runner's start (the runtime's list of osmo's homes).
        """
        self._sandbox, self._hidden = sandbox, hidden

    # ------------------------------------------------------------ runners

    def ready(self, key: WarmKey) -> bool:
        """Whether attempts of ``key`` can start warm now; starts its runner (blocks).

        False when its type cannot run warm (its import failed or started threads: it runs
        cold, and its cold runner says why) or the pool is closing.
        """
        return self._runner(key) is not None

    def refused(self, key: WarmKey) -> str | None:
        """Why ``key`` runs cold (None: it does not, or was not tried)."""
        return self._refused.get(key)

    def _runner(self, key: WarmKey) -> _Runner | None:
        with self._lock:
            if self._closed or key in self._refused:
                return None
            starting = self._starting.setdefault(key, threading.Lock())
        with starting:
            with self._lock:
                found = self._runners.get(key)
            if found is not None and found.alive() and not self._worn(found):
                return found
            if found is not None:
                self._drop(found)
            made = self._spawn(key)
            with self._lock:
                if made is None or self._closed:
                    if made is not None:
                        made.retire()
                    return None
                self._runners[key] = made
            return made

    def _worn(self, runner: _Runner) -> bool:
        """Whether ``runner`` must be retired: over its memory, or its sources changed."""
        return (self.max_rss is not None and runner.rss() > self.max_rss) or runner.stale()

    def _drop(self, runner: _Runner) -> None:
        with self._lock:
            if self._runners.get(runner.key) is runner:
                del self._runners[runner.key]
        runner.retire()
        if runner.popen.poll() is None:  # its attempts still run: it exits after them
            with self._lock:
                self._retired.append(runner)

    def sweep(self) -> None:
        """Reap every runner that exited: idle ones (forgotten here) and retired ones."""
        with self._lock:
            found = list(self._runners.values())
            retired, self._retired = self._retired, []
        for runner in found:
            if runner.popen.poll() is not None:
                self._drop(runner)
        still = [runner for runner in retired if runner.popen.poll() is None]
        with self._lock:
            self._retired += still

    def _spawn(self, key: WarmKey) -> _Runner | None:
        ours, theirs = socket.socketpair(socket.AF_UNIX, socket.SOCK_SEQPACKET)
        env = {**self._env, "PYTHONPATH": key.pythonpath, IDLE_VARIABLE: f"{self.idle:g}",
               **({SANDBOXED_VARIABLE: "1"} if key.sandboxed else {})}
        argv = [key.python, "-m", "osmo.runtime.process.warm_runner", str(theirs.fileno()),
                key.type, key.version or "-", *key.paths]
        sandbox = self._sandbox
        passed: tuple[int, ...] = (theirs.fileno(),)
        try:
            if key.sandboxed:
                if sandbox is None:
                    raise OSError("no sandbox for a sandboxed runner")
                argv, passed = sandbox.runner_argv(argv, self._hidden), (*passed, *sandbox.fds)
            with sandbox.entered() if key.sandboxed and sandbox else contextlib.nullcontext():
                popen = subprocess.Popen(argv, cwd="/", env=env, stdin=subprocess.DEVNULL,
                                         stdout=subprocess.DEVNULL,
                                         stderr=subprocess.DEVNULL, start_new_session=True,
                                         preexec_fn=die_with_parent(), pass_fds=passed)
        except (OSError, subprocess.SubprocessError) as exc:
            ours.close()
            self._refuse(key, f"cannot start a warm runner: {exc}")
            return None
        finally:
            theirs.close()
        try:
            reply = receive(ours, _READY_TIMEOUT)[0]
        except OSError as exc:
            reply = f"error: {exc}".encode()
        if not reply.startswith(READY):
            ours.close()
            popen.kill()
            popen.wait()
            self._refuse(key, reply.decode("utf-8", "replace").removeprefix("error: ")
                         or "the warm runner exited while importing")
            return None
        try:
            sources = json.loads(reply[len(READY):] or b"{}")
        except ValueError:
            sources = {}
        runner = _Runner(key, popen, ours, sources)
        if key.sandboxed:  # bubblewrap, its pid 1, the runner's parent, then the runner
            runner.main = _descendant(popen.pid, 3)
            why = self._trial(runner)
            if why:
                runner.retire()
                popen.kill()
                popen.wait()
                self._refuse(key, f"a sandboxed attempt cannot be set up here: {why}")
                return None
        return runner

    def _trial(self, runner: _Runner) -> str:
        """Why a sandboxed runner cannot make an attempt's view here (empty: it can).

        One attempt of ``true`` with no folders of its own, before any task's: a host that
        refuses one of the child's mounts then runs that type cold instead of failing it.
        """
        launch = Launch(("true",), Path("/"), {"PATH": "/usr/bin:/bin"},
                        run=WarmStart(runner.key, View(hidden=tuple(self._hidden), readonly=(),
                                                       writable=(), cwd=Path("/"))))
        try:
            handle = self._fork(runner, launch)
        except OSError as exc:
            return str(exc)
        try:
            os.set_blocking(handle.exit_fd, True)
            select.select([handle.exit_fd], [], [], _REPLY_TIMEOUT)
            code = self.reap(handle)
            err = b""
            with contextlib.suppress(OSError):
                err = os.read(handle.stderr_fd, 4096)
        finally:
            self.release(handle)
        runner.started = 0
        runner.running.clear()
        return "" if code == 0 else (err.decode("utf-8", "replace").strip() or f"exit {code}")

    def _refuse(self, key: WarmKey, why: str) -> None:
        _log.info("task type %s runs cold: %s", key.type, why)
        with self._lock:
            self._refused[key] = why

    def runners(self) -> list[RunnerInfo]:
        """The live runners (a runner that exited is reaped and forgotten here)."""
        self.sweep()
        with self._lock:
            found = list(self._runners.values())
        out = []
        for runner in found:
            if not runner.alive():  # exited since the sweep: the next one reaps it
                continue
            kind = runner.key.type + (f"@{runner.key.version}" if runner.key.version else "")
            out.append(RunnerInfo(kind, runner.popen.pid, runner.rss(), runner.started,
                                  len(runner.running)))
        return out

    def close(self) -> None:
        """The node stops: every runner is retired and, with what still runs of it, killed."""
        with self._lock:
            self._closed = True
            found = [*self._runners.values(), *self._retired]
            self._runners.clear()
            self._retired.clear()
        for runner in found:
            runner.retire()
            with contextlib.suppress(ProcessLookupError):
                runner.popen.kill()
            runner.popen.wait()

    # ------------------------------------------------------------ attempts

    def start(self, key: WarmKey, launch: Launch) -> ProcessHandle:
        """Fork ``launch``'s attempt from ``key``'s runner (a new one if it is gone).

        Raises:
            StartError: the command cannot be started (not found, no working folder), or no
                runner could fork it.
        """
        if list(launch.argv[1:3]) != ["-m", RUNNER_MODULE]:
            check_runnable(launch.argv[0] if launch.argv else "", launch.cwd, launch.env)
        why = "no warm runner"
        for _ in range(2):  # a runner that just retired or died: once more on a new one
            runner = self._runner(key)
            if runner is None:
                break
            try:
                return self._fork(runner, launch)
            except OSError as exc:
                why = f"its warm runner failed: {exc.strerror or exc}"
                self._drop(runner)
        raise StartError(f"cannot start '{launch.argv[0]}': {self.refused(key) or why}")

    def _fork(self, runner: _Runner, launch: Launch) -> WarmHandle:
        made: list[int] = []
        try:
            out_r, out_w = private_pipe(made)
            err_r, err_w = private_pipe(made)
            req_r, req_w = private_pipe(made)
            status_r, status_w = private_pipe(made)
            request, extra, relay = b"fork", list[int](), None
            if isinstance(launch.run, WarmStart) and launch.run.view is not None:
                request, extra, relay = self._enclosed(launch.run.view, made)
            started_at = start_clock()
            passed = [out_w, err_w, req_r, status_w, *extra]
            with runner.lock:
                socket.send_fds(runner.sock, [request], passed)
                reply, fds = receive(runner.sock, _REPLY_TIMEOUT)
            for fd in passed:
                os.close(fd)
                made.remove(fd)
            if not reply or not fds or not reply.isdigit():
                for fd in fds:
                    os.close(fd)
                raise OSError(f"the runner answered {reply[:200]!r}")
            pid, pidfd = int(reply), fds[0]
            if relay is not None:  # its pid is the runner's namespace's: ours is the pidfd's
                pid = pidfd_pid(pidfd) or pid
                mount_proc(relay)
                relay.close()
            _write_request(req_w, launch)
            made.remove(req_w)
        except BaseException:
            for fd in made:
                os.close(fd)
            raise
        for fd in (out_r, err_r, status_r):
            os.set_blocking(fd, False)
        runner.started += 1
        runner.running.add(pid)
        handle = WarmHandle(pid, status_r, out_r, err_r, ForkedProcess(pid), pidfd=pidfd,
                            runner=runner.popen.pid)
        # the child was forked before the request (the runner's spare): its own start time
        handle.started_at = process_start_time(pid) or started_at
        return handle

    def _enclosed(self, view: View, made: list[int]) -> tuple[bytes, list[int], socket.socket]:
        """A sandboxed fork request: its layout, its folders' detached mounts, its relay.

        The mounts are clones of the attempt's folders made here (the runner cannot reach
        them: osmo's home is hidden from it); missing ones are left out, as bubblewrap's
        ``--bind-try`` does. The relay is the socket on which its pid 1 asks for ``/proc``.
        """
        sandbox = self._sandbox
        if sandbox is None:
            raise OSError("no sandbox for a sandboxed warm start")
        layout = sandbox.layout(view)
        binds: list[list[object]] = []
        clones: list[int] = []
        for path, writable in layout.binds:
            try:
                fd = mounts.detached(path, readonly=not writable)
            except FileNotFoundError:
                continue
            made.append(fd)
            clones.append(fd)
            binds.append([path, writable, os.path.isdir(path)])
        ours, theirs = socket.socketpair(socket.AF_UNIX, socket.SOCK_SEQPACKET)
        relay = theirs.detach()
        made.append(relay)
        request = json.dumps({"hidden": layout.hidden, "masked": layout.masked,
                              "binds": binds, "cwd": layout.cwd}).encode()
        return b"fork " + request, [relay, *clones], ours

    def kill(self, handle: WarmHandle, *, force: bool = False) -> None:
        """SIGTERM (SIGKILL when ``force``) to the child, then to its group. Never raises."""
        signal_attempt(handle, force=force)

    def reap(self, handle: WarmHandle) -> int:
        """The exit code the runner reported; what is left of the group is killed.

        A runner that died before reporting leaves the attempt ``lost`` (137).
        """
        with self._lock:
            running = [runner.running for runner in self._runners.values()]
        return reap_attempt(handle, running, "its warm runner ended while it ran")

    def release(self, handle: WarmHandle) -> None:
        """Close its descriptors (idempotent)."""
        close_attempt(handle)


def changed(sources: Mapping[str, int]) -> bool:
    """Whether a file of ``sources`` (path: mtime in ns) changed or went since."""
    for path, mtime in sources.items():
        try:
            if os.stat(path).st_mtime_ns != mtime:
                return True
        except OSError:
            return True
    return False


def signal_attempt(handle: WarmHandle, *, force: bool) -> None:
    """SIGTERM (SIGKILL when ``force``) to a forked attempt, then to its group.

    Through its pidfd: never a reused pid. Never raises.
    """
    if handle.popen.returncode is not None or handle.pidfd < 0:
        return
    sig = signal.SIGKILL if force else signal.SIGTERM
    try:
        signal.pidfd_send_signal(handle.pidfd, sig)
    except OSError:
        return  # it ended: its group is the runner's reaping business, or empty
    with contextlib.suppress(OSError):
        os.killpg(handle.pid, sig)


def reap_attempt(handle: WarmHandle, running: Sequence[set[int]], lost: str) -> int:
    """The exit code its runner wrote on the status pipe, once it ended.

    What is left of its group is killed, and it leaves the runners' ``running`` sets. No
    code (the runner died first): the attempt is ``lost`` (137), saying ``lost``.
    """
    for pids in running:  # it runs no more (also when its end was seen first)
        pids.discard(handle.pid)
    if handle.popen.returncode is not None:
        return handle.popen.returncode
    try:
        data = os.read(handle.exit_fd, 64)
    except OSError:
        data = b""
    text = data.strip()
    if text.isdigit():
        code = int(text)
    else:
        code = 128 + signal.SIGKILL
        handle.lost = lost
        with contextlib.suppress(OSError):
            signal.pidfd_send_signal(handle.pidfd, signal.SIGKILL)
    with contextlib.suppress(OSError):
        os.killpg(handle.pid, signal.SIGKILL)
    handle.popen.returncode = code
    return code


def close_attempt(handle: WarmHandle) -> None:
    """Close a forked attempt's descriptors (idempotent)."""
    for name in ("exit_fd", "stdout_fd", "stderr_fd", "pidfd"):
        fd = getattr(handle, name)
        if fd >= 0:
            with contextlib.suppress(OSError):
                os.close(fd)
            setattr(handle, name, -1)


def warm_key(launch: Launch, type_ref: str, version: str | None,
             paths: Sequence[str]) -> WarmKey | None:
    """The key of a typed ``launch`` (None: its argv is not a typed task's)."""
    if len(launch.argv) != 4 or list(launch.argv[1:3]) != ["-m", RUNNER_MODULE]:
        return None
    return WarmKey(type_ref, version, tuple(paths), launch.argv[0],
                   launch.env.get("PYTHONPATH", ""))


def commands_key() -> WarmKey:
    """The key of a runner that imports no type: commands forked from it, then exec'd."""
    return WarmKey("", None, (), sys.executable, str(Path(__file__).resolve().parents[3]))


def mount_proc(relay: socket.socket) -> None:
    """Mount the proc context a sandboxed attempt's pid 1 sends, and send it the mount.

    A pid 1 that died first sends nothing: its attempt then reports its own failure.
    """
    try:
        _, fds = receive(relay, _REPLY_TIMEOUT)
    except OSError:
        return
    for context in fds:
        try:
            mounted = mounts.proc_mount(context)
        except OSError as exc:
            _log.warning("cannot mount a warm attempt's /proc: %s", exc)
            continue
        finally:
            os.close(context)
        with contextlib.suppress(OSError):
            socket.send_fds(relay, [b"proc"], [mounted])
        os.close(mounted)


def pidfd_pid(pidfd: int) -> int:
    """The pid (in our namespace) of the process ``pidfd`` refers to; 0 when gone."""
    try:
        for line in Path(f"/proc/self/fdinfo/{pidfd}").read_text().splitlines():
            if line.startswith("Pid:"):
                return max(int(line.split()[1]), 0)
    except (OSError, ValueError, IndexError):
        pass
    return 0


def _descendant(pid: int, depth: int) -> int:
    """The first child's first child ... ``depth`` levels below ``pid`` (0: none yet)."""
    for _ in range(depth):
        try:
            children = Path(f"/proc/{pid}/task/{pid}/children").read_text().split()
        except OSError:
            return 0
        if not children:
            return 0
        pid = int(children[0])
    return pid


def private_pipe(made: list[int]) -> tuple[int, int]:
    """A close-on-exec pipe, its two ends added to ``made`` (closed if the start fails)."""
    read, write = os.pipe2(os.O_CLOEXEC)
    made += (read, write)
    return read, write


def _write_request(fd: int, launch: Launch) -> None:
    """The attempt's request, for its child only; closes ``fd`` (a child that died: ignored)."""
    data = json.dumps({"argv": list(launch.argv), "cwd": str(launch.cwd),
                       "env": {**launch.env, **launch.secret_env}}).encode()
    try:
        with os.fdopen(fd, "wb") as pipe:
            pipe.write(data)
    except BrokenPipeError:
        pass


def receive(sock: socket.socket, timeout: float) -> tuple[bytes, list[int]]:
    """One datagram and its descriptors; ``b""`` when the runner is gone."""
    ready, _, _ = select.select([sock], [], [], timeout)
    if not ready:
        raise OSError(f"no answer from the warm runner in {timeout:g} s")
    data, fds, _, _ = socket.recv_fds(sock, _REPLY_MAX, 1)
    return data, fds


def resident(pid: int) -> int:
    """Resident memory of ``pid`` in bytes (0: gone)."""
    try:
        for line in Path(f"/proc/{pid}/status").read_text().splitlines():
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) * 1024
    except (OSError, ValueError, IndexError):
        pass
    return 0

