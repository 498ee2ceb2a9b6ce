"""Images of a node's container tasks: their ids per workflow, and registry credentials.

:class:`ImageIds` resolves an image to its id (``sha256:...``) once per workflow and host;
the server's placement (cache fingerprints) and the local pool share one.
:func:`registry_auth` finds the stored credential for pulling a task's image
(:func:`registry_credential` names it; a remote worker is given it by the server with the
attempt's other secrets). Engine calls
go through ``osmo.runtime.container.engine``.
"""

from __future__ import annotations

import collections
import threading
from collections.abc import Callable, Mapping

from osmo.runtime.container.engine import ContainerEngine
from osmo.runtime.container.run import ContainerError, RegistryAuth, pull_reference

__all__ = ["REGISTRY_PREFIX", "ImageIds", "registry_auth", "registry_credential"]

_KEEP_IMAGE_IDS = 1024  # (workflow, image) → id pairs remembered


REGISTRY_PREFIX = "registry://"
"""A registry's credential is named ``registry://HOST`` (keys ``username``, ``password``)."""


def registry_credential(image: str) -> str:
    """The name of the credential that pulls ``image``.

    ``registry://HOST``, HOST the image's registry (``docker.io`` for short names), like a
    data URL's credential.
    """
    return REGISTRY_PREFIX + pull_reference(image).split("/", 1)[0]


def registry_auth(image: str, lookup: Callable[[str], Mapping[str, str] | None] | None
                  ) -> RegistryAuth | None:
    """The stored credential for pulling ``image``, if there is one (pull only).

    ``lookup``: credential name → payload (keys ``username``, ``password``).
    """
    name = registry_credential(image)
    payload = lookup(name) if lookup is not None else None
    if not payload or "username" not in payload or "password" not in payload:
        return None
    return RegistryAuth(name.removeprefix(REGISTRY_PREFIX), payload["username"],
                        payload["password"])


class ImageIds:
    """Image ids as each workflow first resolved them on this host (thread-safe).

    A workflow's tasks all run the image its tag named when the first of them was placed or
    prepared, and a tag moved meanwhile changes no task of it (the next workflow sees the
    move). Across workflows an id is looked up again only when the engine's image store
    changed (``ContainerEngine.store_stamp``: one ``stat``, where an ``image inspect`` costs
    ≈ 40 ms); an engine with no stamp is asked once per image and workflow.
    """

    def __init__(self, engine: ContainerEngine) -> None:
        self._engine = engine
        self._ids: collections.OrderedDict[tuple[str, str], str] = collections.OrderedDict()
        self._host: collections.OrderedDict[str, tuple[str, object]] = collections.OrderedDict()
        self._lock = threading.Lock()

    def known(self, workflow_id: str, image: str) -> str | None:
        """``image``'s id for ``workflow_id`` if it is on this host (no pull)."""
        found = self._get(workflow_id, image)
        if found is None:
            try:
                found = self._local(image)
            except ContainerError:
                return None
            found = self._put(workflow_id, image, found) if found is not None else None
        return found

    def resolve(self, workflow_id: str, image: str, *, pull: bool,
                auth: RegistryAuth | None, progress: Callable[[str], None]) -> str:
        """``image``'s id for ``workflow_id``, pulling it when missing (and ``pull``).

        Raises:
            ImageError: ``image 'x' not found: <why>``.
        """
        found = self._get(workflow_id, image)
        if found is None:
            try:
                found = self._local(image)
            except ContainerError:
                found = None  # resolve() below says why, as an ImageError
            if found is None:
                found = self._engine.resolve(image, pull=pull, auth=auth, progress=progress).id
            found = self._put(workflow_id, image, found)
        return found

    def _local(self, image: str) -> str | None:
        """``image``'s id on this host now: remembered while the image store is unchanged."""
        stamp = self._engine.store_stamp()  # before the inspect: a change meanwhile shows
        with self._lock:
            hit = self._host.get(image)
        if stamp is not None and hit is not None and hit[1] == stamp:
            return hit[0]
        info = self._engine.image(image)
        if info is not None and stamp is not None:
            with self._lock:
                self._host[image] = (info.id, stamp)
                self._host.move_to_end(image)
                while len(self._host) > _KEEP_IMAGE_IDS:
                    self._host.popitem(last=False)
        return info.id if info is not None else None

    def _get(self, workflow_id: str, image: str) -> str | None:
        with self._lock:
            return self._ids.get((workflow_id, image))

    def _put(self, workflow_id: str, image: str, ident: str) -> str:
        with self._lock:
            ident = self._ids.setdefault((workflow_id, image), ident)
            while len(self._ids) > _KEEP_IMAGE_IDS:
                self._ids.popitem(last=False)
            return ident
