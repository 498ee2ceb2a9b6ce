"""A remote worker's disk: its artifact store held under a limit, ended attempts' folders gone.

A remote worker's disk holds two things that only grow if nobody removes them:

- **Attempt folders** (``runs/<workflow>/<task>/<retry>``, with their ``.inputs`` sibling). Once
  the server has acknowledged an attempt's exit report, every byte the server takes of it
  (its output's blobs, its log, streamed as it ran) is safe with the server, and the folder
  is removed (:meth:`StoreKeeper.acknowledged`). Output files share their inodes with the
  store's blobs, so this is also what lets evicting a blob free its space.
- **The artifact store** (``artifacts/``): the outputs this worker produced and the inputs it
  fetched. An output whose report is not acknowledged yet is the only copy (the server pulls
  it from here), and an attempt being prepared reads its inputs from here: both are
  *protected*. Everything else is a cache that saves a fetch when a later task reads it again.
  When the store passes ``limit`` bytes, the manifests the worker remembers holding
  (``osmo.worker.held_inputs``) are forgotten oldest first, down to three quarters of the
  limit, and every blob no protected or remembered manifest names is removed
  (``ArtifactStore.gc``). A forgotten input is fetched again if a task needs it.

``ArtifactStore.gc`` keeps a blob stored or deduplicated less than :data:`GRACE` seconds ago: it
covers the moment between an ingest (or a fetch) storing blobs and the worker recording their
manifest (milliseconds; the store's lock keeps gc out of a running ingest). The limit is a
soft one: protected data and that grace are never removed to meet it.

Collections run on the worker's I/O threads, one at a time, never on the thread that received
an order.
"""

from __future__ import annotations

import logging
import os
import shutil
import threading
import time
from collections.abc import Callable, Collection, Iterable
from concurrent.futures import Executor
from pathlib import Path

from osmo.artifacts import ArtifactStore, Manifest
from osmo.artifacts.fsops import remove_tree
from osmo.layout import Home
from osmo.worker.held_inputs import HeldInputs

__all__ = ["GRACE", "StoreKeeper", "clear_runs", "default_limit"]

log = logging.getLogger("osmo.worker")

GRACE = 5.0
"""Seconds a newly stored blob is safe from collection (see the module docstring)."""


def default_limit(folder: Path) -> int:
    """A quarter of the filesystem that holds ``folder`` (bytes)."""
    return shutil.disk_usage(folder).total // 4


class StoreKeeper:
    """Keeps a worker's disk use bounded (see the module docstring).

    Args:
        home: the worker's home (its attempt folders).
        store: its artifact store.
        held: the manifests it remembers holding.
        limit: bytes the store may hold before a collection (0: no limit).
        protected: the manifests that must stay (unacknowledged outputs, inputs of
            attempts being prepared); called with no lock held.
        io: where collections and folder removals run.
    """

    def __init__(self, home: Home, store: ArtifactStore, held: HeldInputs, limit: int,
                 protected: Callable[[], Iterable[Manifest]], io: Executor) -> None:
        self._home, self._store, self._held = home, store, held
        self._limit, self._protected, self._io = limit, protected, io
        self._lock = threading.Lock()
        self._gate = threading.Lock()
        self._size = 0  # bytes in the store at the last count, plus what was added since
        self._collecting = False
        if limit:
            self._start(self._count_then_collect)

    def added(self, manifest: Manifest) -> None:
        """``manifest``'s blobs were stored (an output ingested, an input fetched)."""
        if self._limit and self._claim(lambda size: size + manifest.size):
            self._start(self._collect_then_again)

    def _claim(self, size: Callable[[int], int]) -> bool:
        """Update the size (``size(old)``); True if a collection is due and now ours to run."""
        with self._lock:
            self._size = size(self._size)
            due = self._size > self._limit and not self._collecting
            self._collecting = self._collecting or due
        return due

    def acknowledged(self, attempt_id: str) -> None:
        """The server has all it takes of ``attempt_id``: remove its folders."""
        dirs = self._home.attempt_of(attempt_id)
        if dirs is not None:
            self._start(_remove_attempt, dirs.root, dirs.url_inputs)

    @property
    def gate(self) -> threading.Lock:
        """Held while a collection decides and removes blobs.

        An attempt's inputs are registered as protected (and checked as held) under it, so
        they are never removed in between.
        """
        return self._gate

    def collect(self) -> tuple[int, int]:
        """Forget the oldest cached manifests and remove unnamed blobs (see the docstring).

        Returns:
            ``(blobs removed, bytes)``.
        """
        try:
            with self._gate:
                keep: dict[str, int] = {}
                for manifest in self._protected():
                    keep.update((e.digest, e.size) for e in manifest.entries)
                budget, total = self._limit * 3 // 4, sum(keep.values())
                forget: list[str] = []
                for manifest in reversed(self._held.snapshot()):  # newest first
                    extra = {e.digest: e.size for e in manifest.entries if e.digest not in keep}
                    if total + sum(extra.values()) > budget:
                        forget.append(manifest.digest)
                        continue
                    keep.update(extra)
                    total += sum(extra.values())
                self._held.forget(forget)
                for manifest in self._held.snapshot():  # held since: named too
                    keep.update((e.digest, e.size) for e in manifest.entries)
                removed, freed = self._store.gc(keep, grace=GRACE)
            if removed:
                log.info("artifact store over its limit: removed %d blob(s), %d bytes",
                         removed, freed)
            return removed, freed
        finally:
            with self._lock:
                self._size = self._store.size()
                self._collecting = False

    def _count_then_collect(self) -> None:
        counted = self._store.size()
        if self._claim(lambda _old: counted):
            self._collect_then_again()

    def _collect_then_again(self) -> None:
        """Collect; still over the limit, once more when the grace of what it kept is past."""
        self.collect()
        with self._lock:
            over = self._size > self._limit
        if over:
            again = threading.Timer(GRACE + 0.5, self._start, args=(self.collect,))
            again.daemon = True
            again.start()

    def _start(self, fn: Callable[..., object], *args: object) -> None:
        try:
            self._io.submit(_logged, fn, *args)
        except RuntimeError:  # the worker is closing: the next start counts again
            with self._lock:
                self._collecting = False


