"""What this machine offers a local pool: cpus, memory, gpus, disk; its GPUs by index.

Reads of /proc, /dev and the filesystem, and process limits; :class:`GpuSlots` is the pool's
one piece of state here: which GPU index each running attempt holds.
"""

from __future__ import annotations

import glob
import os
import resource
import shutil
import threading
from pathlib import Path

from osmo.scheduler.types import Capacity

__all__ = ["GpuSlots", "detect_capacity", "raise_fd_limit"]


def detect_capacity(home: Path, *, cpus: float | None = None, gpus: int | None = None,
                    memory: int | None = None) -> Capacity:
    """The machine's capacity; explicit values override what is detected.

    cpus default to the core count, gpus to the number of ``/dev/nvidia<N>`` devices, memory
    to MemTotal, storage to the free space under ``home``.
    """
    return Capacity(
        cpu=float(cpus if cpus is not None else os.cpu_count() or 1),
        gpu=gpus if gpus is not None else len(glob.glob("/dev/nvidia[0-9]*")),
        memory=memory if memory is not None else _mem_total(),
        storage=shutil.disk_usage(home).free,
    )


def raise_fd_limit(wanted: int = 65536) -> None:
    """Lift this process's soft open-files limit toward the hard one.

    Each running attempt holds four descriptors (two pipes, a pidfd, its log), so the usual
    soft limit of 1024 would cap the pool near 250 concurrent attempts.
    """
    soft, hard = resource.getrlimit(resource.RLIMIT_NOFILE)
    target = wanted if hard == resource.RLIM_INFINITY else min(wanted, hard)
    if soft != resource.RLIM_INFINITY and soft < target:
        try:
            resource.setrlimit(resource.RLIMIT_NOFILE, (target, hard))
        except (ValueError, OSError):
            pass  # keep the limit we have; starts then fail with a clear message


def _mem_total() -> int:
    """MemTotal from /proc/meminfo, in bytes (0 if unknown)."""
    try:
        with open("/proc/meminfo") as f:
            for line in f:
                if line.startswith("MemTotal:"):
                    return int(line.split()[1]) * 1024
    except OSError:
        pass
    return 0


class GpuSlots:
    """Which of a node's GPU indices each running attempt holds (the pool's assignment).

    The scheduler counts GPUs; this names them, so two tasks never share one (a container
    task sees exactly its own: ``osmo.runtime.container``). Thread-safe.
    """

    def __init__(self, count: int) -> None:
        self._free = list(range(count))
        self._held: dict[str, tuple[int, ...]] = {}
        self._lock = threading.Lock()

    def take(self, attempt_id: str, count: int) -> tuple[int, ...]:
        """Assign ``count`` free indices to ``attempt_id`` (as many as are free)."""
        with self._lock:
            taken, self._free = tuple(self._free[:count]), self._free[count:]
            self._held[attempt_id] = taken
            return taken

    def give_back(self, attempt_id: str) -> None:
        """Free what ``attempt_id`` held (nothing held is fine)."""
        with self._lock:
            self._free = sorted([*self._free, *self._held.pop(attempt_id, ())])
