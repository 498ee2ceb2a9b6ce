"""The kernel's process table, read to recognise a process across a crash.

A pid alone can be reused; a pid with its start time names one process for good. The pool
records both for every command it starts (``osmo.worker.procs``), and after a crash of the
server or a worker :func:`kill_stale` kills what the previous life left running, only if it
is still the same process group. Everything here reads ``/proc`` (Linux).
"""

from __future__ import annotations

import functools
import os
import signal
import time

__all__ = ["group_members", "kill_stale", "process_start_time", "start_clock", "stat_fields"]


def stat_fields(pid: int) -> list[str] | None:
    """Fields of ``/proc/<pid>/stat`` after the command name (field 3 onwards)."""
    try:
        with open(f"/proc/{pid}/stat", "rb") as f:
            data = f.read().decode("ascii", "replace")
    except OSError:
        return None
    return data[data.rfind(")") + 2 :].split()


@functools.cache  # the boot time does not change while this process lives
def _boot_time() -> float:
    with open("/proc/stat") as f:
        for line in f:
            if line.startswith("btime "):
                return float(line.split()[1])
    return 0.0


def start_clock() -> float:
    """Now, on the clock :func:`process_start_time` reads: boot time + time since boot.

    A process's start time is its fork's ``CLOCK_BOOTTIME`` (in clock ticks, truncated), so
    this read just before a spawn is within a tick or a scheduling delay of it.
    """
    return _boot_time() + time.clock_gettime(time.CLOCK_BOOTTIME)


def process_start_time(pid: int) -> float | None:
    """When process ``pid`` started, in seconds since the epoch (``None`` if it is gone).

    Computed from ``/proc/<pid>/stat`` (clock ticks since boot) and the boot time, so the
    same process always gives the same value; store it beside the pid to check later.
    """
    fields = stat_fields(pid)
    if fields is None:
        return None
    ticks = int(fields[19])  # field 22 of stat(5), counted from field 3
    return _boot_time() + ticks / os.sysconf("SC_CLK_TCK")


def group_members(pgid: int) -> list[int]:
    """The pids of the processes in group ``pgid``."""
    members = []
    for name in os.listdir("/proc"):
        if name.isdigit():
            fields = stat_fields(int(name))
            if fields is not None and int(fields[2]) == pgid:
                members.append(int(name))
    return members


def kill_stale(pid: int, started_at: float, *, tolerance: float = 0.5) -> bool:
    """Kill the process group a crashed server left behind, if it is still the same one.

    The group is killed (SIGKILL) only when process ``pid`` is still running with the start
    time recorded (``started_at``, from ``process_start_time``) and leads its group; or,
    when ``pid`` itself is gone, when every remaining member of group ``pid`` started after
    ``started_at`` (a group id stays reserved while members live, so those are its
    leftovers). Never kills by name.

    Returns:
        True if a group was signalled.
    """
    now_start = process_start_time(pid)
    if now_start is not None:
        fields = stat_fields(pid)
        if abs(now_start - started_at) > tolerance or fields is None or int(fields[2]) != pid:
            return False
    else:
        members = group_members(pid)
        starts = [process_start_time(m) for m in members]
        if not members or any(s is None or s < started_at - tolerance for s in starts):
            return False
    try:
        os.killpg(pid, signal.SIGKILL)
    except (ProcessLookupError, PermissionError):
        return False
    return True
