"""The process runtime's sandbox: bubblewrap (``bwrap``), the one module that knows its flags.

What a sandboxed command sees (``Sandbox.argv``, from an attempt's :class:`View`):

- **the system folders, read-only** (:data:`SYSTEM`: ``/usr``, ``/bin``, ``/sbin``,
  ``/lib*``, ``/opt``, ``/sys``, ``/etc``), with what in them is secret covered
  (:data:`COVERED`: ``/etc/shadow``, ``/etc/gshadow`` and their backups, the ssh host keys,
  and ``/etc/osmo``, where the Helm chart mounts tokens, certificates and zenoh settings).
  **Nothing else of the host**: not ``/root``, ``/home``, ``/var``, ``/srv``, ``/run``,
  ``/mnt``, ``/media``, another osmo home or another worker's, nor the host's ``/tmp``
  (the task has its own empty tmpfs there).
- **what osmo runs tasks with**, read-only, wherever it lives (``Sandbox.runtime``,
  :func:`runtime_folders`): the interpreter's prefixes and the folders of ``osmo`` and
  ``osmo_plugins`` (a virtualenv under ``/root``, pyenv's Python, a clone under ``/tmp``).
- **the operator's shares** (``--sandbox-share DIR``: read-write; ``DIR:ro``: read-only, for
  conda environments and datasets; :func:`parse_share`).
- **its own attempt** at the same absolute paths as outside, so ``{{output}}``,
  ``{{input:N}}`` and ``OSMO_OUTPUT`` work unchanged: its folder read-only, its ``work/``,
  ``output.partial/`` and ``files/`` writable, its inputs read-only. osmo's homes stay hidden
  (an empty tmpfs) even inside a shown folder or a share, and the secret files the pool
  names (``View.masked``: a server's ``--accept-token`` files, a worker's token file) are
  covered (by ``/dev/null``, which a ``nodev`` bind makes unopenable) wherever a folder
  shows them.
- a minimal ``/dev`` (null, zero, random, tty, a private ``shm``, ...) plus the GPU device
  nodes found at probe time (``/dev/nvidia*``, ``/dev/dri``), bound as they are.
- **its own namespaces**: pid (its own ``/proc``, where other tasks' processes and their
  ``/proc/<pid>/environ`` do not exist), IPC, UTS (its name copied from the host's, so
  that it resolves as before; it cannot change it),
  ``/proc/sys`` read-only, and the **node's network namespace** (``osmo.runtime.process.netns``:
  the tasks of a node share a loopback of their own and reach the outside through
  slirp4netns, never the host's loopback listeners or abstract Unix sockets).

Who runs it — always uid 0 *inside*, with no capability (the bounding set is empty) and
``no_new_privs``, so no setuid file gives anything back; the task sees itself as root, as in
a rootless container, and writes its files as the host uid below:

- **osmo as root**: on the host the task is ``nobody`` (:data:`TASK_USER`), through the
  node's user namespace (the keeper's, mapping 0 to nobody). bwrap sets the sandbox up as
  root (it binds folders nobody may not traverse, such as osmo's home, whose
  ``work/``, ``output.partial/`` and ``files/`` the pool gives to nobody:
  :attr:`Sandbox.owner`) and enters that namespace last (``--userns2``); ``setpriv`` then
  makes the command uid 0 there and empties its bounding set. That namespace is root's:
  no process outside, not even one of nobody's, may read a task's
  ``/proc/<pid>/environ`` (its secrets) or trace it. A rw share must be writable by nobody.
- **osmo as another user**: the task is that user on the host (unprivileged user namespaces
  can map nothing else): a process of that user outside the sandbox can read a task's
  environment, as it can read the worker's own memory. The command enters the keeper's
  namespaces with ``nsenter`` and bwrap makes a user namespace of its own inside.

Why a private ``/tmp``: the host's holds other tasks' scratch files and the sockets of the
user's agents (ssh-agent, tmux, X11). Tasks hand files to each other through outputs and
inputs; a host folder every task may write (a scratch disk) is the operator's choice.

``--die-with-parent``: the sandbox is SIGKILLed when the thread that started it ends, so no
task outlives its worker or server (a sandbox still being set up then runs on: the pool's
record of pids covers that, ``osmo.worker.procs``). Everything in the sandbox shares bwrap's
process group; the pid namespace ends, and the kernel kills every process left in it, when
the command ends (a daemon that called ``setsid`` included).

What it does not do: limit CPU, memory or disk; filter system calls (the kernel's attack
surface is the host's); hide the tasks of one node from each other on their shared network.

Cost (``bench/bench_sandbox.py``, two starts at a time on 2 cores, as root): about 1.1 ms
more per start than the sandbox before this one (``--ro-bind / /`` on the host's network,
as root, 2.2 ms): ``setpriv``'s exec 0.7 ms (bubblewrap cannot change the uid after its
setup, and its setup must be root's to bind osmo's 0700 home), the view's binds 0.35 ms,
``/proc/sys`` 0.2 ms, IPC and UTS 0.25 ms; entering the node's network 0.1 ms (a
``setns`` of the spawning thread).

A sandboxed warm runner (``osmo.runtime.process.warm``) is made here too
(:meth:`Sandbox.runner_argv`), and its attempts' views from :meth:`Sandbox.layout`, the
same mounts in the same order as :meth:`Sandbox.argv`.

Availability: :func:`choose` probes once per process whether ``bwrap`` exists and can make
the whole sandbox here, node namespaces included, and whether it reports the command's exit
code on a status pipe (``--json-status-fd``): with it, a failure of bwrap's own setup (its
exit 1, before the command runs) is told from the command's exit 1
(``osmo.runtime.process.groups``; the pool starts it again, ``osmo.worker.starts``). Why none works
is said twice: :func:`unavailable_reason` in full (bwrap's own message and a hint, for logs and
errors) and :func:`unavailable_summary` in a few words (``bwrap not found``, ``user namespaces
refused``, ``cannot mount /proc``; what ``osmo resource list`` shows).
"""

