"""Files between this machine and a (possibly remote) server, as verified blobs.

Downloads fetch the blobs this machine's cache lacks from the server (hard links when the
server shares this host) and write verified copies; uploads ingest a copy of the folder into
the cache and serve it while the server pulls what it lacks. The cache is
``OSMO_HOME/client/artifacts`` (``osmo artifacts gc`` does not touch it; delete it freely).
"""

from __future__ import annotations

import secrets
import shutil
import tempfile
import uuid
from pathlib import Path
from typing import Any

from osmo.artifacts import ArtifactStore, Manifest
from osmo.config import home_dir
from osmo.layout import Home
from osmo.transport.blobs import SERVER, BlobServer, SameHost, fetch_manifest, host_id
from osmo.transport.zenoh_link import Link

__all__ = ["download", "upload"]


def _cache() -> ArtifactStore:
    return ArtifactStore(Home(home_dir()).client_artifacts)


def _same_host(server: dict[str, Any]) -> SameHost | None:
    if server.get("host_id") == host_id() and server.get("artifacts"):
        return SameHost(Path(server["artifacts"]))
    return None


def download(link: Link, server: dict[str, Any], manifest: Manifest, dest: Path,
             only: str | None = None, token: bytes | None = None) -> list[Path]:
    """Write ``manifest``'s files (or just ``only``) under ``dest``, verified.

    ``token`` goes with every blob request (the server's blob server checks it).
    """
    cache = _cache()
    wanted = Manifest(tuple(e for e in manifest.entries if only is None or e.path == only))
    fetch_manifest(link, SERVER, wanted, cache, same_host=_same_host(server),
                   attachment=token)
    return cache.materialize(manifest, dest, only=only)


class Upload:
    """A folder offered to the server: ``source`` tells the server where to pull from.

    Its blob server answers only requests carrying ``source["key"]``, a random key that
    reaches the server inside the (authenticated) upload request.
    """

    def __init__(self, link: Link, folder: Path) -> None:
        cache = _cache()
        staging = Path(tempfile.mkdtemp(prefix="upload-", dir=cache.tmp))
        try:  # a copy: ingest makes files read-only hard links, the user's stay as they are
            shutil.copytree(folder, staging / "data", symlinks=True)
            self.manifest = cache.ingest(staging / "data")
        finally:
            shutil.rmtree(staging, ignore_errors=True)
        owner = f"client-{uuid.uuid4().hex[:12]}"
        key = secrets.token_bytes(16)
        self.source = {"owner": owner, "host_id": host_id(), "artifacts": str(cache.root),
                       "key": key.hex()}
        self._server = BlobServer(link, owner, cache, lambda att, _digest: att == key)

    def close(self) -> None:
        """Stop serving."""
        self._server.close()


def upload(link: Link, folder: Path) -> Upload:
    """Start offering ``folder``; close the returned :class:`Upload` when the server is done."""
    return Upload(link, folder)
