"""Which worker may speak for which attempt: the server's side of worker authorization.

A worker id belongs to the token that registered it (:meth:`WorkerAccess.bind`): it may
register again after a restart, and an id cannot be taken by another token while its worker
is alive. One token may register several ids (the replicas of a Kubernetes pool share one
Secret); they are one trust domain. Every placement the hub sends is
remembered (:meth:`place`), so a report, log batch or secret request is accepted only from
the worker the attempt is placed on (:meth:`placed_on`). A worker reads from the server's
blob server only the inputs its placements listed (:meth:`may_read`); the server reads a
worker's blobs on the channel the worker opened (``osmo.server.workers``).

Every refusal is one log line (``osmo.server.auth.refuse``).
"""

from __future__ import annotations

import threading
from collections import OrderedDict
from collections.abc import Callable, Iterable
from typing import Any

from osmo.errors import OsmoError
from osmo.runtime.choose import container_image
from osmo.runtime.container.images import registry_credential
from osmo.server.auth import refuse
from osmo.spec.model import TaskSpec
from osmo.transport.auth import Identity, Role
from osmo.transport.wire import worker_id
from osmo.worker.secrets import SecretError, gather

__all__ = ["WorkerAccess", "has_secrets", "task_secrets", "task_urls"]

Credential = Callable[[str], dict[str, str] | None]
"""A credential's name or a data URL → its payload (None: there is none)."""

_KEEP_PLACED = 1 << 16  # attempt placements remembered (the engine fences older ones anyway)
_KEEP_GRANTS = 1 << 20  # input blobs remembered per worker


class WorkerAccess:
    """Bindings of tokens to workers, placements and blob grants (see the module docstring).

    Args:
        alive: whether a worker id is alive now (its token seen, its beats on time).
    """

    def __init__(self, alive: Callable[[str], bool]) -> None:
        self._alive = alive
        self._lock = threading.Lock()
        self._owner: dict[str, str] = {}  # worker id -> the token name that registered it
        self._placed: OrderedDict[str, tuple[str, TaskSpec | None]] = OrderedDict()
        self._grants: dict[str, set[str]] = {}  # worker id -> input blobs it may read

    def bind(self, who: Identity, wid: str) -> None:
        """Give worker ``wid`` to ``who``'s token.

        Raises:
            NotAllowed: ``wid`` is a live worker of another token.
        """
        with self._lock:
            owner = self._owner.get(wid)
        if owner not in (None, who.name) and self._alive(wid):
            raise refuse("worker_register", who, f"worker {wid} is registered with another "
                                                 "token and is alive")
        with self._lock:
            self._owner[wid] = who.name

    def speaker(self, verb: str, request: dict[str, Any], who: Identity) -> str:
        """The worker id ``request`` speaks for (its ``id``), if ``who`` registered it.

        Raises:
            UsageError: no valid ``id``.
            NotAllowed: ``who`` did not register it.
        """
        wid = worker_id(request)
        with self._lock:
            ok = self._owner.get(wid) == who.name
        if not ok:
            raise refuse(verb, who, f"token '{who.name}' has not registered worker {wid}")
        return wid

    def place(self, aid: str, wid: str, task: TaskSpec | None,
              inputs: Iterable[str] = ()) -> None:
        """Remember that attempt ``aid`` of ``task`` is placed on ``wid``, reading ``inputs``."""
        with self._lock:
            self._placed[aid] = (wid, task)
            self._placed.move_to_end(aid)
            while len(self._placed) > _KEEP_PLACED:
                self._placed.popitem(last=False)
            grants = self._grants.setdefault(wid, set())
            if len(grants) > _KEEP_GRANTS:
                grants.clear()  # bounded: inputs of attempts long prepared
            grants.update(inputs)

    def restored(self, wid: str, attempts: Iterable[str]) -> None:
        """Attempts the engine says are on ``wid``: restored, or named by a run or kill order.

        Their task is unknown here unless it was placed before.
        """
        with self._lock:
            for aid in attempts:
                if self._placed.get(aid, (None, None))[0] != wid:
                    self._placed[aid] = (wid, None)

    def forget(self, wid: str) -> None:
        """``wid`` is gone: its attempts are lost, none of them is placed on it any more.

        A late report, log batch or secrets request of it is then refused here (if it comes
        back, its registration restores what the engine still places on it).
        """
        with self._lock:
            for aid in [aid for aid, (on, _) in self._placed.items() if on == wid]:
                del self._placed[aid]

    def placed_on(self, verb: str, wid: str, aid: str, who: Identity) -> TaskSpec | None:
        """The task of attempt ``aid`` (None if restored) if it is placed on ``wid``.

        Raises:
            NotAllowed: it is not (the attempt is unaffected).
        """
        with self._lock:
            placed = self._placed.get(aid)
        if placed is None or placed[0] != wid:
            raise refuse(verb, who, f"attempt {aid!r} is not placed on worker {wid}")
        return placed[1]

    def may_read(self, who: Identity | None, digest: str) -> bool:
        """The server's blob server: users and admins read any blob, a worker its inputs."""
        if who is None:
            return False
        if who.role is not Role.WORKER:
            return True
        with self._lock:
            return any(digest in self._grants.get(wid, ()) for wid, name in self._owner.items()
                       if name == who.name)


def task_urls(task: TaskSpec) -> list[str]:
    """The data URLs ``task`` reads or writes (inputs, outputs, checkpoints)."""
    urls = [i.url for i in task.inputs if i.url] + [o.url for o in task.outputs if o.url]
    return urls + [str(c["url"]) for c in task.checkpoint if c.get("url")]


def _registry(task: TaskSpec, credential: Credential, containers: str | None
              ) -> dict[str, dict[str, str]]:
    """The stored credential of ``task``'s image registry, for a worker that pulls it."""
    image = container_image(task, typed=containers == "container") if containers else None
    name = registry_credential(image) if image is not None else None
    payload = credential(name) if name is not None else None
    return {name: payload} if name is not None and payload is not None else {}


def has_secrets(task: TaskSpec, credential: Credential, url_credential: Credential, *,
                containers: str | None) -> bool:
    """Whether a worker must ask for secrets (``task_secrets``) before it prepares ``task``.

    ``containers``: how the worker runs image tasks, so pulls their images: ``container``
    (its own engine, typed tasks' images too), ``kubernetes`` (pods), None (it does not).
    """
    return (bool(task.credentials) or any(url_credential(u) for u in task_urls(task))
            or bool(_registry(task, credential, containers)))


def task_secrets(task: TaskSpec, credential: Credential, url_credential: Credential, *,
                 containers: str | None = None) -> dict[str, Any]:
    """What a worker gets for an attempt of ``task``: its secrets and URL credentials.

    A worker that runs ``task`` in its image (``containers``: as :func:`has_secrets`) also
    gets the stored credential of the registry that image is on (``registry://HOST``), and
    no other registry's.

    Raises:
        OsmoError: a credential it names is gone.
    """
    try:
        values = gather(task, credential) if task.credentials else {}
    except SecretError as exc:
        raise OsmoError(str(exc)) from exc
    values.update(_registry(task, credential, containers))
    return {"secrets": values,
            "url_credentials": {u: c for u in task_urls(task) if (c := url_credential(u))}}
