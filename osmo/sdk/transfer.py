"""Files between this machine and a (possibly remote) server, as verified blobs.

Downloads fetch the blobs this machine's cache lacks from the server (hard links when the
server shares this host) and write verified copies; uploads ingest a copy of the folder into
the cache and serve it while the server pulls what it lacks. The cache is
``OSMO_HOME/client/artifacts`` (``osmo artifacts gc`` does not touch it; delete it freely).
"""

from __future__ import annotations

import shutil
import tempfile
import uuid
from pathlib import Path
from typing import Any

from osmo.artifacts import ArtifactStore, Manifest
from osmo.config import home_dir
from osmo.layout import Home
from osmo.transport.blobs import SERVER, BlobServer, SameHost, fetch_manifest, host_id
from osmo.transport.rpc import ApiClient

__all__ = ["download", "upload"]


def _cache() -> ArtifactStore:
    return ArtifactStore(Home(home_dir()).client_artifacts)


def _same_host(server: dict[str, Any]) -> SameHost | None:
    if server.get("host_id") == host_id() and server.get("artifacts"):
        return SameHost(Path(server["artifacts"]))
    return None


def download(api: ApiClient, server: dict[str, Any], manifest: Manifest, dest: Path,
             only: str | None = None) -> list[Path]:
    """Write ``manifest``'s files (or just ``only``) under ``dest``, verified.

    Every blob request is sealed on ``api``'s channel (the server's blob server checks it).
    """
    cache = _cache()
    wanted = Manifest(tuple(e for e in manifest.entries if only is None or e.path == only))
    fetch_manifest(api, SERVER, wanted, cache, same_host=_same_host(server))
    return cache.materialize(manifest, dest, only=only)


class Upload:
    """A folder offered to the server: ``source`` tells the server where to pull from.

    Its blob server answers only the server's requests sealed on ``api``'s channel (the one
    the upload request itself comes on).
    """

    def __init__(self, api: ApiClient, folder: Path) -> None:
        cache = _cache()
        staging = Path(tempfile.mkdtemp(prefix="upload-", dir=cache.tmp))
        try:  # a copy: ingest makes files read-only hard links, the user's stay as they are
            shutil.copytree(folder, staging / "data", symlinks=True)
            self.manifest = cache.ingest(staging / "data")
        finally:
            shutil.rmtree(staging, ignore_errors=True)
        owner = f"client-{uuid.uuid4().hex[:12]}"
        self.source = {"owner": owner, "host_id": host_id(), "artifacts": str(cache.root)}
        api.channel()  # the server pulls on it: open before the upload request names it
        self._server = BlobServer(api.link, owner, cache, api.open_asked)

    def close(self) -> None:
        """Stop serving."""
        self._server.close()


def upload(api: ApiClient, folder: Path) -> Upload:
    """Start offering ``folder``; close the returned :class:`Upload` when the server is done."""
    return Upload(api, folder)
