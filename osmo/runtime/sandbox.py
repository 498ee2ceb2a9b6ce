"""The process runtime's sandbox: bubblewrap (``bwrap``), the one module that knows its flags.

A sandboxed command sees (``Sandbox.argv``, from an attempt's :class:`View`):

- the host's file system **read-only** (``--ro-bind / /``), with its **own empty ``/tmp``**
  (a tmpfs, gone when the task ends) instead of the host's, and the folders the operator
  shares with every task (``--sandbox-share DIR``) writable; a minimal ``/dev`` (null,
  zero, random, tty, a private ``shm``, ...) plus the GPU device nodes found at probe time
  (``/dev/nvidia*``, ``/dev/dri``, bound as they are, so CUDA and EGL work);
- osmo's home **hidden** under an empty tmpfs (state store, blobs, other attempts' folders,
  credentials), with only the attempt's own paths bound back at the same absolute paths, so
  ``{{output}}``, ``{{input:N}}`` and ``OSMO_OUTPUT`` work unchanged: its folder read-only,
  its ``work/``, ``output.partial/`` and ``files/`` writable, its inputs read-only;
- its own **pid namespace** with its own ``/proc``: other tasks' processes, and their
  ``/proc/<pid>/environ``, do not exist for it;
- the host's network (tasks reach each other through ``{{host:NAME}}``), user and ipc;
- **no capabilities**, under a root worker too (``--cap-drop ALL``; bwrap run by root keeps
  root's otherwise, and a task could unmount the tmpfs that hides osmo's home or remount the
  host writable); bwrap sets ``no_new_privs``, so no exec (a setuid file) gives them back.

``--die-with-parent``: the sandbox is SIGKILLed when the process that started it (the pool
thread that spawned it) ends, so no task outlives its worker or server (a sandbox still being
set up then runs on: the pool's record of pids covers that, ``osmo.worker.procs``). Everything
in the sandbox shares bwrap's process group; the pid namespace ends, and the kernel kills every
process left in it, when the command ends (a daemon that called ``setsid`` included).

Why a private ``/tmp``: the host's holds other tasks' scratch files and the sockets of the
user's agents (ssh-agent, tmux, X11), through which a task could act outside its sandbox.
Tasks hand files to each other through outputs and inputs; a host folder every task may
write (a shared scratch disk) is the operator's explicit choice: ``shared``. osmo's home
stays hidden even when it lies inside a shared folder. What osmo itself runs tasks with stays
visible, read-only, when it lives under ``/tmp`` (a clone or a virtualenv there): the
interpreter's prefixes, the folders of ``osmo`` and its plugins, and ``sys.path``
(``Sandbox.runtime``).

What it does not do: limit CPU, memory or disk; filter system
calls (the kernel's attack surface is the host's); change the user (the task runs as the
worker's uid, so anything that uid can reach over the network, it can reach too).

Availability: :func:`choose` probes once per process whether ``bwrap`` exists and can make
the namespaces (some machines forbid unprivileged user namespaces), and whether it reports
the command's exit code on a status pipe (``--json-status-fd``): with it, a failure of
bwrap's own setup (its exit 1, before the command runs) is told from the command's exit 1
(``osmo.runtime.process``; the pool starts it again, ``osmo.worker.starts``). Why none works
is said twice: :func:`unavailable_reason` in full (bwrap's own message and a hint, for logs and
errors) and :func:`unavailable_summary` in a few words (``bwrap not found``, ``user namespaces
refused``, ``cannot mount /proc``; what ``osmo resource list`` shows).
"""

from __future__ import annotations

import dataclasses
import functools
import glob
import importlib.util
import os
import shutil
import subprocess
import sys
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path

from osmo.errors import InfrastructureError, UsageError
from osmo.options import SANDBOX_MODES, SandboxMode

__all__ = ["Sandbox", "SandboxMode", "View", "choose", "unavailable_reason",
           "unavailable_summary"]

