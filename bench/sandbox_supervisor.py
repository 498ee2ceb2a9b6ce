"""Prototype (issue 16): one long-lived bubblewrap, a fresh mount and pid namespace per task.

Not used by osmo: it measures what a task start would cost if a pool slot kept one sandbox
(bwrap with the parts every task shares: the host read-only, a minimal ``/dev``) and a small
supervisor inside it made, for each task, what bwrap makes today:

1. fork; the child unshares a mount and a pid namespace, mounts a private ``/tmp`` and
   ``/dev/shm``, hides osmo's home under a tmpfs and binds the attempt's folders back
   (read-only with writable children), all with plain ``mount(2)`` calls: no
   ``/proc/self/mountinfo`` read, which is a third of bwrap's CPU;
2. it forks the namespace's pid 1, which mounts its own ``/proc`` and forks the command;
3. the command drops every capability (the supervisor keeps ``CAP_SYS_ADMIN`` for the
   mounts: bwrap run by root keeps root's) and execs.

The supervisor reads one start per line on stdin (``cwd`` and argv, tab-separated; the view
is the fixed one the bench passes with ``--home``/``--attempt``) and writes ``exit-code`` per
line on stdout, in order. ``bench_sandbox.py --supervisor`` drives it under ``perf stat``.

Usage (inside bwrap, as root): python bench/sandbox_supervisor.py --home H --attempt A
"""

from __future__ import annotations

import argparse
import ctypes
import ctypes.util
import os
import sys

_LIBC = ctypes.CDLL(ctypes.util.find_library("c"), use_errno=True)
_MS_RDONLY, _MS_NOSUID, _MS_NODEV, _MS_NOEXEC = 1, 2, 4, 8
_MS_REMOUNT, _MS_BIND, _MS_MOVE, _MS_REC, _MS_PRIVATE = 32, 4096, 8192, 16384, 1 << 18
_PR_CAPBSET_DROP, _PR_SET_NO_NEW_PRIVS, _PR_SET_PDEATHSIG = 24, 38, 1
_CAP_LAST = 40


def _mount(source: str, target: str, fstype: str | None, flags: int, data: str = "") -> None:
    if _LIBC.mount(source.encode(), target.encode(), fstype.encode() if fstype else None,
                   flags, data.encode() or None) != 0:
        errno = ctypes.get_errno()
        raise OSError(errno, f"mount {source} on {target}: {os.strerror(errno)}")


def _bind(source: str, target: str, readonly: bool) -> None:
    _mount(source, target, None, _MS_BIND)
    flags = _MS_REMOUNT | _MS_BIND | _MS_NOSUID | _MS_NODEV | (_MS_RDONLY if readonly else 0)
    _mount("none", target, None, flags)


def _drop_capabilities() -> None:
    for cap in range(_CAP_LAST + 1):
        _LIBC.prctl(_PR_CAPBSET_DROP, cap, 0, 0, 0)
    _LIBC.prctl(_PR_SET_NO_NEW_PRIVS, 1, 0, 0, 0)

    class Header(ctypes.Structure):
        _fields_ = [("version", ctypes.c_uint32), ("pid", ctypes.c_int)]

    class Data(ctypes.Structure):
        _fields_ = [("effective", ctypes.c_uint32), ("permitted", ctypes.c_uint32),
                    ("inheritable", ctypes.c_uint32)]

    header, data = Header(0x20080522, 0), (Data * 2)()
    if _LIBC.capset(ctypes.byref(header), data) != 0:
        raise OSError(ctypes.get_errno(), "capset")


def _task(home: str, attempt: str, cwd: str, argv: list[str]) -> int:
    """In a fork of the supervisor: the namespaces, the view, pid 1; returns the exit code.

    The attempt's folders are bound onto a staging folder in the task's own ``/dev/shm``
    first, then moved (``MS_MOVE``, with their writable children) under the tmpfs that hides
    the home: once hidden, they could not be bound from.
    """
    os.unshare(os.CLONE_NEWNS | os.CLONE_NEWPID)
    _mount("none", "/", None, _MS_REC | _MS_PRIVATE)
    _mount("tmpfs", "/dev/shm", "tmpfs", _MS_NOSUID | _MS_NODEV, "mode=1777")
    stage = "/dev/shm/.attempt"
    os.mkdir(stage)
    _bind(attempt, stage, readonly=True)
    for name in ("work", "output.partial", "files"):
        _bind(os.path.join(attempt, name), os.path.join(stage, name), readonly=False)
    _mount("tmpfs", "/tmp", "tmpfs", _MS_NOSUID | _MS_NODEV, "mode=1777")
    os.makedirs(home, exist_ok=True)  # gone with the host's /tmp when it lies there
    _mount("tmpfs", home, "tmpfs", _MS_NOSUID | _MS_NODEV, "mode=0755")
    os.makedirs(attempt)
    _mount(stage, attempt, None, _MS_MOVE)
    os.rmdir(stage)
    init = os.fork()
    if init == 0:
        os._exit(_init(cwd, argv))
    return os.waitstatus_to_exitcode(os.waitpid(init, 0)[1])


def _init(cwd: str, argv: list[str]) -> int:
    """pid 1 of the task's namespace: its own /proc, then the command as pid 2."""
    _mount("proc", "/proc", "proc", _MS_NOSUID | _MS_NODEV | _MS_NOEXEC)
    command = os.fork()
    if command == 0:
        try:
            _drop_capabilities()
            os.chdir(cwd)
            os.execvp(argv[0], argv)
        finally:
            os._exit(127)
    while True:  # pid 1 reaps every orphan until the command itself ends
        pid, status = os.wait()
        if pid == command:
            return os.waitstatus_to_exitcode(status)


def main() -> None:
    """Serve starts from stdin until it closes."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--home", required=True)
    parser.add_argument("--attempt", required=True)
    args = parser.parse_args()
    _LIBC.prctl(_PR_SET_PDEATHSIG, 9, 0, 0, 0)
    for line in sys.stdin:
        cwd, *argv = line.rstrip("\n").split("\t")
        child = os.fork()
        if child == 0:
            try:
                code = _task(args.home, args.attempt, cwd, argv)
            except BaseException as exc:  # noqa: BLE001 - a prototype: report and exit
                print(f"setup failed: {exc}", file=sys.stderr)
                code = 255
            os._exit(code)
        code = os.waitstatus_to_exitcode(os.waitpid(child, 0)[1])
        sys.stdout.write(f"{code}\n")
        sys.stdout.flush()


if __name__ == "__main__":
    main()