from __future__ import annotations

import contextlib
import dataclasses
import functools
import glob
import importlib.util
import os
import pwd
import shutil
import subprocess
import sys
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path

from osmo.errors import InfrastructureError, UsageError
from osmo.options import SANDBOX_MODES, SandboxMode, parse_share
from osmo.runtime.process.netns import Entry, NodeNetwork, entered

__all__ = ["COVERED", "SYSTEM", "TASK_USER", "Layout", "Sandbox", "SandboxMode", "View", "choose",
           "node_network", "parse_share", "runtime_folders", "unavailable_reason",
           "unavailable_summary"]

SYSTEM = ("/usr", "/bin", "/sbin", "/lib", "/lib32", "/lib64", "/libx32", "/opt", "/sys", "/etc")
"""The host folders every task sees, read-only (those that exist; symlinks stay symlinks)."""
COVERED = ("/etc/shadow", "/etc/shadow-", "/etc/gshadow", "/etc/gshadow-",
           "/etc/ssh/ssh_host_*", "/etc/osmo")
"""What of :data:`SYSTEM` no task may read (globs): a folder is covered by an empty one, a
file the tasks' uid could read by an unreadable device node (``/dev/null``, nodev)."""
TASK_USER = "nobody"
"""Who tasks of a root server or worker are on the host (its uid and primary gid)."""


_PACKAGE = "bubblewrap"
_PROBE_TIMEOUT = 10.0
_PROBE_TRIES = 8  # 5 ms doubling: 0.6 s in all, as a task's start (osmo.worker.starts)
_GPU_DEVICES = ("/dev/nvidia*", "/dev/dri")
_NOBODY = 65534
_AS_ROOT_INSIDE = ("--reuid=0", "--regid=0", "--clear-groups", "--bounding-set=-all",
                   "--inh-caps=-all", "--")


@dataclass(frozen=True)
class View:
    """What one attempt may see of osmo's folders (every path absolute).

    Attributes:
        hidden: folders replaced by an empty tmpfs (osmo's homes).
        readonly: paths bound back read-only (the attempt's folder, its inputs).
        writable: paths bound back writable (``work/``, ``output.partial/``, ``files/``).
        cwd: the command's working folder inside the sandbox.
        masked: files covered by an empty one (secrets a shown folder would show).
        code: folders shown read-only as a share is, before osmo's homes are hidden (a
            typed task's own code: osmo's home stays hidden even inside one).
    """

    hidden: tuple[Path, ...]
    readonly: tuple[Path, ...]
    writable: tuple[Path, ...]
    cwd: Path
    masked: tuple[Path, ...] = ()
    code: tuple[Path, ...] = ()