_PACKAGE = "bubblewrap"
_PROBE_TIMEOUT = 10.0
_PROBE_TRIES = 8  # 5 ms doubling: 0.6 s in all, as a task's start (osmo.worker.starts)
_GPU_DEVICES = ("/dev/nvidia*", "/dev/dri")
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


@dataclass(frozen=True)
class View:
    """What one attempt may see of osmo's folders (every path absolute).

    Attributes:
        hidden: folders replaced by an empty tmpfs (osmo's home).
        readonly: paths bound back read-only (the attempt's folder, its inputs).
        writable: paths bound back writable (``work/``, ``output.partial/``, ``files/``).
        cwd: the command's working folder inside the sandbox.
    """

    hidden: tuple[Path, ...]
    readonly: tuple[Path, ...]
    writable: tuple[Path, ...]
    cwd: Path


@dataclass(frozen=True)
class Sandbox:
    """A working bubblewrap: builds the argv that runs a command in an attempt's view.

    Attributes:
        bwrap: the ``bwrap`` executable.
        devices: host device nodes bound into the sandbox's ``/dev`` (GPUs).
        shared: host folders bound writable into every sandbox (``--sandbox-share``).
        runtime: folders under ``/tmp`` that osmo's own interpreter and code live in, bound
            back read-only (:func:`runtime_folders`).
        status: this bwrap reports the command's exit code on a status pipe
            (``--json-status-fd``, bubblewrap >= 0.5), so a setup failure can be told from it.
    """

    bwrap: str
    devices: tuple[str, ...] = ()
    shared: tuple[str, ...] = ()
    runtime: tuple[str, ...] = ()
    status: bool = False

    def argv(self, command: Sequence[str], view: View, status_fd: int = -1) -> list[str]:
        """``command`` wrapped in bwrap with ``view`` (see the module docstring).

        Mounts are applied in order, so the binds come after the tmpfs that hides their
        parent, and a parent's read-only bind before its writable children. ``status_fd``:
        an inherited descriptor bwrap writes its status to (``osmo.runtime.process``).
        """
        out = [self.bwrap]
        if status_fd >= 0:
            out += ["--json-status-fd", str(status_fd)]
        out += ["--cap-drop", "ALL", "--ro-bind", "/", "/", "--dev", "/dev"]
        for device in self.devices:
            out += ["--dev-bind-try", device, device]
        out += ["--proc", "/proc", "--tmpfs", "/tmp", "--unshare-pid", "--die-with-parent"]
        for folder in self.runtime:  # before the home is hidden: it stays hidden inside one
            out += ["--ro-bind-try", folder, folder]
        for folder in self.shared:
            out += ["--bind-try", folder, folder]
        hidden = sorted({_real_root(str(p)) for p in view.hidden}, key=_depth)
        for folder in hidden:
            out += ["--tmpfs", folder]
        roots = [(str(p), _real_root(str(p))) for p in view.hidden]
        binds = [(_real_under(p, roots), "--ro-bind-try") for p in view.readonly]
        binds += [(_real_under(p, roots), "--bind-try") for p in view.writable]
        for path, flag in sorted(binds, key=lambda b: (_depth(b[0]), b[1] == "--bind-try")):
            out += [flag, path, path]
        return [*out, "--chdir", _real_under(view.cwd, roots), "--", *command]


def _real(path: Path) -> str:
    return os.path.realpath(path)


@functools.lru_cache(maxsize=64)  # osmo's homes: resolved once, not for every start
def _real_root(path: str) -> str:
    return os.path.realpath(path)


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

    ``shared``: host folders every sandboxed command may read and write (absolute).

    Raises:
        UsageError: ``mode`` is not one of ``osmo.options.SANDBOX_MODES``.
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
    relative = [str(p) for p in shared if not os.path.isabs(p)]
    if relative:
        raise UsageError(f"--sandbox-share needs absolute folders, not {', '.join(relative)}")
    return dataclasses.replace(sandbox, runtime=runtime_folders(),
                               shared=tuple(_real(Path(p)) for p in shared))


