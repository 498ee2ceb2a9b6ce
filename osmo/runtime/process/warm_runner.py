"""A warm runner: one process that imported a task type once and forks each attempt from it.

Started by ``osmo.runtime.process.warm`` (the pool's side) as::

    python -m osmo.runtime.process.warm_runner FD TYPE VERSION [FOLDER ...]

``FD`` is its end of a ``SOCK_SEQPACKET`` socket pair with the pool; ``TYPE`` the task type's
reference as a spec writes it, ``VERSION`` the version the pool expects (``-``: any), the
``FOLDER`` s those a custom type is imported from. Its environment is the pool's base
environment (``osmo.worker.taskenv``) with the type's ``PYTHONPATH``: no attempt's variables,
no credential. What it owns:

- **the import**: it puts the folders on ``sys.path``, resolves the type (which imports its
  module and whatever that imports), calls the type's optional ``warm()`` (a built-in
  plugin imports its implementation and the libraries every run needs there), imports the
  modules every attempt uses, then says ``ready``
  (with the files of the modules it imported from the type's folders and their mtimes:
  the pool retires it when one changes) or ``error: WHY`` (the pool then runs that type
  cold). A type whose import started a
  Python thread is refused: its code would run on in the runner, beside every fork request.
  (Native threads of libraries, such as a BLAS pool, are not counted: they do not survive a
  fork, and the libraries that start them handle it.)
- **the forks**: each request on the socket carries four descriptors (the attempt's stdout
  and stderr pipes, the read end of its request pipe, the write end of its status pipe). The
  runner hands them (and a sandboxed request's own, below) to its *spare*, a child it forked
  ahead of the request (over a socket pair of their own), or forks one then if it has none;
  it answers the child's pid with a pidfd of it, closes its copies of the attempt's
  descriptors, and only then forks the next spare: the fork is off an attempt's start. A
  spare leads its own session and process group before the runner counts it as one (so a
  kill from the pool always finds the group) and holds nothing of any attempt until it is
  handed one. The runner never reads the request pipe: only the child does.
- **the exits**: it reaps its children and writes each one's exit code (``128+N`` for signal
  N) to its status pipe, then closes it.
- **its end**: when the pool closes its end of the socket, it takes no more requests and
  exits once its children have ended; when idle for the time the pool gave it (``OSMO_WARM_IDLE``,
  seconds), it exits by itself. It dies with the pool (``PR_SET_PDEATHSIG``, set by the pool's
  spawn), and its children die with it (the same signal, set in each child).

The child (:func:`_spare`, then :func:`_attempt`): ``PR_SET_PDEATHSIG`` (SIGKILL), its own
session (as a cold attempt's ``start_new_session``), default signal handlers, every
descriptor of the runner closed, its attempt's descriptors received, its request read from
the pipe (argv, working folder,
complete environment, as JSON), stdin from ``/dev/null``, stdout and stderr the attempt's
pipes; the environment then *replaces* the runner's. A typed task's argv
(``osmo.worker.launch.runner_argv``) runs in the child itself (``osmo.tasktypes.runner``, its
module already imported); any other argv is executed (what the runtime contract's checks
run). Module state a task changes, threads it starts and memory it takes are its own
process's: the runner, forked again for the next attempt, never ran it. A typed task's
process ends as an interpreter's exit would end it (:func:`_typed`: its threads joined, its
``atexit`` handlers run, the files it left open flushed), then ``os._exit``.

A **sandboxed** runner (started in bubblewrap by the pool, with ``CAP_SYS_ADMIN`` in the
node's user namespace, and ``OSMO_WARM_SANDBOXED=1``) gets ``fork LAYOUT`` requests with
two more kinds of descriptor: a relay socket and a detached mount of each of the
attempt's folders. Each of its children is forked into a new pid namespace, whose pid 1
it is (the runner makes that namespace before the fork and returns to its own after it:
for that it runs as the pid 1 of a pid namespace it made itself, below bubblewrap's, its
first process waiting for it). A child handed an attempt makes the attempt's view before
anything else and forks the attempt's own process (:func:`_enclose`: pid 2, no
capability, ``no_new_privs``), which reads the request only then; the child stays the
namespace's init, and the runner reaps it as any child: its exit is the attempt's.

A **container** runner (``OSMO_WARM_CONTAINER=1``, started by
``osmo.runtime.container.warm`` as the pid 1 of a container of the task's image, with no
``CAP_SYS_ADMIN``) first makes a user namespace of its own (:func:`_own_user_namespace`:
every uid mapped to itself; a process without ``CAP_SYS_ADMIN`` cannot write such maps
where it was: the pool writes them) and in it a pid namespace, and then serves as a
sandboxed runner does:
each child is the pid 1 of a new pid namespace, in a mount, IPC and UTS namespace of its
own owned by that user namespace (the container's mounts are locked there, podman's
covers on ``/proc`` too). Its view (:func:`_enclose_container`): the image's root and
every mount of the container read-only (the container's writable layer is shared by every
attempt of the runner), an empty ``/tmp`` and ``/dev/shm``, its own ``/dev/pts``, its
folders' detached mounts at their container paths, a ``/proc`` of its pid namespace
through the relay, with podman's covers made again on it; its process runs with the
request's uid and gid. Its end differs: a container runner whose socket's peer is gone
without a ``retire`` first (the pool was killed) exits at once, and with it every attempt
(it is the pid 1 of the namespace theirs are below); ``retire`` makes it exit once its
attempts ended, as a closed socket makes the others.

It must not import anything of the worker or the server.
"""