@dataclass(frozen=True)
class Layout:
    """Where one attempt's view is mounted (real paths), in the order bubblewrap mounts it.

    Attributes:
        hidden: folders covered by an empty tmpfs (osmo's homes), parents first.
        masked: files covered by ``/dev/null``.
        binds: ``(path, writable)`` bound at the same path, parents first, a parent's
            read-only bind before its writable children.
        cwd: the command's working folder.
    """

    hidden: tuple[str, ...]
    masked: tuple[str, ...]
    binds: tuple[tuple[str, bool], ...]
    cwd: str


@dataclass(frozen=True)
class Sandbox:
    """A working bubblewrap: builds the argv that runs a command in an attempt's view.

    Attributes:
        bwrap: the ``bwrap`` executable.
        devices: host device nodes bound into the sandbox's ``/dev`` (GPUs).
        shared: host folders bound writable into every sandbox (``--sandbox-share DIR``).
        shared_readonly: host folders bound read-only into every sandbox (``DIR:ro``).
        runtime: folders osmo's own interpreter and code live in, outside the system
            folders, bound read-only (:func:`runtime_folders`).
        status: this bwrap reports the command's exit code on a status pipe
            (``--json-status-fd``, bubblewrap >= 0.5), so a setup failure can be told from it.
        system: bwrap arguments that show the system folders and cover their secrets.
        setpriv: the ``setpriv`` executable (osmo as root: it makes the command uid 0 in the
            node's user namespace).
        owner: ``(uid, gid)`` on the host that tasks run as when osmo is root (the owner
            of what an attempt writes); None: osmo's own.
        entry: how a start enters the node's namespaces (:meth:`joined`); None: not yet.
    """

    bwrap: str
    devices: tuple[str, ...] = ()
    shared: tuple[str, ...] = ()
    shared_readonly: tuple[str, ...] = ()
    runtime: tuple[str, ...] = ()
    status: bool = False
    system: tuple[str, ...] = ()
    setpriv: str = "setpriv"
    owner: tuple[int, int] | None = None
    entry: Entry | None = None

    def joined(self, network: NodeNetwork) -> Sandbox:
        """This sandbox with its commands in ``network``'s namespaces."""
        return dataclasses.replace(self, entry=network.entry())

    @property
    def fds(self) -> tuple[int, ...]:
        """Descriptors a start must pass to bwrap (the node's user namespace, as root)."""
        entry = self.entry
        return (entry.userns_fd,) if entry is not None and entry.userns_fd >= 0 else ()

    def entered(self) -> contextlib.AbstractContextManager[None]:
        """While inside, the calling thread's new processes start in the node's network."""
        return entered(self.entry) if self.entry is not None else contextlib.nullcontext()

    def shows(self, path: str) -> bool:
        """Whether ``path`` (absolute) is visible to every task (system, runtime, shares)."""
        return any(path == top or path.startswith(top.rstrip("/") + "/") for top in self._tops)

    def argv(self, command: Sequence[str], view: View, status_fd: int = -1) -> list[str]:
        """``command`` wrapped in bwrap with ``view`` (see the module docstring).

        Start it with :attr:`fds` passed and inside :meth:`entered`. Mounts are applied in
        order: the system, then what osmo runs with, the shares and the task's code, then
        the tmpfs that hides osmo's homes, the covers, and the attempt's own paths (a
        parent's read-only bind before its writable children). ``status_fd``: an inherited
        descriptor bwrap writes its status to (``osmo.runtime.process.groups``).

        Raises:
            InfrastructureError: the sandbox has not joined a node's namespaces.
        """
        entry = self.entry
        if entry is None:
            raise InfrastructureError("the sandbox has not joined the node's namespaces")
        out = [*entry.prefix, self.bwrap]
        if status_fd >= 0:
            out += ["--json-status-fd", str(status_fd)]
        out += self._fixed
        made: set[str] = set()
        code = sorted({_real(p) for p in view.code if not self.shows(_real(p))}, key=_depth)
        for folder in code:  # (a share that shows it already keeps its own access)
            out += _parent_dir(folder, made)
            out += ["--ro-bind-try", folder, folder]
        placed = self.layout(view, code)
        for folder in placed.hidden:
            out += ["--tmpfs", folder]
            made.add(folder)
        for file in placed.masked:
            out += ["--ro-bind", "/dev/null", file]
        for bound, writable in placed.binds:
            out += _parent_dir(bound, made)
            out += ["--bind-try" if writable else "--ro-bind-try", bound, bound]
            made.add(bound)
        out += ["--chdir", placed.cwd, "--"]
        if entry.userns_fd >= 0:  # root: the command becomes uid 0 of the node's namespace
            out += [self.setpriv, *_AS_ROOT_INSIDE]
        return [*out, *command]

    def layout(self, view: View, code: Sequence[str] = ()) -> Layout:
        """Where ``view``'s mounts go, in the order :meth:`argv` makes them (real paths).

        ``code``: the typed task's code folders shown before the homes are hidden.
        """
        tops = (*self._tops, *code) if self.owner is not None else ()
        hidden = sorted({_closed_root(_real_root(str(p)), tops) for p in view.hidden},
                        key=_depth)
        roots = [(str(p), _real_root(str(p))) for p in view.hidden]
        binds = [(_real_under(p, roots), False) for p in view.readonly]
        binds += [(_real_under(p, roots), True) for p in view.writable]
        return Layout(tuple(hidden), tuple(_real_under(f, roots) for f in view.masked),
                      tuple(sorted(binds, key=lambda b: (_depth(b[0]), b[1]))),
                      _real_under(view.cwd, roots))

    def runner_argv(self, command: Sequence[str], hidden: Sequence[Path]) -> list[str]:
        """``command`` in a sandbox that hides ``hidden``, as a sandboxed warm runner.

        The view of an attempt with no folders of its own, except that the command keeps
        ``CAP_SYS_ADMIN`` and ``CAP_SETPCAP`` in the node's user namespace: what it needs to
        build each forked attempt's view (``osmo.runtime.process.warm_runner``), which drops
        them. Only for a root osmo (:attr:`owner`), whose runner is trusted code (a built-in
        task type): a runner reads its attempts' folders once they run a program.
        """
        if self.owner is None:
            raise InfrastructureError("a sandboxed warm runner needs a root osmo")
        argv = self.argv(command, View(hidden=tuple(hidden), readonly=(), writable=(),
                                       cwd=Path("/")))
        out: list[str] = []
        for arg in argv:
            out.append("--bounding-set=-all,+sys_admin,+setpcap"
                       if arg == "--bounding-set=-all" else arg)
            if arg == "ALL" and out[-2:-1] == ["--cap-drop"]:
                out += ["--cap-add", "CAP_SYS_ADMIN"]
        return out

    @functools.cached_property
    def _tops(self) -> tuple[str, ...]:
        """The host folders every task sees (what :meth:`shows` checks), real paths."""
        return (*_shown_system(), *self.runtime, *self.shared, *self.shared_readonly)

    @functools.cached_property
    def _fixed(self) -> tuple[str, ...]:
        """The arguments every start shares (namespaces, system, /dev, /proc, /tmp, shares)."""
        entry = self.entry
        assert entry is not None
        out = ["--unshare-pid", "--unshare-ipc", "--unshare-uts", "--die-with-parent",
               "--cap-drop", "ALL"]
        if entry.userns_fd >= 0:  # root: set up as root, then enter the node's user namespace
            out += ["--userns2", str(entry.userns_fd), "--cap-add", "CAP_SETUID",
                    "--cap-add", "CAP_SETGID", "--cap-add", "CAP_SETPCAP"]
        else:  # a user namespace of its own inside the node's: its bounding set is emptied
            out += ["--unshare-user", "--uid", "0", "--gid", "0"]
        out += self.system
        out += ["--dev", "/dev"]
        for device in self.devices:
            out += ["--dev-bind-try", device, device]
        out += ["--proc", "/proc", "--ro-bind", "/proc/sys", "/proc/sys",
                "--perms", "1777", "--tmpfs", "/tmp"]
        if entry.resolv_conf is not None:
            out += ["--ro-bind", entry.resolv_conf, "/etc/resolv.conf"]
        made: set[str] = set()
        folders = [(f, "--ro-bind-try") for f in (*self.runtime, *self.shared_readonly)]
        folders += [(f, "--bind-try") for f in self.shared]
        for folder, flag in sorted(folders, key=lambda f: _depth(f[0])):
            out += _parent_dir(folder, made)
            out += [flag, folder, folder]
            made.add(folder)
        return tuple(out)


