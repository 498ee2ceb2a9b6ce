"""What the engine settles for a placed attempt before it is prepared on a worker.

:class:`Placements` resolves a ``PrepareAttempt`` once its placement is committed: dataset
and other-workflow inputs, the cache key (``osmo.server.cache``) and a cache hit, and what
provenance must remember for the attempt's lineage. When the command is executed, the
attempt is then prepared on its executor, completed from the cache at once (the scheduler
sees an ordinary success), or failed to start with the reason its inputs could not be
resolved. Runs on the engine thread only; must not touch the scheduler.
"""

from __future__ import annotations

import functools
import logging
from collections.abc import Callable

from osmo.artifacts import Manifest
from osmo.errors import OsmoError
from osmo.executor import Executor
from osmo.runtime.choose import container_image
from osmo.scheduler.types import (
    AttemptExited,
    AttemptPrepared,
    AttemptStarted,
    AttemptStartFailed,
    Event,
    PrepareAttempt,
)
from osmo.server import cache
from osmo.server.cache import CacheHit
from osmo.server.datasets import Datasets
from osmo.server.provenance import Provenance
from osmo.spec.model import WorkflowSpec
from osmo.status import CACHED_MESSAGE
from osmo.store.sqlite import Store

__all__ = ["Placements", "output_manifests"]

log = logging.getLogger("osmo.server")


class Placements:
    """Placed attempts between their commit and their preparation (engine thread).

    Args:
        store: read for input manifests and cache entries.
        specs: workflow id → spec, shared with the engine (kept current by it).
        reuse: workflow id → True if submitted with ``--reuse``, False with ``--no-cache``
            (absent: neither), shared with the engine.
        post: queues an event for the engine.
        provenance: remembers each placement for its lineage.
        datasets: resolves dataset and other-workflow inputs (None: none to resolve).
        image_ids: ``(workflow id, image) → id`` on this host (None: not here), when image
            tasks run in containers (``cache`` uses the id).
    """

    def __init__(self, *, store: Store, specs: dict[str, WorkflowSpec], reuse: dict[str, bool],
                 post: Callable[[Event], None], provenance: Provenance,
                 datasets: Datasets | None,
                 image_ids: Callable[[str, str], str | None] | None = None) -> None:
        self._store, self._specs, self._reuse = store, specs, reuse
        self._post = post
        self._provenance, self._datasets = provenance, datasets
        self._ready: dict[str, PrepareAttempt | str] = {}  # the final command, or why not
        self._hits: dict[str, CacheHit] = {}
        self._image_ids = image_ids

    def resolve(self, cmd: PrepareAttempt) -> None:
        """Settle what a placed attempt needs before it is prepared.

        Its dataset and other-workflow inputs, its cache key, and a cache hit if there is one. Never
        raises: a failure is kept as the reason the attempt cannot start.
        """
        settled = self._settle(cmd)
        if isinstance(settled, str):
            self._ready[cmd.attempt_id] = settled
            return
        cmd, hit = settled
        self._ready[cmd.attempt_id] = cmd
        if hit is not None:
            self._hits[cmd.attempt_id] = hit

    def recall(self, cmd: PrepareAttempt) -> None:
        """Remember an attempt an earlier server placed, for its lineage; nothing is prepared.

        A restarted server calls this for each attempt still running on a remote worker, so
        that its exit under this server records its output and lineage. Never raises.
        """
        settled = self._settle(cmd)
        if isinstance(settled, str):
            log.warning("attempt %s: its inputs cannot be resolved again (%s); its output "
                        "will have no lineage", cmd.attempt_id, settled)

    def _settle(self, cmd: PrepareAttempt) -> tuple[PrepareAttempt, CacheHit | None] | str:
        """Resolve ``cmd``'s inputs and cache key and remember its placement in provenance.

        Returns:
            the resolved command and a cache hit (or None), or why its inputs cannot be had.
        """
        try:
            if self._datasets is not None:
                cmd = self._datasets.resolve_inputs(cmd, self._specs[cmd.workflow_id].task(
                    cmd.task))
            sources = cache.input_sources(self._store, cmd)
            spec = self._specs[cmd.workflow_id]
            task = spec.task(cmd.task)
            image = container_image(task) if self._image_ids is not None else None
            image_id = self._image_ids(cmd.workflow_id, image) if (
                self._image_ids is not None and image is not None) else None
            contained = image is not None
            key = cache.key(cmd, task, sources, contained=contained, image_id=image_id)
            reuses = cache.reuses(spec, task, submitted=self._reuse.get(cmd.workflow_id))
            hit = cache.lookup(self._store, key) if key and reuses else None
        except OsmoError as exc:
            return str(exc)
        except Exception as exc:  # noqa: BLE001 - fails this attempt's start, nothing else
            log.exception("resolving the inputs of %s failed", cmd.attempt_id)
            return f"cannot resolve its inputs: {exc!r}"
        self._provenance.placed(cmd, cmd.hosts.get(cmd.task, cmd.node_id), key, sources,
                                image_id=image_id)
        return cmd, hit

    def prepare(self, cmd: PrepareAttempt, executor: Executor | None) -> None:
        """Execute a placement: prepare it, complete it from the cache, or fail its start.

        It is prepared on ``executor``, the one of its node, its output limited to the task's
        ``storage``.
        """
        ready = self._ready.pop(cmd.attempt_id, cmd)
        hit = self._hits.pop(cmd.attempt_id, None)
        if isinstance(ready, str):
            self._post(AttemptStartFailed(cmd.attempt_id, ready))
        elif hit is not None:
            self._replay(ready, hit)
        elif executor is None:
            self._post(AttemptStartFailed(cmd.attempt_id,
                                          f"no executor runs node '{cmd.node_id}'"))
        else:
            spec = self._specs[ready.workflow_id]
            task = spec.task(ready.task)
            request = spec.resource_for(task)
            executor.prepare(ready, task, max_output_bytes=request.storage, resources=request)

    def _replay(self, cmd: PrepareAttempt, hit: CacheHit) -> None:
        """Complete a cache hit at once: the scheduler sees an ordinary successful attempt."""
        message = CACHED_MESSAGE + hit.attempt_id
        for event in (AttemptPrepared(cmd.attempt_id), AttemptStarted(cmd.attempt_id),
                      AttemptExited(cmd.attempt_id, 0, hit.output_path, message,
                                    manifest=hit.manifest_body, cached=True)):
            self._post(event)


def output_manifests(store: Store) -> Callable[[str], Manifest | None]:
    """``folder → manifest`` of recorded output folders (task outputs, dataset versions).

    How a pool on this host finds what to copy for an attempt's inputs. Parsed manifests are kept by
    digest (a fan-out reads the same one a thousand times).
    """

    @functools.lru_cache(maxsize=256)
    def parsed(digest: str) -> Manifest | None:
        body = store.manifest_body(digest)
        return Manifest.from_json(body) if body is not None else None

    def lookup(ref: str) -> Manifest | None:
        found = store.output_of(ref)
        return parsed(found[0]) if found is not None else None

    return lookup