from __future__ import annotations

import atexit
import contextlib
import ctypes
import gc
import io
import json
import os
import re
import selectors
import signal
import socket
import sys
import threading
import time
from collections.abc import Sequence
from pathlib import PurePosixPath
from typing import Any, NoReturn

from osmo.runtime.process import mounts

__all__ = ["CONTAINER_VARIABLE", "IDLE_VARIABLE", "MAP", "MAPPED", "READY", "RETIRE",
           "RUNNER_MODULE", "SANDBOXED_VARIABLE", "main"]

READY = b"ready"
"""What the runner sends once it has imported its type."""
RUNNER_MODULE = "osmo.tasktypes.runner"
"""The module of a typed task's argv (``python -m osmo.tasktypes.runner CONTEXT``)."""
IDLE_VARIABLE = "OSMO_WARM_IDLE"
"""The variable that gives a runner its idle time in seconds (it exits after that long idle)."""
SANDBOXED_VARIABLE = "OSMO_WARM_SANDBOXED"
"""The variable that makes a runner sandboxed (``1``: each child a new pid namespace's pid 1)."""
CONTAINER_VARIABLE = "OSMO_WARM_CONTAINER"
"""The variable that makes a runner a container's (``1``: see the module docstring)."""
RETIRE = b"retire"
"""What the pool sends a container runner to retire it (its attempts run on to their end)."""
MAP, MAPPED = b"map", b"mapped"
"""A container runner's request for its user namespace's maps, and the pool's answer."""
_container = False  # set by main: this runner serves attempts in a container

_LAYOUT_ROOTS = ("/osmo/data/", "/osmo/run/")  # a container attempt's layout (its mount points)
_PR_SET_PDEATHSIG = 1
_DESCRIPTORS = 4  # stdout, stderr, request pipe, status pipe
_BINDS_MAX = 200  # a sandboxed attempt's folders, one descriptor each (SCM_RIGHTS: <= 253)
_DATAGRAM_MAX = 1 << 20
_REQUEST_LIMIT = 64 * 1024 * 1024
_SOURCES_MAX = 200  # a reply is one datagram: a project's own modules, not a library's


def _die_with_parent() -> None:
    ctypes.CDLL(None, use_errno=True).prctl(_PR_SET_PDEATHSIG, signal.SIGKILL, 0, 0, 0)


def _load(ref: str, version: str, folders: Sequence[str]) -> str:
    """Import the type and what every attempt uses; empty, or why it cannot be warm."""
    for folder in reversed(folders):
        if folder not in sys.path:
            sys.path.insert(0, folder)
    try:
        from osmo.errors import OsmoError
        from osmo.tasktypes import context, runner  # noqa: F401 - what each attempt imports
        from osmo.tasktypes.registry import resolve

        if not ref:  # a runner of commands (a fork, then their exec): nothing more to import
            return ""
        obj = resolve(ref)
        runner.keep_resolved(ref, obj)
    except OsmoError as exc:
        return str(exc)
    except Exception as exc:  # noqa: BLE001 - the type's own import failed: say so, run cold
        return f"importing {ref}: {exc!r}"
    if version != "-" and str(obj.version) != version:
        return f"{ref} is version {obj.version} here, not {version}"
    warm = getattr(obj, "warm", None)
    if callable(warm):
        try:
            warm()
        except Exception as exc:  # noqa: BLE001 - its own warm-up failed: run it cold
            return f"warming {ref}: {exc!r}"
    if threading.active_count() != 1:
        return f"importing {ref} started a Python thread; a warm runner must have none"
    return ""