def _parent_dir(path: str, made: set[str]) -> list[str]:
    """``--dir PARENT`` unless ``path``'s parent is ``/`` or was made already.

    bubblewrap 0.8 makes the missing parents of a mount point mode 0700 (root's), which
    a task that is not root on the host could not pass; ``--dir`` makes them 0755.
    """
    parent = os.path.dirname(path)
    if parent in ("/", "") or parent in made:
        return []
    made.add(parent)
    return ["--dir", parent]


def _real(path: Path) -> str:
    return os.path.realpath(path)


@functools.lru_cache(maxsize=64)  # osmo's homes: resolved once, not for every start
def _real_root(path: str) -> str:
    return os.path.realpath(path)


@functools.lru_cache(maxsize=64)
def _closed_root(root: str, tops: tuple[str, ...]) -> str:
    """What to hide for osmo's home ``root`` when tasks are not osmo's uid.

    A home inside a shown folder (a share) may lie below a folder the task's uid cannot
    enter (an ``OSMO_HOME`` is 0700, a worker's home is inside it); the empty tmpfs then
    goes on the highest such folder, so the attempt's own paths bound below it can be
    reached. (Hiding a folder the task could not enter hides nothing it could see.)
    """
    top = max((t for t in tops if root.startswith(t.rstrip("/") + "/")), key=len, default=None)
    if top is None:
        return root
    path = top
    for part in Path(root).relative_to(top).parts[:-1]:
        path = os.path.join(path, part)
        try:
            if not os.stat(path).st_mode & 0o001:
                return path
        except OSError:
            return path
    return root


