"""Linux mount and namespace system calls for sandboxed warm starts: the one ctypes adapter.

``osmo.runtime.process.warm`` (the pool, root on the host) and ``warm_runner`` (an attempt
forked in a sandboxed runner) build an attempt's view with these, as bubblewrap builds it
cold (``osmo.runtime.process.sandbox``):

- the pool clones each folder the attempt may see into a detached mount (:func:`detached`:
  ``open_tree(OPEN_TREE_CLONE)``, read-only ones with ``mount_setattr``), which the attempt,
  in a mount namespace of its own, moves into place (:func:`move`);
- ``/proc``: the attempt's pid 1 makes a proc context of its own pid namespace
  (:func:`proc_context`); the pool mounts it (:func:`proc_mount`: the attempt's own
  ``mount("proc")`` is refused, EPERM, because bubblewrap's covers in the runner's ``/proc``
  are locked in the node's user namespace) and the attempt moves the result into place;
- the rest: :func:`unshare` and :func:`setns` (the runner's pid namespace for each child),
  tmpfs and bind mounts (:func:`mount_tmpfs`, :func:`bind`), :func:`drop_privileges`
  (every capability, ``no_new_privs``), :func:`undumpable`, :func:`die_with_parent`.

Every failure raises ``OSError`` with the call's name and errno. It must not import anything
of osmo: the runner imports it before its fork.
"""

from __future__ import annotations

import ctypes
import functools
import os

__all__ = ["NEWIPC", "NEWNS", "NEWPID", "NEWUSER", "NEWUTS", "devpts", "bind", "detached",
           "die_with_parent", "drop_privileges", "make_private", "mount_tmpfs", "move",
           "proc_context", "proc_mount", "readonly_tree", "setns", "undumpable", "unshare",
           "unsupported"]

NEWNS, NEWUTS, NEWIPC, NEWPID = 0x20000, 0x04000000, 0x08000000, 0x20000000
"""``unshare`` flags: a mount, a UTS, an IPC and a pid namespace."""
NEWUSER = 0x10000000
"""``unshare`` flag: a user namespace (a container warm runner's, ``warm_runner``)."""

_LIBC = ctypes.CDLL(None, use_errno=True)
_AT_FDCWD = -100
_AT_EMPTY_PATH, _AT_RECURSIVE = 0x1000, 0x8000
_OPEN_TREE_CLONE, _OPEN_TREE_CLOEXEC = 1, 0o2000000
_MOVE_MOUNT_F_EMPTY_PATH = 4
_ATTR_RDONLY, _ATTR_NOSUID, _ATTR_NODEV, _ATTR_NOEXEC = 1, 2, 4, 8
_FSOPEN_CLOEXEC, _FSMOUNT_CLOEXEC, _FSCONFIG_CMD_CREATE = 1, 1, 6
_SYSCALLS = {"open_tree": 428, "move_mount": 429, "fsopen": 430, "fsconfig": 431,
           "fsmount": 432, "mount_setattr": 442}  # one numbering on every architecture (>= 424)
_MS_RDONLY, _MS_NOSUID, _MS_NODEV, _MS_NOEXEC = 1, 2, 4, 8
_MS_REMOUNT, _MS_BIND, _MS_REC, _MS_PRIVATE = 32, 4096, 16384, 1 << 18
_PR_SET_PDEATHSIG, _PR_SET_DUMPABLE, _PR_CAPBSET_DROP, _PR_SET_NO_NEW_PRIVS = 1, 4, 24, 38
_CAP_LAST = 63
_SIGKILL = 9


class _MountAttr(ctypes.Structure):
    _fields_ = [("attr_set", ctypes.c_uint64), ("attr_clr", ctypes.c_uint64),
                ("propagation", ctypes.c_uint64), ("userns_fd", ctypes.c_uint64)]


class _CapHeader(ctypes.Structure):
    _fields_ = [("version", ctypes.c_uint32), ("pid", ctypes.c_int)]


class _CapData(ctypes.Structure):
    _fields_ = [("effective", ctypes.c_uint32), ("permitted", ctypes.c_uint32),
                ("inheritable", ctypes.c_uint32)]


def _checked(name: str, result: int) -> int:
    if result < 0:
        errno = ctypes.get_errno()
        raise OSError(errno, f"{name}: {os.strerror(errno)}")
    return result


def _syscall(name: str, *args: object) -> int:
    return _checked(name, _LIBC.syscall(_SYSCALLS[name], *args))


def _mount(source: str | None, target: str, fstype: str | None, flags: int,
           data: str | None = None) -> None:
    enc = [s.encode() if s is not None else None for s in (source, target, fstype, data)]
    _checked(f"mount {target}", _LIBC.mount(enc[0], enc[1], enc[2], ctypes.c_ulong(flags),
                                            enc[3]))


@functools.cache  # the kernel does not change while we run
def unsupported() -> str:
    """Why this kernel lacks what a sandboxed warm start needs (empty: it has it all).

    Tried once, as the pool: a detached read-only clone (``open_tree``, ``mount_setattr``:
    Linux 5.12) and a proc context (``fsopen``, ``fsconfig``; ``fsmount`` is tried by the
    first attempt, in its own pid namespace).
    """
    try:
        os.close(detached("/", readonly=True))
        os.close(proc_context())
    except OSError as exc:
        return str(exc)
    return ""