def _sources(folders: Sequence[str]) -> dict[str, int]:
    """The files of the modules imported from ``folders`` with their mtimes (stale checks)."""
    tops = tuple(os.path.join(os.path.realpath(f), "") for f in folders)
    out: dict[str, int] = {}
    for module in list(sys.modules.values()):
        path = getattr(module, "__file__", None)
        if isinstance(path, str) and tops and os.path.realpath(path).startswith(tops):
            with contextlib.suppress(OSError):
                out[path] = os.stat(path).st_mtime_ns
        if len(out) >= _SOURCES_MAX:
            break
    return out


class _Runner:
    """The serving loop (see the module docstring)."""

    def __init__(self, sock: socket.socket, idle: float, *, sandboxed: bool = False,
                 container: bool = False) -> None:
        self.sock, self.idle, self.container = sock, idle, container
        self.retiring = False
        # a sandboxed runner's children: each the pid 1 of a pid namespace of its own, made
        # by an unshare before the fork; the runner returns to its own with this
        self.pid_ns = os.open("/proc/self/ns/pid", os.O_RDONLY | os.O_CLOEXEC) if sandboxed else -1
        self.children: dict[int, int] = {}  # pid -> its status pipe's write end
        self.spare: tuple[int, socket.socket] | None = None  # forked ahead: pid, its socket
        self.accepting = True
        self.wake_r, self.wake_w = os.pipe2(os.O_NONBLOCK | os.O_CLOEXEC)
        self.selector = selectors.DefaultSelector()

    def serve(self) -> None:
        signal.set_wakeup_fd(self.wake_w)
        signal.signal(signal.SIGCHLD, lambda *_: None)
        signal.signal(signal.SIGTERM, signal.SIG_DFL)
        selector = self.selector
        selector.register(self.sock, selectors.EVENT_READ, "sock")
        selector.register(self.wake_r, selectors.EVENT_READ, "wake")
        last = time.monotonic()
        self._fork_spare()
        while self.accepting or self.children:
            ready = selector.select(timeout=1.0)
            for key, _ in ready:
                if key.data == "wake":
                    with contextlib.suppress(BlockingIOError):
                        os.read(self.wake_r, 4096)
                    self._reap()
                elif not self._serve_one():
                    if self.container and not self.retiring:
                        return  # the pool is gone: this exit ends every attempt
                    self.accepting = False
                    selector.unregister(self.sock)
            self._reap()
            if self.children:
                last = time.monotonic()
            elif time.monotonic() - last > self.idle:
                return

    def _serve_one(self) -> bool:
        """One request; False when the pool closed its end."""
        try:
            data, fds, _, _ = socket.recv_fds(self.sock, _DATAGRAM_MAX,
                                              _DESCRIPTORS + 1 + _BINDS_MAX)
        except OSError:
            return False
        if not data or (self.container and data == RETIRE):
            for fd in fds:
                os.close(fd)
            self.retiring = bool(data)
            return False
        layout = _layout(data)
        if len(fds) != _DESCRIPTORS + (1 + len(layout["binds"]) if layout else 0):
            for fd in fds:
                os.close(fd)
            self.sock.send(b"error: a fork request without its descriptors")
            return True
        status = fds[_DESCRIPTORS - 1]
        handed = [*fds[:_DESCRIPTORS - 1], *fds[_DESCRIPTORS:]]  # all but the status pipe
        pid = self._hand_over(data, handed, status)
        for fd in handed:
            os.close(fd)
        self.children[pid] = status
        pidfd = os.pidfd_open(pid)
        try:
            socket.send_fds(self.sock, [str(pid).encode()], [pidfd])
        except OSError:
            pass  # the pool is gone: the child dies with this runner
        finally:
            os.close(pidfd)
        self._fork_spare()
        return True

    def _hand_over(self, data: bytes, fds: list[int], status: int) -> int:
        """The request (``data``) and the attempt's descriptors to the spare; the child's pid.

        With no spare (or a dead one), one is forked now.
        """
        while True:
            if self.spare is None:  # its copies of these: only those it is handed
                self._fork_spare(*fds, status)
            assert self.spare is not None
            pid, sock = self.spare
            self.spare = None
            try:
                socket.send_fds(sock, [data], fds)
                return pid
            except OSError:  # it died (killed from outside): it is reaped as a stranger
                continue
            finally:
                sock.close()

    def _fork_spare(self, *also_drop: int) -> None:
        """Fork the child of the next attempt ahead of its request (see the module docstring).

        Returns once the child leads its own session (or is gone).
        """
        ours, theirs = socket.socketpair(socket.AF_UNIX, socket.SOCK_SEQPACKET)
        sys.stdout.flush()
        sys.stderr.flush()
        led_r, led_w = os.pipe2(os.O_CLOEXEC)
        if self.pid_ns >= 0:
            mounts.unshare(mounts.NEWPID)  # the next child: a new pid namespace's pid 1
        try:
            pid = os.fork()
            if pid == 0:
                os.close(led_r)
                _spare(theirs.fileno(), led_w, enclosed=self.pid_ns >= 0,
                       drop=(self.sock.fileno(), self.wake_r, self.wake_w, ours.fileno(),
                             self.selector.fileno(), self.pid_ns,
                             *also_drop, *self.children.values()))
        finally:
            if self.pid_ns >= 0:  # the runner's next child (a spare too) is no child of it
                mounts.setns(self.pid_ns, mounts.NEWPID)
        theirs.close()
        os.close(led_w)
        os.read(led_r, 1)  # its end closed: the child leads its session (or is gone)
        os.close(led_r)
        self.spare = (pid, ours)

    def _reap(self) -> None:
        while self.children:
            try:
                pid, wait_status = os.waitpid(-1, os.WNOHANG)
            except ChildProcessError:
                return
            if pid == 0:
                return
            status = self.children.pop(pid, -1)
            if self.spare is not None and pid == self.spare[0]:  # a spare killed from outside
                self.spare[1].close()
                self.spare = None
            if status < 0:
                continue
            code = os.waitstatus_to_exitcode(wait_status)
            code = 128 - code if code < 0 else code
            with contextlib.suppress(OSError):
                os.write(status, f"{code}\n".encode())
            os.close(status)