def _real_under(path: Path, roots: Sequence[tuple[str, str]]) -> str:
    """The real path of ``path``; below a hidden root, the root's real path and the rest.

    What lies below osmo's home was made by osmo (no symlinks): resolving the root alone
    gives the same path as resolving every part, without an ``lstat`` per part per start.
    """
    text = str(path)
    for root, real in roots:
        if text.startswith(root + "/") and "/../" not in text[len(root):] + "/":
            return real + text[len(root):]
    return os.path.realpath(text)


def _depth(path: str) -> int:
    return path.rstrip("/").count("/")


def choose(mode: SandboxMode, shared: Sequence[str | Path] = ()) -> Sandbox | None:
    """The sandbox to use for ``mode`` (None: run commands unsandboxed).

    ``shared``: host folders every sandboxed command may see (absolute; ``DIR:ro`` for
    read-only, :func:`parse_share`). The sandbox must then join a node's namespaces
    (:func:`node_network`, :meth:`Sandbox.joined`) before it runs anything.

    Raises:
        UsageError: ``mode`` is not one of ``osmo.options.SANDBOX_MODES``, or a shared
            folder is relative.
        InfrastructureError: ``mode`` is ``on`` and bubblewrap is missing or does not work
            here (the message names the package and the reason).
    """
    if mode not in SANDBOX_MODES:
        raise UsageError(f"sandbox mode {mode!r}: choose one of {', '.join(SANDBOX_MODES)}")
    if mode == "off":
        return None
    sandbox = _probe()
    if sandbox is None and mode == "on":
        raise InfrastructureError(f"--sandbox on: {unavailable_reason()}")
    if sandbox is None:
        return None
    parsed = [parse_share(str(p)) for p in shared]
    relative = [folder for folder, _ in parsed if not os.path.isabs(folder)]
    if relative:
        raise UsageError(f"--sandbox-share needs absolute folders, not {', '.join(relative)}")
    return dataclasses.replace(
        sandbox, runtime=runtime_folders(),
        shared=tuple(_real(Path(f)) for f, writable in parsed if writable),
        shared_readonly=tuple(_real(Path(f)) for f, writable in parsed if not writable))


