"""Files between this machine and a (possibly remote) server, as verified blobs.

Downloads fetch the blobs this machine's cache lacks from the server (hard links when the
server shares this host) and write verified copies; uploads ingest a copy of the folder into
the cache and serve it while the server pulls what it lacks. The cache is
``client/artifacts`` in the client's home, ``OSMO_HOME`` unless it names another (``osmo
artifacts gc`` does not touch it; delete it freely).

Either way can report its progress to a :data:`Progress` callback: bytes fetched (a blob
linked on the same host, or resumed, counts when it is done), or bytes the server pulled.
Drawing it is the caller's business (the CLI's ``osmo.cli.render``).
"""

from __future__ import annotations

import shutil
import tempfile
import threading
import uuid
from collections.abc import Callable
from pathlib import Path
from typing import Any

from osmo.artifacts import ArtifactStore, Manifest
from osmo.layout import Home
from osmo.transport.blobs import (
    SERVER,
    BlobServer,
    Opener,
    SameHost,
    fetch_blob,
    fetch_manifest,
    host_id,
)
from osmo.transport.rpc import ApiClient

__all__ = ["Progress", "download", "upload"]

Progress = Callable[[int, int], None]
"""``(bytes done, bytes in all)`` of a transfer, called as it goes (first with 0 done)."""


def _cache(home: Home) -> ArtifactStore:
    return ArtifactStore(home.client_artifacts)


def _same_host(server: dict[str, Any]) -> SameHost | None:
    if server.get("host_id") == host_id() and server.get("artifacts"):
        return SameHost(Path(server["artifacts"]))
    return None


def download(api: ApiClient, server: dict[str, Any], manifest: Manifest, dest: Path,
             only: str | None = None, on_progress: Progress | None = None, *,
             home: Home) -> list[Path]:
    """Write ``manifest``'s files (or just ``only``) under ``dest``, verified.

    Every blob request is sealed on ``api``'s channel (the server's blob server checks it).
    ``on_progress`` hears of the bytes this machine's cache (``home``'s) lacked.
    """
    cache = _cache(home)
    wanted = Manifest(tuple(e for e in manifest.entries if only is None or e.path == only))
    if on_progress is None:
        fetch_manifest(api, SERVER, wanted, cache, same_host=_same_host(server))
    else:
        _fetch_counted(api, wanted, cache, _same_host(server), on_progress)
    return cache.materialize(manifest, dest, only=only)


def _fetch_counted(api: ApiClient, manifest: Manifest, cache: ArtifactStore,
                   same_host: SameHost | None, on_progress: Progress) -> None:
    """``fetch_manifest``, telling ``on_progress`` of each chunk that arrives."""
    sizes = {e.digest: e.size for e in manifest.entries if not cache.has(e.digest)}
    total, done = sum(sizes.values()), 0
    on_progress(0, total)

    def arrived(n: int) -> None:
        nonlocal done
        done += n
        on_progress(done, total)

    for digest, size in sizes.items():
        before = done
        fetch_blob(api, SERVER, digest, size, cache, same_host=same_host, on_bytes=arrived)
        done = before + size  # linked or resumed bytes count once the blob is here
        on_progress(done, total)


class Upload:
    """A folder offered to the server: ``source`` tells the server where to pull from.

    Its blob server answers only the server's requests sealed on ``api``'s channel (the one
    the upload request itself comes on). ``size``: the bytes of its distinct files, what the
    server pulls if it holds none of them. The copy is staged in ``home``'s cache.
    """

    def __init__(self, api: ApiClient, folder: Path, on_progress: Progress | None = None, *,
                 home: Home) -> None:
        cache = _cache(home)
        staging = Path(tempfile.mkdtemp(prefix="upload-", dir=cache.tmp))
        try:  # a copy: ingest makes files read-only hard links, the user's stay as they are
            shutil.copytree(folder, staging / "data", symlinks=True)
            self.manifest = cache.ingest(staging / "data")
        finally:
            shutil.rmtree(staging, ignore_errors=True)
        owner = f"client-{uuid.uuid4().hex[:12]}"
        self.source = {"owner": owner, "host_id": host_id(), "artifacts": str(cache.root)}
        sizes = {e.digest.removeprefix("sha256:"): e.size for e in self.manifest.entries}
        self.size = sum(sizes.values())
        api.channel()  # the server pulls on it: open before the upload request names it
        opener = (api.open_asked if on_progress is None
                  else _counting(api.open_asked, sizes, on_progress))
        self._server = BlobServer(api.link, owner, cache, opener)

    def close(self) -> None:
        """Stop serving."""
        self._server.close()


def upload(api: ApiClient, folder: Path, on_progress: Progress | None = None, *,
           home: Home) -> Upload:
    """Start offering ``folder``; close the returned :class:`Upload` when the server is done.

    ``on_progress`` hears of the bytes the server pulls (blobs it holds already are not).
    """
    return Upload(api, folder, on_progress, home=home)


def _counting(opener: Opener, sizes: dict[str, int], on_progress: Progress) -> Opener:
    """``opener``, also telling ``on_progress`` of each chunk the server asks for.

    ``sizes``: blob hex digest → size. Asks come on several threads at once.
    """
    total, sent = sum(sizes.values()), 0
    lock = threading.Lock()
    on_progress(0, total)

    def counted(rel: str, attachment: bytes | None, payload: bytes) -> Any:
        nonlocal sent
        opened = opener(rel, attachment, payload)
        size = sizes.get(rel.rsplit("/", 1)[-1])
        if opened is not None and size is not None:
            try:
                offset, length = (int(x) for x in opened[1].split(b":"))
            except ValueError:
                return opened  # the blob server answers it as malformed
            with lock:
                sent += max(0, min(length, size - offset))
                on_progress(min(sent, total), total)
        return opened

    return counted