def _layout(data: bytes) -> dict[str, Any] | None:
    """A sandboxed fork request's layout (``fork LAYOUT``); None for a plain ``fork``."""
    if not data.startswith(b"fork "):
        return None
    layout: dict[str, Any] = json.loads(data[5:])
    return layout


def _spare(sock: int, led: int, *, enclosed: bool, drop: tuple[int, ...]) -> None:
    """In the forked child: lead a session, await an attempt, become it; never returns.

    It waits for its attempt's request and descriptors on ``sock``, then runs
    :func:`_attempt`. ``enclosed``: it is the pid 1 of a pid namespace of its own (a
    sandboxed runner's child), which takes only sandboxed requests (``fork LAYOUT``), as a
    runner's child that is not takes only plain ones.

    ``led``: closed once the child leads its own session (and process group). The runner
    closing its end of ``sock`` (or dying) before handing an attempt over ends the child.
    """
    code = 127
    try:
        _die_with_parent()
        os.setsid()
        os.close(led)
        signal.set_wakeup_fd(-1)
        for sig in (signal.SIGCHLD, signal.SIGTERM, signal.SIGINT, signal.SIGPIPE):
            signal.signal(sig, signal.SIG_DFL)
        for fd in drop:
            with contextlib.suppress(OSError):
                os.close(fd)
        with socket.socket(fileno=sock) as handed:
            data, fds, _, _ = socket.recv_fds(handed, _DATAGRAM_MAX, _DESCRIPTORS + _BINDS_MAX)
        if len(fds) >= _DESCRIPTORS - 1:  # none: the runner closed its end (it retires)
            layout = _layout(data)
            if (layout is not None) != enclosed:
                raise OSError(f"a {'plain' if enclosed else 'sandboxed'} request to a "
                              f"{'sandboxed' if enclosed else 'plain'} runner")
            out, err, request, *extra = fds
            code = _attempt(out, err, request, layout=layout, extra=extra)
    except BaseException as exc:  # noqa: BLE001 - whatever happens, the child must exit here
        with contextlib.suppress(Exception):
            os.write(2, f"osmo: warm start failed: {exc!r}\n".encode())
    finally:
        os._exit(code)


