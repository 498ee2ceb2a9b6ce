"""API verbs for datasets: list, info, tag, download, upload.

Writes (tag, upload) run on the engine thread like every other state change; reads go to the
store. Files travel between the client's machine and the server as blobs
(``osmo.transport.blobs``): ``download`` hands the client the version's manifest and the
client fetches what it lacks; ``upload`` gets a manifest of the client's folder and the server
pulls the blobs it lacks from the client.
"""

from __future__ import annotations

import re
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

from osmo.artifacts import ArtifactStore, Manifest
from osmo.errors import InfrastructureError, NotFoundError, UsageError
from osmo.names import check_name, check_tag, check_worker_name, parse_ref, shown
from osmo.server.datasets import select
from osmo.server.engine import Engine
from osmo.server.requests import AddDatasetVersion, TagDataset
from osmo.transport.auth import Identity
from osmo.transport.blobs import SERVER, Asker, SameHost, fetch_manifest, host_id
from osmo.transport.rpc import field, str_map

__all__ = ["DatasetHandlers"]

_MAX_TEXT = 4096  # characters of an owner, a host id or a folder in a request


class DatasetHandlers:
    """Handlers for ``dataset_*`` verbs.

    Args:
        asker_of: asks a caller's own blob server on the caller's channel, to pull an
            upload's blobs from it (None: this server takes no uploads).
    """

    def __init__(self, engine: Engine, artifacts: ArtifactStore,
                 asker_of: Callable[[Identity], Asker | None] | None = None) -> None:
        self._asker_of = asker_of
        self._engine = engine
        self._store = engine.store
        self._artifacts = artifacts

    def list(self, request: dict[str, Any]) -> list[dict[str, Any]]:
        """Every version (of one dataset), newest first, with size and tags."""
        name = request.get("name")
        if name is not None:
            check_name(name, "dataset name")
        return [self._public(row) for row in self._store.datasets(name)]

    def info(self, request: dict[str, Any]) -> dict[str, Any]:
        """One version with its files and what made it."""
        row = self._row(request.get("ref"))
        body = self._store.manifest_body(row["manifest"]) or '{"entries": []}'
        files = [vars(e) for e in Manifest.from_json(body).entries]
        return {**self._public(row), "files": files}

    def tag(self, request: dict[str, Any]) -> dict[str, Any]:
        """Point ``tag`` at a version (moving it if it pointed elsewhere)."""
        tag = check_tag(request.get("tag"))
        row = self._row(request.get("ref"))
        self._engine.ask(TagDataset(row["name"], tag, row["version"]))
        return {"name": row["name"], "version": row["version"], "tag": tag}

    def download(self, request: dict[str, Any]) -> dict[str, Any]:
        """A version's manifest (``regex`` applied); the client fetches the blobs."""
        regex = field(request, "regex", str, default=None, max_len=1000)
        try:
            re.compile(regex or "")
        except re.error as exc:
            raise UsageError(f"--regex {shown(regex)} is not a valid regular expression: "
                             f"{exc}") from None
        row = self._row(request.get("ref"))
        body = self._store.manifest_body(row["manifest"])
        assert body is not None
        manifest = select(Manifest.from_json(body), path=None, regex=regex)
        return {"manifest": manifest.to_json(), "version": row["version"]}

    def upload(self, request: dict[str, Any], who: Identity) -> dict[str, Any]:
        """Make a new version of ``name`` from the manifest of a client's folder.

        The blobs this server lacks are pulled from the client (``request["source"]``) first,
        on the channel this request came on.
        """
        asker = self._asker_of(who) if self._asker_of is not None else None
        if asker is None:
            raise UsageError("this server cannot receive uploads")
        name = check_name(request.get("name"), "dataset name")
        try:
            manifest = Manifest.from_json(field(request, "manifest", str))
        except InfrastructureError as exc:
            raise UsageError(f"'manifest' is not one: {str(exc)[:300]}") from None
        source = field(request, "source", dict)
        metadata = str_map(request, "metadata")
        self._pull(asker, source, manifest)
        version = self._engine.ask(AddDatasetVersion(name, manifest, metadata))
        return {"name": name, "version": version, "manifest": manifest.digest}

    def _pull(self, asker: Asker, source: dict[str, Any], manifest: Manifest) -> None:
        """Fetch ``manifest``'s blobs from the client that serves them.

        It serves them as ``source["owner"]``; they are linked from ``source["artifacts"]`` instead
        when ``source["host_id"]`` is this host.

        Raises:
            UsageError: ``source`` is not such an object.
        """
        owner = check_worker_name(field(source, "owner", str, max_len=_MAX_TEXT,
                                        what="'source.owner'"), reserved=(SERVER,))
        host = field(source, "host_id", str, default=None, max_len=_MAX_TEXT,
                     what="'source.host_id'")
        artifacts = field(source, "artifacts", str, default=None, max_len=_MAX_TEXT,
                          what="'source.artifacts'")
        same = SameHost(Path(artifacts)) if host == host_id() and artifacts else None
        fetch_manifest(asker, owner, manifest, self._artifacts, same_host=same)

    def _row(self, ref: object) -> dict[str, Any]:
        name, tag = parse_ref(ref)
        row = self._store.dataset(name, tag)
        if row is None:
            raise NotFoundError(f"dataset '{ref}' does not exist")
        return row

    def _public(self, row: dict[str, Any]) -> dict[str, Any]:
        body = self._store.manifest_body(row["manifest"]) or '{"entries": []}'
        manifest = Manifest.from_json(body)
        return {"name": row["name"], "version": row["version"], "tags": row["tags"],
                "manifest": row["manifest"], "files": len(manifest.entries),
                "size": manifest.size, "created_at": row["created_at"],
                "made_by": row["attempt_id"], "metadata": row["metadata"],
                "created": time.strftime("%Y/%m/%d %H:%M:%S",
                                         time.localtime(row["created_at"]))}



