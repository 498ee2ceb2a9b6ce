"""Mounts that appear and vanish while sandboxes start: the race bubblewrap's setup loses.

A read-only bind of a system folder (``--ro-bind /opt /opt``) copies every mount below it
and then remounts each read-only; a mount in a shared peer group (podman's overlays) that
is unmounted in between makes bwrap fail with ``Can't bind mount /oldroot/...: ... Invalid
argument``. :func:`churning_mounts` reproduces that: a scratch folder under ``/opt`` (a
folder every sandbox shows), made a shared mount,
with tmpfs mounts made and removed under it in a loop. Root only (skips otherwise).
"""

from __future__ import annotations

import contextlib
import ctypes
import os
import tempfile
import threading
from collections.abc import Iterator

import pytest

_MS_BIND = 4096
_MS_SHARED = 1 << 20
_MNT_DETACH = 2
_libc = ctypes.CDLL(None, use_errno=True)


def _mount(source: str, target: str, fstype: str | None, flags: int) -> int:
    return int(_libc.mount(source.encode(), target.encode(),
                           fstype.encode() if fstype else None, flags, None))


def _umount(target: str) -> None:
    _libc.umount2(target.encode(), _MNT_DETACH)


@contextlib.contextmanager
def churning_mounts(count: int = 20, pause: float = 0.0) -> Iterator[None]:
    """While inside: ``count`` tmpfs mounts appear and vanish under a shared scratch mount.

    ``pause``: seconds between rounds (fewer vanishing mounts per second).
    """
    if os.geteuid() != 0:
        pytest.skip("making and removing mounts needs root")
    root = tempfile.mkdtemp(prefix="osmo-churn-", dir="/opt")
    folders = [os.path.join(root, str(i)) for i in range(count)]
    for folder in folders:
        os.mkdir(folder)
    stop = threading.Event()

    def churn() -> None:
        while not stop.is_set():
            for folder in folders:
                _mount("none", folder, "tmpfs", 0)
            for folder in folders:
                _umount(folder)
            stop.wait(pause)

    worker = threading.Thread(target=churn, name="churn", daemon=True)
    try:
        if _mount(root, root, None, _MS_BIND) != 0 or _mount("none", root, None, _MS_SHARED):
            pytest.skip(f"cannot make a shared mount: {os.strerror(ctypes.get_errno())}")
        worker.start()
        yield
    finally:
        stop.set()
        if worker.is_alive():
            worker.join()
        for folder in folders:
            _umount(folder)
        _umount(root)
        for folder in folders:
            os.rmdir(folder)
        os.rmdir(root)
