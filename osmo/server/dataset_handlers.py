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
from osmo.names import check_name, check_tag, parse_ref, shown
from osmo.server.datasets import select
from osmo.server.engine import Engine
from osmo.server.requests import AddDatasetVersion, TagDataset
from osmo.transport.rpc import field, str_map

__all__ = ["DatasetHandlers"]


class DatasetHandlers:
    """Handlers for ``datasets_*`` verbs."""

    def __init__(self, engine: Engine, artifacts: ArtifactStore, home: Path,
                 pull: Callable[[dict[str, Any], Manifest], None] | None = None) -> None:
        self._pull = pull  # fetch a manifest's blobs from a client (see WorkerHub.pull)
        self._engine = engine
        self._store = engine.store
        self._artifacts = artifacts
        self._home = home

    def verbs(self) -> dict[str, Any]:
        """Verb name → handler."""
        return {"dataset_list": self.list, "dataset_info": self.info,
                "dataset_tag": self.tag, "dataset_download": self.download,
                "dataset_upload": self.upload}

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

    def upload(self, request: dict[str, Any]) -> dict[str, Any]:
        """Make a new version of ``name`` from the manifest of a client's folder: the blobs
        this server lacks are pulled from the client (``request["source"]``) first."""
        if self._pull is None:
            raise UsageError("this server cannot receive uploads")
        name = check_name(request.get("name"), "dataset name")
        try:
            manifest = Manifest.from_json(field(request, "manifest", str))
        except InfrastructureError as exc:
            raise UsageError(f"'manifest' is not one: {str(exc)[:300]}") from None
        source = field(request, "source", dict)
        metadata = str_map(request, "metadata")
        self._pull(source, manifest)
        version = self._engine.ask(AddDatasetVersion(name, manifest, metadata))
        return {"name": name, "version": version, "manifest": manifest.digest}

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



