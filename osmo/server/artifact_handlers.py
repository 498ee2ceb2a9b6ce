"""API verbs for artifacts and lineage: list, get and gc of promoted outputs, lineage graphs.

Reads go to the store; the client fetches the blobs a manifest names itself
(``osmo.transport.blobs``).
"""

from __future__ import annotations

import builtins
from collections.abc import Callable
from typing import Any

from osmo.artifacts import ArtifactStore, Manifest
from osmo.errors import NotFoundError
from osmo.names import check_name
from osmo.server.lineage_query import lineage_graph, resolve_target
from osmo.store.sqlite import Store, WorkflowRow
from osmo.transport.rpc import field

__all__ = ["ArtifactHandlers"]

_MAX_TEXT = 4096  # characters of an artifact target in a request


class ArtifactHandlers:
    """Handlers for ``lineage`` and the ``artifact_*`` verbs.

    Args:
        store: the state store.
        artifacts: the blob store.
        row_of: the workflow a request names (``Handlers._row``: NotFoundError with hints).
    """

    def __init__(self, store: Store, artifacts: ArtifactStore,
                 row_of: Callable[[object], WorkflowRow]) -> None:
        self._store, self._artifacts, self._row = store, artifacts, row_of

    def lineage(self, request: dict[str, Any]) -> dict[str, Any]:
        """The lineage graph of a target (see ``osmo.server.lineage_query``)."""
        return lineage_graph(self._store, _target(request),
                             downstream=field(request, "downstream", bool, default=False))

    def artifact_list(self, request: dict[str, Any]) -> builtins.list[dict[str, Any]]:
        """Promoted outputs of a workflow (optionally one task) with their files."""
        row = self._row(request.get("workflow_id"))
        task = field(request, "task", str, default=None)
        if task is not None:
            check_name(task, "task name")
        out = []
        for output in self._store.outputs(row.id, task):
            body = self._store.manifest_body(output["manifest"]) or '{"entries": []}'
            files = [vars(e) for e in Manifest.from_json(body).entries]
            out.append({**output, "files": files})
        if task and not out:
            raise NotFoundError(f"task '{task}' of {row.id} has no recorded output")
        return out

    def artifact_get(self, request: dict[str, Any]) -> dict[str, Any]:
        """A target's manifest, and the one file meant if it names a file.

        The client fetches the blobs and writes the files.
        """
        manifests, blob = resolve_target(self._store, _target(request))
        body = self._store.manifest_body(manifests[0])
        assert body is not None
        manifest = Manifest.from_json(body)
        only = next((e.path for e in manifest.entries if e.digest == blob), None) if blob else None
        return {"manifest": manifests[0], "body": body, "only": only}

    def artifact_gc(self, _request: dict[str, Any]) -> dict[str, Any]:
        """Remove blobs no recorded manifest references (recent blobs are kept)."""
        count, size = self._artifacts.gc(self._store.all_blob_digests())
        return {"removed": count, "bytes": size}


def _target(request: dict[str, Any]) -> str:
    """An artifact target: ``sha256:...``, ``WORKFLOW_ID:TASK[:PATH]`` or ``dataset:REF``.

    ``osmo.server.lineage_query`` checks what it names.
    """
    target: str = field(request, "target", str, max_len=_MAX_TEXT)
    return target