def _attempt(out: int, err: int, request: int, *, layout: dict[str, Any] | None = None,
             extra: Sequence[int] = ()) -> int:
    """In the child, handed its attempt: become it, then run it; its exit code.

    ``layout`` and ``extra`` (a sandboxed attempt's): where its view goes, and the
    descriptors of its relay to the pool and of its folders' detached mounts
    (:func:`_enclose`).
    """
    code = 127
    try:
        null = os.open(os.devnull, os.O_RDONLY)
        os.dup2(null, 0)
        os.dup2(out, 1)
        os.dup2(err, 2)
        for fd in (null, out, err):
            if fd > 2:
                os.close(fd)
        enclose = _enclose_container if _container else _enclose
        cwd = enclose(layout, extra[0], extra[1:], request) if layout is not None else None
        with os.fdopen(request, "rb") as pipe:  # its credentials: read here, never before
            wanted: dict[str, Any] = json.loads(pipe.read(_REQUEST_LIMIT))
        code = _run(list(wanted["argv"]), cwd or str(wanted["cwd"]), dict(wanted["env"]))
    except BaseException as exc:  # noqa: BLE001 - whatever happens, the child must exit
        with contextlib.suppress(Exception):
            os.write(2, f"osmo: warm start failed: {exc!r}\n".encode())
    return code


def _enclose(layout: dict[str, Any], relay: int, binds: Sequence[int], request: int) -> str:
    """Make this fork a sandboxed attempt's, as bubblewrap would; its working folder.

    Called in the pid 1 of a pid namespace of its own (the runner made it); returns only in
    the attempt's own process (pid 2, every capability dropped, ``no_new_privs``). This
    process stays the namespace's init, as bubblewrap's pid 1 does: it reaps what the
    attempt leaves, exits with the attempt's code when the attempt's process ends, and its
    exit (or its kill) ends every process left in the namespace. It holds no capability
    and cannot be traced once the attempt's process runs; as the namespace's init, the
    kernel drops every signal from inside that it has no handler for (SIGKILL and SIGSTOP
    too).

    Its own namespaces (mount, IPC, UTS) inside the runner's sandbox; the runner's mounts
    copied, then what bubblewrap mounts for this attempt: an empty tmpfs over osmo's homes
    (``hidden``), ``/dev/null`` over the ``masked`` files, its folders (``binds``:
    ``[path, writable, folder]``, their detached mounts from the pool) at their paths, an
    empty ``/tmp``, a ``/dev`` of its own (the runner's device nodes, a private ``shm``
    and ``pts``), and a ``/proc`` of its pid namespace with ``/proc/sys`` read-only: its
    context goes first on ``relay`` and the pool mounts it meanwhile.
    """
    if os.getpid() != 1:
        raise OSError("a sandboxed attempt's process is not its pid namespace's pid 1")
    os.umask(0o022)
    mounts.unshare(mounts.NEWNS | mounts.NEWIPC | mounts.NEWUTS)
    relay_sock = _ask_proc(relay)  # in a mount namespace of the node's user namespace
    mounts.make_private()
    _fresh_dev(_devices())  # in bubblewrap's order: /dev, /tmp, the homes, covers, binds
    shown = _shown_under("/tmp", layout["hidden"])  # bound after /tmp, as cold: keep them
    mounts.mount_tmpfs("/tmp", 0o1777)
    for path, folder, fd in shown:
        _mount_point(path, folder)
        mounts.move(fd, path)
        os.close(fd)
    for folder in layout["hidden"]:
        os.makedirs(folder, exist_ok=True)
        mounts.mount_tmpfs(folder, 0o755)
    for file in layout["masked"]:
        mounts.bind("/dev/null", file, readonly=True)
    _move_binds(layout["binds"], binds)
    _take_proc(relay_sock)
    task = os.fork()
    if task == 0:
        mounts.drop_privileges()
        return str(layout["cwd"])
    _init(task, request)