def node_network(outbound: bool = True, address: str | None = None) -> NodeNetwork:
    """A new network namespace for this node's sandboxed tasks (close it when done).

    ``address``: the node's address as its peers know it (``NodeNetwork.start``).

    Raises:
        InfrastructureError: it cannot be made here.
    """
    return NodeNetwork.start(_task_ids(), outbound=outbound, address=address)


def runtime_folders(paths: Sequence[str] | None = None) -> tuple[str, ...]:
    """The folders tasks need from osmo's own installation that no system folder shows.

    ``paths`` (default: this interpreter's prefixes and the folders holding the ``osmo``
    and ``osmo_plugins`` packages, ``osmo.worker.launch.osmo_paths``), reduced to those
    outside the system folders, without the ones inside another. Not ``sys.path``: it may
    hold the current folder, such as a home.
    """
    if paths is None:
        paths = [sys.prefix, sys.base_prefix, sys.exec_prefix, *_package_roots()]
    real = {_real(Path(p)) for p in paths if p and os.path.isabs(p) and os.path.isdir(p)}
    system = _shown_system()
    found = sorted(p for p in real if not any(p == s or p.startswith(s + "/") for s in system))
    return tuple(p for p in found if not any(p.startswith(q + "/") for q in found))


def _package_roots() -> list[str]:
    out = []
    for package in ("osmo", "osmo_plugins"):
        spec = importlib.util.find_spec(package)
        for location in (spec.submodule_search_locations or []) if spec else []:
            out.append(str(Path(location).parent))
    return out


@functools.cache  # the host's layout does not change while we run
def _shown_system() -> tuple[str, ...]:
    """The real paths of the system folders that exist here."""
    return tuple(dict.fromkeys(_real(Path(top)) for top in SYSTEM if os.path.exists(top)))


def _system_view(owner: tuple[int, int] | None) -> tuple[str, ...]:
    """The bwrap arguments that show :data:`SYSTEM` read-only and cover :data:`COVERED`.

    A covered file is covered only if the tasks' uid (``owner``; None: this process's)
    could read it: each cover is one more mount per start, and ``/etc/shadow`` (0640,
    root's) is unreadable to a task that is not root on the host anyway.
    """
    out: list[str] = []
    for top in SYSTEM:
        if os.path.islink(top):
            out += ["--symlink", os.readlink(top), top]
        elif os.path.isdir(top):
            out += ["--ro-bind", top, top]
    for pattern in COVERED:
        for path in sorted(glob.glob(pattern)):
            if os.path.isdir(path) and not os.path.islink(path):
                out += ["--tmpfs", path]
            elif os.path.exists(path) and _readable(path, owner):
                out += ["--ro-bind", "/dev/null", path]
    return tuple(out)


def _readable(path: str, owner: tuple[int, int] | None) -> bool:
    """Whether ``owner`` (uid, gid; None: this process) may read the file ``path``."""
    if owner is None:
        return os.access(path, os.R_OK)
    st = os.stat(path)
    if st.st_uid == owner[0]:
        return bool(st.st_mode & 0o400)
    if st.st_gid == owner[1]:
        return bool(st.st_mode & 0o040)
    return bool(st.st_mode & 0o004)


def _task_ids() -> tuple[int, int]:
    """``(uid, gid)`` of :data:`TASK_USER` (65534 where no such user exists)."""
    try:
        entry = pwd.getpwnam(TASK_USER)
    except KeyError:
        return _NOBODY, _NOBODY
    return entry.pw_uid, entry.pw_gid


def unavailable_reason() -> str:
    """Why no sandbox is available here, in full (empty when one is)."""
    return _probe_result()[1]


def unavailable_summary() -> str:
    """Why no sandbox is available here, in a few words (empty when one is)."""
    return _probe_result()[2]


def _probe() -> Sandbox | None:
    return _probe_result()[0]


