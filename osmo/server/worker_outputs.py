"""A remote attempt's exit, taken in: its outputs fetched and verified before the engine sees it.

An exit report with outputs is handled on a transfer thread (unless every blob is already
here): the blobs the server lacks are fetched from the worker (``osmo.transport.blobs``,
verified by digest), the output folder is linked into the server's ``runs/`` tree (so
downstream tasks and ``osmo artifacts`` find it where local outputs live), and only then does
the engine see the exit; the worker then gets its ``ack``. A transfer that fails makes the
attempt lost (rescheduled); a bug fails it, never leaves it open.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import replace

from osmo.artifacts import ArtifactStore, Manifest
from osmo.errors import OsmoError
from osmo.layout import AttemptDirs, Home
from osmo.scheduler.types import AttemptExited, AttemptLost, Event
from osmo.transport.blobs import Asker, SameHost, fetch_manifest
from osmo.transport.wire import Ack

__all__ = ["OutputIntake"]

log = logging.getLogger("osmo.server.workers")
_INLINE_ENTRIES = 16  # an output this small whose blobs are all here needs no thread hop


class OutputIntake:
    """Takes remote exits in (see the module docstring).

    Args:
        artifacts: the server's artifact store.
        home: the server's home (outputs are linked under ``runs/``).
        emit: the engine's event queue.
        send: ``(worker id, order)`` — the :class:`Ack` after the exit was emitted.
        asker: asks a worker's blob server on its channel (None: it has none open).
        same_host: a worker's same-host details, if it shares this host's store.
    """

    def __init__(self, *, artifacts: ArtifactStore, home: Home,
                 emit: Callable[[Event], None], send: Callable[[str, Ack], None],
                 asker: Callable[[str], Asker | None],
                 same_host: Callable[[str], SameHost | None]) -> None:
        self._artifacts, self._home = artifacts, home
        self._emit, self._send = emit, send
        self._asker, self._same_host = asker, same_host
        self._transfers = ThreadPoolExecutor(4, thread_name_prefix="osmo-pull")

    def exited(self, wid: str, event: AttemptExited) -> None:
        """Take ``event``'s outputs from worker ``wid``, then emit it (inline or on a thread)."""
        manifest = Manifest.from_json(event.manifest) if event.manifest else None
        if self._nothing_to_fetch(manifest):
            self._take(wid, event, manifest)  # a few links at most: no other thread
        else:
            self._transfers.submit(self._take, wid, event, manifest)

    def close(self) -> None:
        """Stop the transfers not started yet."""
        self._transfers.shutdown(wait=False, cancel_futures=True)

    def _nothing_to_fetch(self, manifest: Manifest | None) -> bool:
        if manifest is None:
            return True
        entries = manifest.entries
        return (len(entries) <= _INLINE_ENTRIES
                and all(self._artifacts.has(e.digest) for e in entries))

    def _take(self, wid: str, event: AttemptExited, manifest: Manifest | None) -> None:
        try:
            if manifest is not None:
                t0 = time.perf_counter()
                asker = self._asker(wid)
                if asker is None:
                    raise OsmoError(f"worker {wid} has no open channel to pull from")
                sent = fetch_manifest(asker, wid, manifest, self._artifacts,
                                      same_host=self._same_host(wid))
                if sent:
                    took = time.perf_counter() - t0
                    log.info("outputs of %s: %d bytes fetched from worker %s in %.3fs "
                             "(%.0f MiB/s)", event.attempt_id, sent, wid, took,
                             sent / max(took, 1e-9) / 2**20)
                dirs = _dirs(self._home, event.attempt_id)
                self._artifacts.link_tree(manifest, dirs.output)
                event = replace(event, output=str(dirs.output))
            else:
                event = replace(event, output=None)
        except (OsmoError, OSError) as exc:
            log.warning("outputs of %s from worker %s: %s", event.attempt_id, wid, exc)
            self._emit(AttemptLost(event.attempt_id, f"outputs could not be taken from worker "
                                                      f"{wid}: {exc}"))
            return
        except Exception as exc:  # noqa: BLE001 - a bug: fail the attempt, never leave it open
            log.exception("outputs of %s from worker %s", event.attempt_id, wid)
            event = replace(event, output=None, manifest=None,
                            message=f"outputs could not be promoted: {exc!r}")
        self._emit(event)
        self._send(wid, Ack(event.attempt_id))


def _dirs(home: Home, attempt_id: str) -> AttemptDirs:
    dirs = home.attempt_of(attempt_id)
    if dirs is None:
        raise OsmoError(f"malformed attempt id {attempt_id!r}")
    return dirs