def detached(path: str, *, readonly: bool, device: bool = False) -> int:
    """A detached clone of the mount tree at ``path`` (nosuid, nodev; read-only if asked).

    ``device``: a device node, which keeps working (not nodev). Returns its descriptor
    (close-on-exec). Raises OSError (ENOENT: ``path`` is missing).
    """
    fd = _syscall("open_tree", _AT_FDCWD, path.encode(),
                  _OPEN_TREE_CLONE | _OPEN_TREE_CLOEXEC | _AT_RECURSIVE)
    attr = _MountAttr(_ATTR_NOSUID | (0 if device else _ATTR_NODEV)
                      | (_ATTR_RDONLY if readonly else 0))
    try:
        _syscall("mount_setattr", fd, b"", _AT_EMPTY_PATH | _AT_RECURSIVE, ctypes.byref(attr),
                 ctypes.sizeof(attr))
    except OSError:
        os.close(fd)
        raise
    return fd


def move(fd: int, target: str) -> None:
    """Attach the detached mount ``fd`` on ``target`` (an existing folder or file)."""
    _syscall("move_mount", fd, b"", _AT_FDCWD, target.encode(), _MOVE_MOUNT_F_EMPTY_PATH)


def proc_context() -> int:
    """A new proc filesystem context for the calling process's pid namespace (its fd)."""
    context = _syscall("fsopen", b"proc", _FSOPEN_CLOEXEC)
    try:
        _syscall("fsconfig", context, _FSCONFIG_CMD_CREATE, None, None, 0)
    except OSError:
        os.close(context)
        raise
    return context


def proc_mount(context: int) -> int:
    """A detached mount of the proc ``context`` (nosuid, nodev, noexec): its descriptor."""
    return _syscall("fsmount", context, _FSMOUNT_CLOEXEC,
                    _ATTR_NOSUID | _ATTR_NODEV | _ATTR_NOEXEC)


def unshare(flags: int) -> None:
    """New namespaces for the calling process (``NEWNS | NEWPID | ...``)."""
    _checked("unshare", _LIBC.unshare(flags))


def setns(fd: int, flags: int) -> None:
    """Join the namespace ``fd`` refers to (``NEWPID``: the one of the caller's next children)."""
    _checked("setns", _LIBC.setns(fd, flags))


def make_private() -> None:
    """Nothing mounted here from now on propagates to or from the runner's mounts."""
    _mount(None, "/", None, _MS_REC | _MS_PRIVATE)


def mount_tmpfs(target: str, mode: int) -> None:
    """An empty tmpfs on ``target`` (nosuid, nodev), its root with ``mode``."""
    _mount("tmpfs", target, "tmpfs", _MS_NOSUID | _MS_NODEV, f"mode={mode:o}")


def devpts(target: str) -> None:
    """A new instance of devpts on ``target`` (the pseudo-terminals of this attempt only)."""
    _mount("devpts", target, "devpts", _MS_NOSUID | _MS_NOEXEC,
           "newinstance,ptmxmode=0666,mode=620")


def bind(source: str, target: str, *, readonly: bool) -> None:
    """Bind ``source`` on ``target`` (recursively), read-only if asked (nosuid, nodev)."""
    _mount(source, target, None, _MS_BIND | _MS_REC)
    if readonly:
        _mount(None, target, None,
               _MS_BIND | _MS_REMOUNT | _MS_RDONLY | _MS_NOSUID | _MS_NODEV)


def readonly_tree(path: str) -> None:
    """Make the mount at ``path`` and every mount below it read-only (``mount_setattr``).

    Other flags are left as they are (a locked ``nosuid`` stays set): only read-only is
    added, which even a mount locked in a less privileged namespace accepts.
    """
    attr = _MountAttr(_ATTR_RDONLY)
    _syscall("mount_setattr", _AT_FDCWD, path.encode(), _AT_RECURSIVE, ctypes.byref(attr),
             ctypes.sizeof(attr))


def drop_privileges(uid: int | None = None, gid: int | None = None) -> None:
    """Empty the bounding set and every capability set; set ``no_new_privs``.

    ``uid`` and ``gid``: become them (no supplementary groups) once the bounding set is
    empty and before the other sets are, while ``CAP_SETUID`` and ``CAP_SETGID`` still hold.
    """
    for cap in range(_CAP_LAST + 1):
        _LIBC.prctl(_PR_CAPBSET_DROP, cap, 0, 0, 0)  # EINVAL past the kernel's last: fine
    if gid is not None:
        os.setgroups([])
        os.setresgid(gid, gid, gid)
    if uid is not None:
        os.setresuid(uid, uid, uid)
    _checked("no_new_privs", _LIBC.prctl(_PR_SET_NO_NEW_PRIVS, 1, 0, 0, 0))
    _checked("capset", _LIBC.capset(ctypes.byref(_CapHeader(0x20080522, 0)),
                                    (_CapData * 2)()))


def undumpable() -> None:
    """Make the calling process undumpable: no process without ``CAP_SYS_PTRACE`` traces it.

    Nor reads its ``/proc/PID`` files that need that (``mem``, ``environ``, ``fd``, ...).
    """
    _checked("prctl", _LIBC.prctl(_PR_SET_DUMPABLE, 0, 0, 0, 0))


def die_with_parent() -> None:
    """SIGKILL the calling process when its parent (thread) ends."""
    _checked("prctl", _LIBC.prctl(_PR_SET_PDEATHSIG, _SIGKILL, 0, 0, 0))