def _enclose_container(layout: dict[str, Any], relay: int, binds: Sequence[int],
                       request: int) -> str:
    """Make this fork a container attempt's (see the module docstring); its working folder.

    As :func:`_enclose`, in the pid 1 of a pid namespace of its own; returns only in the
    attempt's process (pid 2, the request's ``user``, no capability, ``no_new_privs``).
    ``layout``: ``binds`` (``[target, writable, folder]``, one detached mount each), ``cwd``
    and ``user`` (``[uid, gid]``). The mount points of osmo's layout (``/osmo/data``,
    ``/osmo/run``) are made on the container's root first (empty, named by osmo: the same
    for every attempt), before the root turns read-only for this attempt; any other target
    must be in the image (or under ``/tmp`` or ``/dev/shm``, its own), or the attempt
    fails: what one attempt made there every later one would see (the pool starts such an
    attempt cold: ``osmo.runtime.container.runtime``).
    """
    if os.getpid() != 1:
        raise OSError("a container attempt's process is not its pid namespace's pid 1")
    os.umask(0o022)
    mounts.unshare(mounts.NEWNS | mounts.NEWIPC | mounts.NEWUTS)
    relay_sock = _ask_proc(relay)
    mounts.make_private()
    covers = _proc_covers()
    for target, _, folder in layout["binds"]:
        if target.startswith(_LAYOUT_ROOTS):  # osmo's own names, the same for every attempt
            _mount_point(target, folder)
        elif not target.startswith(("/tmp/", "/dev/shm/")) and not os.path.lexists(target):
            # made on the container's root, it would be there for every later attempt
            raise OSError(f"{target} is not in the image: a warm attempt cannot add it")
    mounts.readonly_tree("/")
    mounts.mount_tmpfs("/tmp", 0o1777)
    mounts.mount_tmpfs("/dev/shm", 0o1777)
    mounts.devpts("/dev/pts")
    _move_binds(layout["binds"], binds)
    _take_proc(relay_sock)
    for path, folder in covers:
        if folder is None:
            mounts.bind(path, path, readonly=True)
        elif os.path.exists(path):
            if folder:
                mounts.mount_tmpfs(path, 0o555)
                mounts.readonly_tree(path)
            else:  # /dev/null's mount has locked flags: add read-only, keep those
                mounts.bind("/dev/null", path, readonly=False)
                mounts.readonly_tree(path)
    uid, gid = layout.get("user") or (0, 0)
    task = os.fork()
    if task == 0:
        mounts.drop_privileges(int(uid), int(gid))
        return str(layout["cwd"])
    _init(task, request)


def _ask_proc(relay: int) -> socket.socket:
    """Send the pool a proc context of this namespace on ``relay`` (it mounts it for us)."""
    relay_sock = socket.socket(fileno=relay)
    context = mounts.proc_context()
    socket.send_fds(relay_sock, [b"proc"], [context])
    os.close(context)
    return relay_sock


def _take_proc(relay_sock: socket.socket) -> None:
    """Move the ``/proc`` the pool mounted in place, ``/proc/sys`` read-only; close the relay."""
    _, got, _, _ = socket.recv_fds(relay_sock, 16, 1)
    relay_sock.close()
    if not got:
        raise OSError("the pool did not mount this attempt's /proc")
    mounts.move(got[0], "/proc")
    os.close(got[0])
    mounts.bind("/proc/sys", "/proc/sys", readonly=True)


def _move_binds(binds: Sequence[Sequence[Any]], fds: Sequence[int]) -> None:
    """Move each detached mount in ``fds`` to its ``[path, writable, folder]`` (closed)."""
    for (path, _, folder), fd in zip(binds, fds, strict=True):
        _mount_point(path, folder)
        mounts.move(fd, path)
        os.close(fd)


def _proc_covers() -> list[tuple[str, bool | None]]:
    """The engine's covers on the container's ``/proc``, to make again on an attempt's.

    (path, None): a part of ``/proc`` the engine made read-only; (path, True/False): a
    folder or file it hid (an empty tmpfs, ``/dev/null``).
    """
    out: list[tuple[str, bool | None]] = []
    with open("/proc/self/mountinfo", "rb") as table:
        for line in table:
            fields = line.split()
            point = os.fsdecode(fields[4])
            if not point.startswith("/proc/") or point == "/proc/sys":
                continue
            kind = fields[fields.index(b"-") + 1]
            out.append((point, None) if kind == b"proc" else (point, os.path.isdir(point)))
    return out