@functools.cache  # once per process: whether bwrap works does not change while we run
def _probe_result() -> tuple[Sandbox | None, str, str]:
    """The working sandbox, or None with why: in full and in a few words."""
    bwrap = shutil.which("bwrap")
    if bwrap is None:
        return None, (f"bubblewrap is not installed (install the '{_PACKAGE}' package, "
                      "e.g. apt-get install bubblewrap)"), "bwrap not found"
    root = os.geteuid() == 0
    needed = "setpriv" if root else "nsenter"  # who enters the node's namespaces
    helper = shutil.which(needed)
    if helper is None:
        return (None, f"util-linux's {needed} is missing (apt-get install util-linux)",
                f"{needed} not found")
    owner = _task_ids() if root else None
    sandbox = Sandbox(bwrap, system=_system_view(owner), setpriv=helper if root else "setpriv",
                      owner=owner)
    try:
        network = node_network(outbound=False)
    except InfrastructureError as exc:
        return None, f"bubblewrap ({bwrap}): {exc}", "no network namespace"
    try:
        problem = _try(sandbox.joined(network))
        if problem:
            summary, hint = _failure(problem)
            return None, (f"bubblewrap ({bwrap}) cannot make its sandbox here: {problem} "
                          f"({hint})"), summary
        status = bool(_tried(lambda: _status_once(sandbox.joined(network))))
    finally:
        network.close()
    devices = tuple(sorted(d for pattern in _GPU_DEVICES for d in glob.glob(pattern)))
    return dataclasses.replace(sandbox, devices=devices, status=status), "", ""


# bwrap's failure (a fragment of its message) -> (summary, hint). bwrap says little more than
# "Operation not permitted"; these are the causes seen in containers and on locked-down hosts.
_FAILURES = (
    ("namespace", "user namespaces refused",
     "are unprivileged user namespaces disabled (sysctl user.max_user_namespaces, "
     "kernel.unprivileged_userns_clone), or refused by a seccomp or AppArmor profile?"),
    ("uid map", "user namespaces refused",
     "are unprivileged user namespaces disabled, or refused by an AppArmor profile?"),
    ("mount proc", "cannot mount /proc",
     "is /proc masked, as in a container? Kubernetes: procMount Unmasked, with hostUsers false"),
    ("mount", "mounts refused", "does an AppArmor or SELinux profile refuse mounts?"),
)


def _failure(message: str) -> tuple[str, str]:
    """A few words and a hint for bwrap's failure ``message`` (:data:`_FAILURES`)."""
    low = message.lower()
    for fragment, summary, hint in _FAILURES:
        if fragment in low:
            return summary, hint
    return "bwrap fails", "see bubblewrap's message"


def _probe_view() -> View:
    return View(hidden=(), readonly=(), writable=(), cwd=Path("/"))


def _try(sandbox: Sandbox) -> str:
    """Why ``true`` does not run in ``sandbox`` (empty: it does)."""
    runs: list[subprocess.CompletedProcess[bytes]] = []

    def once() -> bool:
        with sandbox.entered():
            runs.append(subprocess.run(sandbox.argv(["true"], _probe_view()),
                                       stdin=subprocess.DEVNULL, capture_output=True,
                                       timeout=_PROBE_TIMEOUT, check=False,
                                       pass_fds=sandbox.fds))
        return runs[-1].returncode == 0

    try:
        _tried(once)
    except (OSError, subprocess.SubprocessError) as exc:
        return f"{exc}"
    done = runs[-1]
    if done.returncode == 0:
        return ""
    return done.stderr.decode("utf-8", "replace").strip() or f"exit {done.returncode}"


def _tried(attempt: Callable[[], object]) -> object:
    """``attempt()`` until it returns something true, :data:`_PROBE_TRIES` times at most.

    A probe loses the same setup race as a task (a mount vanishing under a bind of a
    system folder, ``osmo.worker.starts``); one lost race must not decide a server's sandbox.
    """
    delay = 0.005
    for _ in range(_PROBE_TRIES - 1):
        result = attempt()
        if result:
            return result
        time.sleep(delay)
        delay *= 2
    return attempt()


def _status_once(sandbox: Sandbox) -> bool:
    """Whether this bwrap writes the command's exit code to ``--json-status-fd``."""
    read, write = os.pipe()
    try:
        with sandbox.entered():
            done = subprocess.run(sandbox.argv(["true"], _probe_view(), write),
                                  stdin=subprocess.DEVNULL, capture_output=True,
                                  pass_fds=(write, *sandbox.fds), timeout=_PROBE_TIMEOUT,
                                  check=False)
        os.close(write)
        write = -1
        return done.returncode == 0 and b'"exit-code": 0' in os.read(read, 65536)
    except (OSError, subprocess.SubprocessError):
        return False
    finally:
        os.close(read)
        if write >= 0:
            os.close(write)