def runtime_folders(paths: Sequence[str] | None = None) -> tuple[str, ...]:
    """The folders under ``/tmp`` that tasks need from osmo's own installation.

    ``paths`` (default: this interpreter's prefixes, the folders holding the ``osmo`` and
    ``osmo_plugins`` packages, and ``sys.path``), reduced to those inside ``/tmp`` (which a
    sandbox replaces by its own), without the ones inside another.
    """
    if paths is None:
        paths = [sys.prefix, sys.base_prefix, sys.exec_prefix, *sys.path]
        for package in ("osmo", "osmo_plugins"):
            spec = importlib.util.find_spec(package)
            if spec is not None and spec.origin:
                paths.append(str(Path(spec.origin).parent.parent))
    inside = _real(Path("/tmp")) + "/"
    real = {_real(Path(p)) for p in paths if p and os.path.isabs(p) and os.path.isdir(p)}
    found = sorted(p for p in real if p.startswith(inside))
    return tuple(p for p in found if not any(p.startswith(q + "/") for q in found))


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
    probe = [bwrap, "--cap-drop", "ALL", "--ro-bind", "/", "/", "--dev", "/dev", "--proc", "/proc",
             "--unshare-pid", "--die-with-parent", "--", "true"]
    runs: list[subprocess.CompletedProcess[bytes]] = []

    def once() -> bool:
        runs.append(subprocess.run(probe, stdin=subprocess.DEVNULL, capture_output=True,
                                   timeout=_PROBE_TIMEOUT, check=False))
        return runs[-1].returncode == 0

    try:
        _tried(once)
        done = runs[-1]
    except (OSError, subprocess.SubprocessError) as exc:
        return None, f"bubblewrap ({bwrap}) cannot run: {exc}", "bwrap cannot run"
    if done.returncode != 0:
        message = done.stderr.decode("utf-8", "replace").strip() or f"exit {done.returncode}"
        summary, hint = _failure(message)
        return None, f"bubblewrap ({bwrap}) cannot make its sandbox here: {message} ({hint})", \
            summary
    devices = tuple(sorted(d for pattern in _GPU_DEVICES for d in glob.glob(pattern)))
    return Sandbox(bwrap, devices, status=_reports_status(probe)), "", ""


def _failure(message: str) -> tuple[str, str]:
    """A few words and a hint for bwrap's failure ``message`` (:data:`_FAILURES`)."""
    low = message.lower()
    for fragment, summary, hint in _FAILURES:
        if fragment in low:
            return summary, hint
    return "bwrap fails", "see bubblewrap's message"


def _tried(attempt: Callable[[], object]) -> object:
    """``attempt()`` until it returns something true, :data:`_PROBE_TRIES` times at most.

    A probe loses the same setup race as a task (a mount vanishing under ``--ro-bind / /``,
    module docstring); one lost race must not decide a whole server's sandbox.
    """
    delay = 0.005
    for _ in range(_PROBE_TRIES - 1):
        result = attempt()
        if result:
            return result
        time.sleep(delay)
        delay *= 2
    return attempt()


def _reports_status(probe: list[str]) -> bool:
    """Whether this bwrap writes the command's exit code to ``--json-status-fd``."""
    return bool(_tried(lambda: _status_once(probe)))


def _status_once(probe: list[str]) -> bool:
    read, write = os.pipe()
    try:
        done = subprocess.run([probe[0], "--json-status-fd", str(write), *probe[1:]],
                              stdin=subprocess.DEVNULL, capture_output=True, pass_fds=(write,),
                              timeout=_PROBE_TIMEOUT, check=False)
        os.close(write)
        write = -1
        return done.returncode == 0 and b'"exit-code": 0' in os.read(read, 65536)
    except (OSError, subprocess.SubprocessError):
        return False
    finally:
        os.close(read)
        if write >= 0:
            os.close(write)