def _own_user_namespace(sock: socket.socket) -> None:
    """Go on in a new user namespace in which the pool maps every uid and gid to itself.

    A container runner's: the container's pid 1 (this process) has no ``CAP_SYS_ADMIN``,
    which the runner needs over the namespaces it makes for each attempt; its own user
    namespace gives it that over them only. Maps naming more than the caller's own uid
    need a writer with ``CAP_SYS_ADMIN`` and ``CAP_SETUID`` where this process was: the
    pool, root on the host, which gets a pidfd of this process (``map``) and answers
    ``mapped`` once it wrote them.
    """
    mounts.unshare(mounts.NEWUSER)
    me = os.pidfd_open(os.getpid())
    try:
        socket.send_fds(sock, [MAP], [me])
    finally:
        os.close(me)
    if sock.recv(64) != MAPPED:
        raise OSError("the pool did not map this runner's user namespace")


def _init(task: int, request: int) -> NoReturn:
    """The attempt's pid 1 once its process (``task``) runs: reap, then exit with its code."""
    mounts.undumpable()  # before its capabilities go: never traceable by the attempt
    mounts.drop_privileges()
    os.close(request)
    null = os.open(os.devnull, os.O_WRONLY)
    os.dup2(null, 1)  # the attempt's output ends when its own processes end
    os.dup2(null, 2)
    os.close(null)
    while True:  # reap, until the attempt's own process ends
        pid, status = os.waitpid(-1, 0)
        if pid == task:
            os._exit(_exit_code(status))


def _shown_under(root: str, hidden: Sequence[str]) -> list[tuple[str, bool, int]]:
    """The runner's mounts under ``root`` as detached clones: (path, folder?, descriptor).

    What the runner's own sandbox binds on its ``/tmp`` (a share, osmo's code when it lives
    under ``/tmp``), which bubblewrap binds after the ``/tmp`` of a cold attempt too; each
    clone keeps its mount's flags (a read-only one stays read-only), nested mounts with it.
    Osmo's homes (``hidden``) are left out: the attempt gets an empty tmpfs there anyway.
    """
    found: list[str] = []
    with open("/proc/self/mountinfo", "rb") as table:
        for line in table:
            point = os.fsdecode(re.sub(rb"\\([0-7]{3})",
                                       lambda m: bytes([int(m.group(1), 8)]),
                                       line.split()[4]))
            if point.startswith(root + "/"):
                found.append(point)
    out: list[tuple[str, bool, int]] = []
    kept: list[str] = []
    for point in sorted(set(found)):
        if any(PurePosixPath(point).is_relative_to(top) for top in (*kept, *hidden)):
            continue  # comes with its parent's clone, or lies under a home
        kept.append(point)
        folder = os.path.isdir(point)
        out.append((point, folder, mounts.detached(point, readonly=False)))
    return out


def _exit_code(status: int) -> int:
    code = os.waitstatus_to_exitcode(status)
    return 128 - code if code < 0 else code


def _mount_point(path: str, folder: bool) -> None:
    if folder:
        os.makedirs(path, exist_ok=True)
        return
    os.makedirs(os.path.dirname(path), exist_ok=True)
    if not os.path.exists(path):
        os.close(os.open(path, os.O_WRONLY | os.O_CREAT, 0o644))


def _devices() -> list[tuple[str, str | int, bool]]:
    """The runner's ``/dev`` as bubblewrap made it: symlinks, clones of its nodes' mounts."""
    out: list[tuple[str, str | int, bool]] = []
    for entry in os.scandir("/dev"):
        if entry.is_symlink():
            out.append((entry.name, os.readlink(entry.path), False))
        elif entry.name not in ("shm", "pts") and os.path.ismount(entry.path):
            clone = mounts.detached(entry.path, readonly=False, device=True)
            out.append((entry.name, clone, entry.is_dir(follow_symlinks=False)))
    return out


def _fresh_dev(devices: list[tuple[str, str | int, bool]]) -> None:
    """A ``/dev`` of this attempt's own over the runner's (nothing written there is shared)."""
    mounts.mount_tmpfs("/dev", 0o755)
    for name, what, folder in devices:
        path = os.path.join("/dev", name)
        if isinstance(what, str):
            os.symlink(what, path)
            continue
        _mount_point(path, folder)
        mounts.move(what, path)
        os.close(what)
    os.mkdir("/dev/shm")
    os.chmod("/dev/shm", 0o1777)
    os.mkdir("/dev/pts")
    mounts.devpts("/dev/pts")