def clear_runs(home: Home, io: Executor, keep: Collection[Path] = ()) -> None:
    """Remove every attempt folder a previous life of the worker left (before it takes work).

    Its attempts were rescheduled when it died, and their reports were never acknowledged;
    but the attempts in ``keep`` (folders the node adopts): they and their workflow's and
    task's folders stay. The folders are renamed at once, and removed on ``io``.
    """
    if not home.runs.exists():
        return
    if keep:
        _clear_but(home, io, {Path(folder) for folder in keep})
        return
    old = home.root / f"runs.old-{os.getpid()}-{time.monotonic_ns()}"
    try:
        home.runs.rename(old)
    except OSError as exc:
        log.warning("could not clear the attempt folders of a previous run: %s", exc)
        return
    for stale in home.root.glob("runs.old-*"):  # this one, and any a crash left
        io.submit(_logged, _remove, stale)


def _clear_but(home: Home, io: Executor, keep: set[Path]) -> None:
    """Move every attempt folder (and its ``.inputs``) but ``keep`` aside, then remove it."""
    old = home.root / f"runs.old-{os.getpid()}-{time.monotonic_ns()}"
    old.mkdir(mode=0o700)
    runs = home.runs.absolute()
    parents = {folder.parent for folder in keep} | {folder.parent.parent for folder in keep}
    for n, path in enumerate(p for p in runs.glob("*/*/*") if p not in keep
                             and p.with_name(p.name.removesuffix(".inputs")) not in keep):
        try:
            path.rename(old / str(n))
        except OSError as exc:
            log.warning("could not clear %s: %s", path, exc)
    for folder in [*runs.glob("*/*"), *runs.glob("*")]:
        if folder not in parents:
            try:
                folder.rmdir()
            except OSError:
                pass  # not empty, or not a folder: it stays
    for stale in home.root.glob("runs.old-*"):
        io.submit(_logged, _remove, stale)


def _remove(folder: Path) -> None:
    remove_tree(folder, ignore_errors=True)


def _remove_attempt(root: Path, url_inputs: Path) -> None:
    _remove(root)
    _remove(url_inputs)
    for folder in (root.parent, root.parent.parent):  # the task's, then the workflow's
        try:
            folder.rmdir()
        except OSError:  # not empty (other attempts), or gone
            return


def _logged(fn: Callable[..., object], *args: object) -> None:
    try:
        fn(*args)
    except Exception:  # an I/O thread's failure must be seen, not lost in a future
        log.exception("worker disk upkeep failed")
