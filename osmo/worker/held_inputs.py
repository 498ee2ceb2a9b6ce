"""What a remote worker's artifact store holds of the inputs its attempts need.

An attempt's inputs reach a remote worker as manifests (``osmo.transport.wire``); the worker
fetches the blobs it lacks from the server's store by digest (hard links when both share a
host and filesystem) and remembers each manifest it then holds, so that a second attempt
reading the same input — or a task reading an output this worker produced itself — fetches
nothing. The pool finds an input's manifest by the reference :meth:`HeldInputs.fetch`
returned (``artifact:<manifest digest>``). Only the newest manifests are remembered (a
forgotten one is fetched again: nothing is fetched twice that the store still has).
"""

from __future__ import annotations

import collections
import threading

from osmo.artifacts import ArtifactStore, Manifest
from osmo.transport.blobs import SERVER, Asker, SameHost, fetch_manifest

__all__ = ["HeldInputs"]

_REF = "artifact:"  # an input reference of this worker: "artifact:<manifest digest>"


class HeldInputs:
    """The manifests whose blobs ``store`` holds (see the module docstring).

    Args:
        asker: the worker's API client: fetches from the server's blob server, sealed.
        store: the worker's artifact store.
        keep: how many manifests are remembered.
    """

    def __init__(self, asker: Asker, store: ArtifactStore, keep: int = 4096) -> None:
        self._asker, self._store, self._keep = asker, store, keep
        self._lock = threading.Lock()
        self._manifests: collections.OrderedDict[str, Manifest] = collections.OrderedDict()

    def holds(self, manifest: Manifest) -> bool:
        """Whether ``manifest``'s blobs are known to be in the store."""
        with self._lock:
            return manifest.digest in self._manifests

    def fetch(self, manifest: Manifest, same_host: SameHost | None) -> str:
        """Make the store hold ``manifest``'s blobs; the reference the pool knows it by."""
        if not self.holds(manifest):
            fetch_manifest(self._asker, SERVER, manifest, self._store, same_host=same_host)
        self.hold(manifest)
        return f"{_REF}{manifest.digest}"

    def hold(self, manifest: Manifest) -> None:
        """Remember that the store holds ``manifest``'s blobs (the newest kept)."""
        with self._lock:
            self._manifests[manifest.digest] = manifest
            self._manifests.move_to_end(manifest.digest)
            while len(self._manifests) > self._keep:
                self._manifests.popitem(last=False)

    def snapshot(self) -> list[Manifest]:
        """The manifests remembered, oldest first."""
        with self._lock:
            return list(self._manifests.values())

    def forget(self, digests: list[str]) -> None:
        """Stop remembering these manifests (their blobs may be removed next)."""
        with self._lock:
            for digest in digests:
                self._manifests.pop(digest, None)

    def manifest_of(self, ref: str) -> Manifest | None:
        """The manifest behind a reference :meth:`fetch` returned (None if not one)."""
        if not ref.startswith(_REF):
            return None
        with self._lock:
            return self._manifests.get(ref[len(_REF):])