def _run(argv: list[str], cwd: str, env: dict[str, str]) -> int:
    """The attempt's command in this process: its environment, its folder, its task."""
    os.chdir(cwd)
    os.environ.clear()
    os.environ.update(env)
    if len(argv) == 4 and argv[1:3] == ["-m", RUNNER_MODULE]:
        return _typed(argv[3])
    try:
        os.execvpe(argv[0], argv, env)
    except OSError as exc:
        os.write(2, f"osmo: cannot start '{argv[0]}': {exc.strerror or exc}\n".encode())
    return 127


def _typed(context: str) -> int:
    """A typed task, as ``python -m osmo.tasktypes.runner CONTEXT`` would run it.

    The process then ends with ``os._exit`` (an interpreter's own exit would tear the
    runner's imports down again), so first it does what that exit would do for the task:
    join its threads, run the ``atexit`` handlers it registered (the runner's own, from its
    imports, are dropped before the task runs) and flush the files it left open.
    """
    from osmo.tasktypes import runner

    sys.argv = [runner.__file__ or RUNNER_MODULE, context]
    numpy = sys.modules.get("numpy")
    if numpy is not None:  # a fork shares its parent's global generator: give it its own
        with contextlib.suppress(Exception):
            numpy.random.seed()
    atexit._clear()
    code = runner.main([context])
    for thread in threading.enumerate():  # as an interpreter's exit would: its own threads
        if thread is not threading.current_thread() and not thread.daemon:
            thread.join()
    atexit._run_exitfuncs()
    _flush_files()
    with contextlib.suppress(Exception):
        sys.stdout.flush()
        sys.stderr.flush()
    return code


def _flush_files() -> None:
    """Flush every file object the attempt left open, as their close at exit would.

    The runner froze what it made before forking (``gc.freeze``), so the collector lists
    only what the attempt made.
    """
    for found in gc.get_objects():
        if isinstance(found, io.IOBase):
            with contextlib.suppress(Exception):
                if not found.closed:
                    found.flush()


def _own_pid_namespace(sock: int) -> None:
    """Go on as the pid 1 of a new pid namespace; this process waits for it and exits with it.

    A sandboxed runner's: bubblewrap made its pid namespace before entering the node's
    user namespace, so only in one the runner made itself may it return to its own pid
    namespace after each spare's (``setns``). Done before the import: what waits is small.
    """
    mounts.unshare(mounts.NEWPID)
    pid = os.fork()
    if pid == 0:
        mounts.die_with_parent()  # and if this one is gone already, bubblewrap ends it
        return
    os.close(sock)  # the runner's end: the pool sees the runner's exit, not this one's
    os._exit(_exit_code(os.waitpid(pid, 0)[1]))


def main(argv: Sequence[str] | None = None) -> int:
    """``python -m osmo.runtime.process.warm_runner FD TYPE VERSION [FOLDER ...]``."""
    args = list(sys.argv[1:] if argv is None else argv)
    if len(args) < 3:
        sys.stderr.write("usage: python -m osmo.runtime.process.warm_runner FD TYPE VERSION "
                         "[FOLDER ...]\n")
        return 2
    global _container
    _container = os.environ.pop(CONTAINER_VARIABLE, "") == "1"
    sandboxed = os.environ.pop(SANDBOXED_VARIABLE, "") == "1" or _container
    sock = socket.socket(fileno=int(args[0]))
    if _container:
        _own_user_namespace(sock)
    if sandboxed:
        _own_pid_namespace(int(args[0]))
    why = _load(args[1], args[2], args[3:])
    if why:
        sock.send(f"error: {why}".encode()[:4096])
        return 1
    sock.send(READY + b" " + json.dumps(_sources(args[3:])).encode())
    gc.freeze()  # what an attempt's collector lists is the attempt's own (_flush_files)
    _Runner(sock, float(os.environ.get(IDLE_VARIABLE, "60")), sandboxed=sandboxed,
            container=_container).serve()
    return 0


if __name__ == "__main__":
    sys.exit(main())
